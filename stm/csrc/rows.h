// Step blocks for the C++ steps' plain loops: a (K, B, X) tensor whose last dimension is contiguous, its K and B
// strides free (a step's slice of a buffer of all steps, or a broadcast constant: stride 0). (The build is keyed
// on the sources only: edit a .cpp that includes this with it.)
#pragma once

#include <ATen/ATen.h>

namespace stm_cpp {

// A step block's rows: row (k, b) starts at p + k * sk + b * sb.
template <typename T>
struct Rows {
  T* p = nullptr;
  int64_t sk = 0, sb = 0;
  T* at(int64_t k, int64_t b) const { return p + k * sk + b * sb; }
};

// The rows of t (K, B, X), last dimension contiguous; undefined t: none (p null).
template <typename T>
Rows<T> rows(const at::Tensor& t) {
  if (!t.defined()) return {};
  TORCH_CHECK(t.dim() == 3 && (t.stride(2) == 1 || t.size(2) == 1),
              "a step block is (K, B, X), its last dimension contiguous");
  return {t.data_ptr<T>(), t.stride(0), t.stride(1)};
}

}  // namespace stm_cpp
