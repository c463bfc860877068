// The elementwise part of the state a self-fed step feeds back (stm.model.feedback_state), forward and backward,
// in plain loops over a step's rows (rows.h's step blocks) instead of two dozen small ATen calls per step: the same
// arithmetic, operation for operation (the clamps, masks, straight-through rounding, the centring x = s - mean, and
// backward the Jacobian's sum over the tip's three coordinates in ATen's order), so the results are bitwise those
// of the calls they replace. The tip's kinematics stay ATen products (self_fed.cpp).
#pragma once

#include <ATen/ATen.h>

namespace stm_cpp {

constexpr int64_t JOINTS = 7;

// q = clamp(q_prev + pred[:7], lower, upper) and mask_q, where the clamp passes the gradient; into x (the step's
// centred input) the joint columns q - q_prev and, where mask_g is defined, the gripper's straight-through
// rounding of clamp(pred[7], 0, 1) (mask_g: where pred[7] was within [0, 1]). lower, upper (K, B, 7) and mean
// (K, B, D) may be broadcast blocks.
void fed_joints(const at::Tensor& q_prev, const at::Tensor& pred, const at::Tensor& lower, const at::Tensor& upper,
                const at::Tensor& mean, const at::Tensor& q, const at::Tensor& mask_q, const at::Tensor& x,
                const at::Tensor& mask_g);
// Into x from column phi_start: phi (phi_src, plus offset where defined) and psi, centred.
void fed_context(const at::Tensor& phi_src, const at::Tensor& offset, const at::Tensor& psi, const at::Tensor& mean,
                 int64_t phi_start, const at::Tensor& x);
// Backward from dx (the step's input gradient) and gq (the gradient of the q the step left; undefined: none):
// the new gq (the gradient of q_prev), and the gradient of the head's outputs into dout (zeros where nothing
// lands): the prediction's columns [dz (7), gripper, free phi] at the chosen component's mean (idx, MDN head with
// `mixtures` > 0) or as they are. jac (K, B, 21): d tip / d q (undefined: free phi, phi_dim columns of dx passed
// through).
void fed_backward(const at::Tensor& dx, const at::Tensor& gq, const at::Tensor& jac, const at::Tensor& mask_q,
                  const at::Tensor& mask_g, const at::Tensor& idx, int64_t phi_start, int64_t phi_dim,
                  int64_t mixtures, int64_t dims, const at::Tensor& gq_new, const at::Tensor& dout);

}  // namespace stm_cpp
