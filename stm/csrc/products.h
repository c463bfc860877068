// The C++ steps' matrix products on raw memory (edit with products.cpp: the build is keyed on the sources only).
//
// Per step and layer an ATen product costs more in dispatch, views and checks than its arithmetic at these sizes;
// `gemm` issues BLAS's gemm (sgemm_, dgemm_: the routine ATen's CPU products call) with the arguments ATen's addmm
// and bmm pass it for the same operands (the same transposition and leading dimensions), so its results are those
// of at::bmm / baddbmm / mm / addmm bit for bit, and takes ATen's own call where BLAS is not linked in, or where a
// TorchDispatchMode watches the dispatcher (stm.speed.floor records an iteration's products so).
// bf16 products (`low_bmm`): MKL's bf16 x bf16 -> float32 GEMM where libtorch carries it.
#pragma once

#include <ATen/ATen.h>

#include "rows.h"

namespace stm_cpp {

// A (K, R, C) matrix per model in memory: element (k, r, c) at p + k * sk + r * sr + c * sc (in elements). It holds
// no reference: the memory must outlive it.
struct Mat {
  void* p = nullptr;
  at::ScalarType dtype = at::kFloat;
  int64_t K = 0, R = 0, C = 0, sk = 0, sr = 0, sc = 0;

  Mat() = default;
  Mat(const at::Tensor& t);  // NOLINT(google-explicit-constructor): a 3-d tensor (a 2-d one: K = 1) as it lies
  Mat(const Block& b, int64_t K, int64_t B, int64_t X);  // a (K, B, X) step block
  Mat(void* p, at::ScalarType dt, int64_t K, int64_t R, int64_t C, int64_t sk, int64_t sr, int64_t sc)
      : p(p), dtype(dt), K(K), R(R), C(C), sk(sk), sr(sr), sc(sc) {}
  Mat t() const;                                   // the transpose of each model's matrix (a view)
  Mat cols(int64_t from, int64_t n) const;         // columns [from, from + n)
  Mat rows(int64_t from, int64_t n) const;         // rows [from, from + n)
  at::Tensor tensor() const;                       // an ATen view of it (the fallbacks)
};

// A (K, ..., X) tensor's rows as (K, N, X): its middle dimensions merged (they must be, as a view would).
Mat rows_of(const at::Tensor& t);

// out = beta out + a @ b for each model (beta 0: out's contents are not read).
void gemm(const Mat& out, const Mat& a, const Mat& b, double beta = 0.0);

// bf16 products (TrainConfig.matmul_dtype "bfloat16"): out (K, M, N) float32, its rows contiguous, = a @ b, or
// += with accumulate; a (K, M, P), b (K, P, N) bfloat16, transposed views taken as they are. Through MKL's
// bf16 x bf16 -> float32 GEMM where libtorch carries it (float32 accumulation and result: no bf16 rounding of
// the output, which ATen's bf16 product rounds, and less time); else ATen's bf16 product, added or copied.
void low_bmm(const Mat& out, const Mat& a, const Mat& b, bool accumulate);
// a @ b into a new float32 tensor: gemm for float32 operands, low_bmm for bfloat16 ones.
at::Tensor product(const Mat& a, const Mat& b);

}  // namespace stm_cpp
