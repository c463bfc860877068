// The C++ steps' transcendental functions: see vec_math.h. (Edit this file with the header: the build is keyed on
// the sources only.)
#include "vec_math.h"

#include <ATen/Version.h>

#include <cmath>
#include <cstdint>
#include <immintrin.h>

// SLEEF's vector exp and MKL's VML, as linked into libtorch; weak: absent elsewhere (null), and there ATen runs.
// (The vector types need the ISA only in the functions that use them: target attributes below.)
#pragma GCC push_options
#pragma GCC target("avx512f,avx2,fma")
extern "C" {
__m512 Sleef_expf16_u10(__m512) __attribute__((weak));
__m256 Sleef_expf8_u10(__m256) __attribute__((weak));
}
#pragma GCC pop_options
extern "C" {
void vmsTanh(int64_t n, const float* a, float* r, int64_t mode) __attribute__((weak));
void vmsSin(int64_t n, const float* a, float* r, int64_t mode) __attribute__((weak));
}

namespace stm_cpp {
namespace {

constexpr int64_t VML_MODE = 0x2 | 0x140000 | 0x100;  // VML_HA | VML_FTZDAZ_OFF | VML_ERRMODE_IGNORE, as at::vml

enum class Isa { none, avx2, avx512 };

// The vector width ATen's kernels dispatch to (ATEN_CPU_CAPABILITY can lower it), where SLEEF is linked in.
Isa sigmoid_isa() {
  static const Isa isa = [] {
    const auto cap = at::get_cpu_capability();
    if (cap == "AVX512" && Sleef_expf16_u10 != nullptr) return Isa::avx512;
    if (cap == "AVX2" && Sleef_expf8_u10 != nullptr) return Isa::avx2;
    return Isa::none;
  }();
  return isa;
}

// ATen's sigmoid kernel on n contiguous floats: two vectors at a time 1 / (1 + exp(0 - x)), the rest (fewer than
// two vectors) in scalar code, 1 / (1 + std::exp(-x)).
inline void sigmoid_tail(float* x, int64_t i, int64_t n) {
  for (; i < n; ++i) x[i] = 1.0F / (1.0F + std::exp(-x[i]));
}

__attribute__((target("avx512f"))) void sigmoid_avx512(float* x, int64_t n) {
  const __m512 one = _mm512_set1_ps(1.0F), zero = _mm512_set1_ps(0.0F);
  int64_t i = 0;
  for (; i <= n - 32; i += 32) {
    for (int64_t h = 0; h < 32; h += 16) {
      const __m512 e = Sleef_expf16_u10(_mm512_sub_ps(zero, _mm512_loadu_ps(x + i + h)));
      _mm512_storeu_ps(x + i + h, _mm512_div_ps(one, _mm512_add_ps(e, one)));
    }
  }
  sigmoid_tail(x, i, n);
}

__attribute__((target("avx2,fma"))) void sigmoid_avx2(float* x, int64_t n) {
  const __m256 one = _mm256_set1_ps(1.0F), zero = _mm256_set1_ps(0.0F);
  int64_t i = 0;
  for (; i <= n - 16; i += 16) {
    for (int64_t h = 0; h < 16; h += 8) {
      const __m256 e = Sleef_expf8_u10(_mm256_sub_ps(zero, _mm256_loadu_ps(x + i + h)));
      _mm256_storeu_ps(x + i + h, _mm256_div_ps(one, _mm256_add_ps(e, one)));
    }
  }
  sigmoid_tail(x, i, n);
}

at::Tensor flat(const void* p, int64_t n, at::ScalarType dt) {
  return at::from_blob(const_cast<void*>(p), {n}, at::TensorOptions().dtype(dt));
}

}  // namespace

void sigmoid_block(const Block& b, int64_t K, int64_t B, int64_t X) {
  const Isa isa = b.dtype == at::kFloat ? sigmoid_isa() : Isa::none;
  // TensorIterator's innermost run: X, then B and K where their strides continue it (size-1 dimensions vanish)
  int64_t run = X, rows_b = B, rows_k = K;
  const bool b_joins = B == 1 || b.sb == X;
  if (b_joins) {
    run *= B;
    rows_b = 1;
    if (K == 1 || b.sk == run) {
      run *= K;
      rows_k = 1;
    }
  }
  const bool ordered = b_joins || K == 1 || b.sk >= b.sb;  // else ATen would iterate K innermost
  if (isa == Isa::none || !ordered) {
    at::from_blob(b.data, {K, B, X}, {b.sk, b.sb, 1}, at::TensorOptions().dtype(b.dtype)).sigmoid_();
    return;
  }
  const auto r = rows<float>(b);
  for (int64_t k = 0; k < rows_k; ++k) {
    for (int64_t i = 0; i < rows_b; ++i) {
      if (isa == Isa::avx512) sigmoid_avx512(r.at(k, i), run);
      else sigmoid_avx2(r.at(k, i), run);
    }
  }
}

void tanh_into(const void* in, void* out, int64_t n, at::ScalarType dt) {
  if (dt == at::kFloat && vmsTanh != nullptr) {
    vmsTanh(n, static_cast<const float*>(in), static_cast<float*>(out), VML_MODE);
    return;
  }
  auto o = flat(out, n, dt);
  at::tanh_out(o, flat(in, n, dt));
}

void sin_into(const void* in, void* out, int64_t n, at::ScalarType dt) {
  if (dt == at::kFloat && vmsSin != nullptr) {
    vmsSin(n, static_cast<const float*>(in), static_cast<float*>(out), VML_MODE);
    return;
  }
  auto o = flat(out, n, dt);
  at::sin_out(o, flat(in, n, dt));
}

}  // namespace stm_cpp
