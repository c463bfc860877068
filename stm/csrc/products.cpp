// The C++ steps' matrix products: see products.h. (Edit this file with the header: the build is keyed on the
// sources only.)
#include "products.h"

#include <c10/core/impl/TorchDispatchModeTLS.h>

#include <algorithm>
#include <climits>
#include <cstdint>
#include <utility>
#include <vector>

// BLAS's gemm (column-major, Fortran calling convention) and MKL's bf16 GEMM (row-major CBLAS), in the BLAS that
// libtorch links in; weak: absent where it links none (null), and there ATen's products run.
extern "C" {
void sgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const float* alpha,
            const float* a, const int* lda, const float* b, const int* ldb, const float* beta, float* c,
            const int* ldc) __attribute__((weak));
void dgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const double* alpha,
            const double* a, const int* lda, const double* b, const int* ldb, const double* beta, double* c,
            const int* ldc) __attribute__((weak));
void cblas_gemm_bf16bf16f32(int layout, int trans_a, int trans_b, int m, int n, int k, float alpha, const uint16_t* a,
                            int lda, const uint16_t* b, int ldb, float beta, float* c, int ldc)
    __attribute__((weak));
}

namespace stm_cpp {

Mat::Mat(const at::Tensor& t) {
  TORCH_CHECK(t.dim() == 3 || t.dim() == 2, "a matrix per model: (K, R, C) or (R, C)");
  const int64_t o = t.dim() - 2;
  p = t.data_ptr();
  dtype = t.scalar_type();
  K = o ? t.size(0) : 1;
  sk = o ? t.stride(0) : 0;
  R = t.size(o);
  C = t.size(o + 1);
  sr = t.stride(o);
  sc = t.stride(o + 1);
}

Mat::Mat(const Block& b, int64_t K_, int64_t B, int64_t X)
    : p(b.data), dtype(b.dtype), K(K_), R(B), C(X), sk(b.sk), sr(b.sb), sc(1) {}

Mat Mat::t() const {
  Mat m = *this;
  std::swap(m.R, m.C);
  std::swap(m.sr, m.sc);
  return m;
}

Mat Mat::cols(int64_t from, int64_t n) const {
  TORCH_CHECK(from >= 0 && from + n <= C, "Mat::cols: out of range");
  Mat m = *this;
  m.p = static_cast<char*>(p) + from * sc * c10::elementSize(dtype);
  m.C = n;
  return m;
}

Mat Mat::rows(int64_t from, int64_t n) const { return t().cols(from, n).t(); }

at::Tensor Mat::tensor() const {
  return at::from_blob(p, {K, R, C}, {sk, sr, sc}, at::TensorOptions().dtype(dtype));
}

Mat rows_of(const at::Tensor& t) {
  const int64_t d = t.dim();
  TORCH_CHECK(d >= 3 && t.stride(d - 1) == 1, "rows_of: a (K, ..., X) tensor, its rows contiguous");
  int64_t N = 1;
  for (int64_t i = 1; i < d - 1; ++i) {
    TORCH_CHECK(i == d - 2 || t.size(i + 1) == 1 || t.stride(i) == t.stride(i + 1) * t.size(i + 1),
                "rows_of: middle dimensions that merge");
    N *= t.size(i);
  }
  return Mat(t.data_ptr(), t.scalar_type(), t.size(0), N, t.size(d - 1), t.stride(0), t.stride(d - 2), 1);
}

namespace {

// One model's matrix as ATen's addmm sees it: sizes and strides of its two dimensions.
struct Matrix {
  const void* p;
  int64_t size[2], stride[2];
};

Matrix matrix(const Mat& m, int64_t k) {
  return {static_cast<const char*>(m.p) + k * m.sk * c10::elementSize(m.dtype), {m.R, m.C}, {m.sr, m.sc}};
}

// The arguments ATen's addmm_impl_cpu_ and cpublas::gemm give BLAS for result = m1 @ m2 (column-major: where the
// result's rows are contiguous it computes the transpose, m2^T m1^T); false where ATen would copy an operand
// first (neither dimension unit-stride) or not call BLAS (cpublas's use_blas_gemm).
struct Call {
  char ta = 'n', tb = 'n';
  int m = 0, n = 0, k = 0, lda = 0, ldb = 0, ldc = 0;
  const void *a = nullptr, *b = nullptr;
};

bool blas_call(Matrix res, Matrix m1, Matrix m2, Call& call) {
  bool tc = false;
  if (res.stride[0] == 1 && (res.size[1] == 1 || res.stride[1] >= std::max<int64_t>(1, res.size[0]))) {
    tc = false;
  } else if (res.stride[1] == 1 && (res.size[0] == 1 || res.stride[0] >= std::max<int64_t>(1, res.size[1]))) {
    std::swap(m1, m2);
    tc = true;
  } else {
    return false;
  }
  const int64_t m = res.size[tc ? 1 : 0], n = res.size[tc ? 0 : 1], k = m1.size[tc ? 0 : 1];
  const int i0 = tc ? 1 : 0, i1 = tc ? 0 : 1;
  bool ta = false, tb = false;
  if (m1.stride[i0] == 1 && m1.stride[i1] >= std::max<int64_t>(1, m)) ta = false;
  else if (m1.stride[i1] == 1 && m1.stride[i0] >= std::max<int64_t>(1, k)) ta = true;
  else return false;
  if (m2.stride[i0] == 1 && m2.stride[i1] >= std::max<int64_t>(1, k)) tb = false;
  else if (m2.stride[i1] == 1 && m2.stride[i0] >= std::max<int64_t>(1, n)) tb = true;
  else return false;
  int64_t lda = m1.stride[(ta == tc) ? 1 : 0], ldb = m2.stride[(tb == tc) ? 1 : 0];
  int64_t ldc = res.stride[tc ? 0 : 1];
  // cpublas's normalize_last_dims
  if (n == 1) ldc = m;
  if (ta) {
    if (m == 1) lda = k;
  } else if (k == 1) {
    lda = m;
  }
  if (tb) {
    if (k == 1) ldb = n;
  } else if (n == 1) {
    ldb = k;
  }
  // cpublas's use_blas_gemm
  const bool fits = m <= INT_MAX && n <= INT_MAX && k <= INT_MAX && lda <= INT_MAX && ldb <= INT_MAX && ldc <= INT_MAX;
  if (!fits || lda < std::max<int64_t>(1, ta ? k : m) || ldb < std::max<int64_t>(1, tb ? n : k) ||
      ldc < std::max<int64_t>(1, m))
    return false;
  call.ta = ta ? 't' : 'n';
  call.tb = tb ? 't' : 'n';
  call.m = static_cast<int>(m);
  call.n = static_cast<int>(n);
  call.k = static_cast<int>(k);
  call.lda = static_cast<int>(lda);
  call.ldb = static_cast<int>(ldb);
  call.ldc = static_cast<int>(ldc);
  call.a = m1.p;
  call.b = m2.p;
  return true;
}

template <typename T, typename Gemm>
bool blas_gemm(Gemm* routine, const Mat& out, const Mat& a, const Mat& b, double beta) {
  if (routine == nullptr) return false;
  std::vector<Call> calls(out.K);
  for (int64_t k = 0; k < out.K; ++k)
    if (!blas_call(matrix(out, k), matrix(a, k), matrix(b, k), calls[k])) return false;
  const T one = T(1), bt = static_cast<T>(beta);
  for (int64_t k = 0; k < out.K; ++k) {
    const Call& c = calls[k];
    routine(&c.ta, &c.tb, &c.m, &c.n, &c.k, &one, static_cast<const T*>(c.a), &c.lda, static_cast<const T*>(c.b),
            &c.ldb, &bt, static_cast<T*>(static_cast<void*>(static_cast<char*>(out.p) + k * out.sk * sizeof(T))),
            &c.ldc);
  }
  return true;
}

}  // namespace

void gemm(const Mat& out, const Mat& a, const Mat& b, double beta) {
  TORCH_CHECK(a.K == out.K && b.K == out.K && a.R == out.R && b.C == out.C && a.C == b.R && a.dtype == out.dtype &&
                  b.dtype == out.dtype,
              "gemm: (K, M, P) @ (K, P, N) into (K, M, N) of one dtype");
  if (out.K == 0 || out.R == 0 || out.C == 0) return;
  // Under a TorchDispatchMode (stm.speed.floor's recorder of an iteration's products, or any other mode that watches
  // the dispatcher) ATen's call runs, which the mode sees; BLAS's it would not. The same results either way.
  if (a.C > 0 && !c10::impl::TorchDispatchModeTLS::any_modes_set()) {
    if (out.dtype == at::kFloat && blas_gemm<float>(sgemm_, out, a, b, beta)) return;
    if (out.dtype == at::kDouble && blas_gemm<double>(dgemm_, out, a, b, beta)) return;
  }
  auto res = out.tensor();
  if (beta == 0.0) at::bmm_out(res, a.tensor(), b.tensor());
  else at::baddbmm_out(res, res, a.tensor(), b.tensor(), beta);
}

namespace {

constexpr int CBLAS_ROW_MAJOR = 101, CBLAS_NO_TRANS = 111, CBLAS_TRANS = 112;

// A bf16 operand as a row-major matrix per model: (memory, transposed, leading dimension); a contiguous copy only
// where neither of its last two dimensions is unit-stride.
struct Operand {
  at::Tensor copy;  // holds a copy's memory
  const uint16_t* p = nullptr;
  int64_t sk = 0, ld = 0;
  bool trans = false;
};

Operand operand(const Mat& m) {
  Operand o;
  o.p = static_cast<const uint16_t*>(m.p);
  o.sk = m.sk;
  if (m.sc == 1 && m.sr >= std::max<int64_t>(m.C, 1)) {
    o.ld = m.sr;
  } else if (m.sr == 1 && m.sc >= std::max<int64_t>(m.R, 1)) {
    o.trans = true;
    o.ld = m.sc;
  } else {
    o.copy = m.tensor().contiguous();
    o.p = static_cast<const uint16_t*>(o.copy.data_ptr());
    o.sk = m.R * m.C;
    o.ld = m.C;
  }
  return o;
}

}  // namespace

void low_bmm(const Mat& out, const Mat& a, const Mat& b, bool accumulate) {
  TORCH_CHECK(a.dtype == at::kBFloat16 && b.dtype == at::kBFloat16 && out.dtype == at::kFloat && out.sc == 1 &&
                  a.K == out.K && b.K == out.K && a.R == out.R && b.C == out.C && a.C == b.R,
              "low_bmm: bf16 (K, M, P) @ (K, P, N) into float32 (K, M, N) rows");
  const int64_t K = out.K, M = out.R, N = out.C, P = a.C;
  if (cblas_gemm_bf16bf16f32 == nullptr) {  // ATen's bf16 product, its output rounded to bf16
    const auto p = at::bmm(a.tensor(), b.tensor());
    auto res = out.tensor();
    if (accumulate) res.add_(p);
    else res.copy_(p);
    return;
  }
  const auto oa = operand(a), ob = operand(b);
  auto* pc = static_cast<float*>(out.p);
  const int64_t ldc = std::max<int64_t>(out.sr, std::max<int64_t>(N, 1));
  for (int64_t k = 0; k < K; ++k) {
    cblas_gemm_bf16bf16f32(CBLAS_ROW_MAJOR, oa.trans ? CBLAS_TRANS : CBLAS_NO_TRANS,
                           ob.trans ? CBLAS_TRANS : CBLAS_NO_TRANS, static_cast<int>(M), static_cast<int>(N),
                           static_cast<int>(P), 1.0F, oa.p + k * oa.sk, static_cast<int>(oa.ld), ob.p + k * ob.sk,
                           static_cast<int>(ob.ld), accumulate ? 1.0F : 0.0F, pc + k * out.sk, static_cast<int>(ldc));
  }
}

at::Tensor product(const Mat& a, const Mat& b) {
  const auto dt = a.dtype == at::kBFloat16 ? at::kFloat : a.dtype;
  auto out = at::empty({a.K, a.R, b.C}, at::TensorOptions().dtype(dt));
  if (a.dtype == at::kBFloat16) low_bmm(out, a, b, false);
  else gemm(out, a, b);
  return out;
}

}  // namespace stm_cpp
