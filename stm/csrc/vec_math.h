// The C++ steps' transcendental functions on raw memory, as ATen computes them (edit with vec_math.cpp: the build is
// keyed on the sources only): per step and layer an ATen call costs more than the function on a few thousand
// floats. float32 takes the routines ATen's CPU kernels call, in the same arrangement, so the results are ATen's bit
// for bit: sigmoid as ATen's vectorised kernel (SLEEF's exp at the vector width ATen dispatches to, its scalar tail
// with std::exp), tanh and sin through MKL's VML (the same mode as ATen's at::vml). Elsewhere (another dtype or
// CPU, or a libtorch without them) ATen's own call runs. As ATen on one thread: with several, ATen splits its loops
// where it likes, and its sigmoid's scalar tails move with the splits.
#pragma once

#include <ATen/ATen.h>

#include "rows.h"

namespace stm_cpp {

// sigmoid in place on a (K, B, X) step block, as at::sigmoid_ on a tensor with its strides.
void sigmoid_block(const Block& b, int64_t K, int64_t B, int64_t X);
// out = tanh(in) / sin(in) over n contiguous elements of dtype dt (in and out may be the same memory).
void tanh_into(const void* in, void* out, int64_t n, at::ScalarType dt);
void sin_into(const void* in, void* out, int64_t n, at::ScalarType dt);

}  // namespace stm_cpp
