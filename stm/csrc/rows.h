// Step blocks for the C++ steps' plain loops: a (K, B, X) tensor whose last dimension is contiguous, its K and B
// strides free (a step's slice of a buffer of all steps, or a broadcast constant: stride 0). (The build is keyed
// on the sources only: edit a .cpp that includes this with it.)
#pragma once

#include <ATen/ATen.h>

#include <cstring>

namespace stm_cpp {

// A step block's rows: row (k, b) starts at p + k * sk + b * sb.
template <typename T>
struct Rows {
  T* p = nullptr;
  int64_t sk = 0, sb = 0;
  T* at(int64_t k, int64_t b) const { return p + k * sk + b * sb; }
};

// Where a step block lies, without a tensor view of it (a view is a heap-allocated TensorImpl: per step and
// layer, a dozen of them cost more than the loops they feed): a (K, B, X) tensor as it is (undefined: none), or
// a slice of a buffer of steps (`slice`). It holds no reference: the tensor must outlive it.
struct Block {
  void* data = nullptr;
  at::ScalarType dtype = at::kFloat;
  int64_t sk = 0, sb = 0;

  Block() = default;
  Block(const at::Tensor& t) {  // NOLINT(google-explicit-constructor): a tensor is a block as it is
    if (!t.defined()) return;
    TORCH_CHECK(t.dim() == 3 && (t.stride(2) == 1 || t.size(2) == 1),
                "a step block is (K, B, X), its last dimension contiguous");
    data = t.data_ptr();
    dtype = t.scalar_type();
    sk = t.stride(0);
    sb = t.stride(1);
  }
};

// The step block at `index` along `dim` (0, 1 or 2) of a 4-d buffer whose other two leading dimensions are K, B
// (in that order), from column `col` of its last, contiguous, dimension.
inline Block slice(const at::Tensor& buf, int64_t dim, int64_t index, int64_t col = 0) {
  TORCH_CHECK(buf.dim() == 4 && buf.stride(3) == 1 && dim >= 0 && dim < 3 && index >= 0 && index < buf.size(dim) &&
                  col >= 0 && col < buf.size(3),
              "slice: a step of a (., ., ., X) buffer");
  Block b;
  b.dtype = buf.scalar_type();
  b.data = static_cast<char*>(buf.data_ptr()) + (index * buf.stride(dim) + col) * buf.element_size();
  const int64_t first = dim == 0 ? 1 : 0, second = dim == 2 ? 1 : 2;
  b.sk = buf.stride(first);
  b.sb = buf.stride(second);
  return b;
}

template <typename T>
Rows<T> rows(const Block& b) {
  TORCH_CHECK(b.data == nullptr || b.dtype == c10::CppTypeToScalarType<T>::value, "a step block of another dtype");
  return {static_cast<T*>(b.data), b.sk, b.sb};
}

// The block's columns from `col` on (a view of the same rows).
inline Block at_col(Block b, int64_t col) {
  if (b.data != nullptr) b.data = static_cast<char*>(b.data) + col * static_cast<int64_t>(c10::elementSize(b.dtype));
  return b;
}

// X columns of every row of src into dst (K, B rows): a copy, without an ATen copy's views and iterator set-up.
inline void copy_rows(const Block& src, const Block& dst, int64_t K, int64_t B, int64_t X) {
  TORCH_CHECK(src.dtype == dst.dtype, "copy_rows: blocks of one dtype");
  const int64_t size = static_cast<int64_t>(c10::elementSize(src.dtype)), row = X * size;
  for (int64_t k = 0; k < K; ++k) {
    for (int64_t b = 0; b < B; ++b) {
      std::memcpy(static_cast<char*>(dst.data) + (k * dst.sk + b * dst.sb) * size,
                  static_cast<const char*>(src.data) + (k * src.sk + b * src.sb) * size, row);
    }
  }
}

}  // namespace stm_cpp
