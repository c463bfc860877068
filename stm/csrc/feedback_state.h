// The elementwise part of the state a self-fed step feeds back (stm.model.feedback_state), forward and backward,
// in plain loops over a step's rows (rows.h's step blocks) instead of two dozen small ATen calls per step: the same
// arithmetic, operation for operation (the clamps, masks, straight-through rounding, the centring x = s - mean, and
// backward the Jacobian's sum over the tip's three coordinates in ATen's order), so the results are bitwise those
// of the calls they replace. The tip's kinematics stay ATen products (self_fed.cpp).
#pragma once

#include <ATen/ATen.h>

#include "rows.h"

namespace stm_cpp {

constexpr int64_t JOINTS = 7;

// q = clamp(q_prev + pred[:7], lower, upper) and mask_q, where the clamp passes the gradient; into x (the step's
// centred input) the joint columns q - q_prev and, where mask_g is defined, the gripper's straight-through
// rounding of clamp(pred[7], 0, 1) (mask_g: where pred[7] was within [0, 1]). lower, upper (K, B, 7) and mean
// (K, B, D) may be broadcast blocks.
void fed_joints(const Block& q_prev, const at::Tensor& pred, const Block& lower, const Block& upper,
                const Block& mean, const Block& q, const Block& mask_q, const Block& x, const Block& mask_g);
// Into x from column phi_start: phi (phi_src, plus offset where given) and psi (psi_dim columns), centred.
void fed_context(const at::Tensor& phi_src, const Block& offset, const Block& psi, int64_t psi_dim, const Block& mean,
                 int64_t phi_start, const Block& x);
// Backward from dx (the step's input gradient) and gq (the gradient of the q the step left; none: zero):
// the new gq (the gradient of q_prev), and the gradient of the head's outputs into dout (zeros where nothing
// lands): the prediction's columns [dz (7), gripper, free phi] at the chosen component's mean (idx, MDN head with
// `mixtures` > 0) or as they are. jac (K, B, 21): d tip / d q (none: free phi, phi_dim columns of dx passed
// through).
void fed_backward(const Block& dx, const Block& gq, const Block& jac, const Block& mask_q, const Block& mask_g,
                  const Block& idx, int64_t phi_start, int64_t phi_dim, int64_t mixtures, int64_t dims,
                  const at::Tensor& gq_new, const Block& dout);

// The tip kinematics' monomials (stm.fk._slots): mono[r, s] = prod over d < degree of factors[r, index[d * S + s]]
// (S = index's length / degree), multiplied in d's order as ATen's prod over that dimension does; one loop for
// factors.index_select(1, index).view(N, degree, S).prod(1).
at::Tensor monomial_products(const at::Tensor& factors, const at::Tensor& index, int64_t degree);

}  // namespace stm_cpp
