// The MDN head's mixture negative log-likelihood fused into one pass per row, forward and backward
// (mdn_nll.cpp; stm.mdn_fused wraps it as an autograd function).
#pragma once

#include <ATen/ATen.h>

#include <tuple>

namespace stm_cpp {

std::tuple<at::Tensor, at::Tensor> mdn_nll_forward(const at::Tensor& raw, const at::Tensor& target, int64_t mixtures,
                                                   double sigma_min, bool need_coef);
std::tuple<at::Tensor, at::Tensor> mdn_nll_backward(const at::Tensor& grad, const at::Tensor& raw,
                                                    const at::Tensor& target, const at::Tensor& coef,
                                                    int64_t mixtures, bool need_target);

}  // namespace stm_cpp
