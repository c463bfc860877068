// What a self-fed step feeds back, in plain loops over a step's rows (rows.h's step blocks) and BLAS products
// (products.h), forward and backward: the feedback head's pick of a mixture component (stm.mdn.component_mean),
// the fed-back state's elementwise part (stm.model.feedback_state) and the tip's kinematics (stm.fk) instead of
// some sixty small ATen calls per step. The same arithmetic, operation for operation (the argmax and gather, the
// clamps, masks, straight-through rounding, the centring x = s - mean, the kinematics' products and sine as ATen
// computes them, and backward the Jacobian's sum over the tip's three coordinates in ATen's order), so the results
// are bitwise those of the calls they replace.
#pragma once

#include <ATen/ATen.h>

#include <vector>

#include "products.h"
#include "rows.h"

namespace stm_cpp {

constexpr int64_t JOINTS = 7;

// An MDN head's feedback (K, B rows of out: m logits, then m means of `dims` columns): the most likely component
// (argmax: the first largest logit, a NaN first) into idx (int64), its mean into pred.
void component_mean(const Block& out, int64_t m, int64_t dims, const Block& idx, const Block& pred, int64_t K,
                    int64_t B);
// q = clamp(q_prev + pred[:7], lower, upper) and mask_q, where the clamp passes the gradient; into x (the step's
// centred input) the joint columns q - q_prev and, where mask_g is defined, the gripper's straight-through
// rounding of clamp(pred[7], 0, 1) (mask_g: where pred[7] was within [0, 1]). lower, upper (K, B, 7) and mean
// (K, B, D) may be broadcast blocks.
void fed_joints(const Block& q_prev, const Block& pred, const Block& lower, const Block& upper, const Block& mean,
                const Block& q, const Block& mask_q, const Block& x, const Block& mask_g, int64_t K, int64_t B);
// Into x from column phi_start: phi (phi_dim columns of phi_src, plus offset where given) and psi (psi_dim
// columns), centred.
void fed_context(const Block& phi_src, int64_t phi_dim, const Block& offset, const Block& psi, int64_t psi_dim,
                 const Block& mean, int64_t phi_start, const Block& x, int64_t K, int64_t B);
// Backward from dx (the step's input gradient) and gq (the gradient of the q the step left; none: zero):
// the new gq (the gradient of q_prev), and the gradient of the head's outputs into dout (zeros where nothing
// lands): the prediction's columns [dz (7), gripper, free phi] at the chosen component's mean (idx, MDN head with
// `mixtures` > 0) or as they are. jac (K, B, 21): d tip / d q (none: free phi, phi_dim columns of dx passed
// through).
void fed_backward(const Block& dx, const Block& gq, const Block& jac, const Block& mask_q, const Block& mask_g,
                  const Block& idx, int64_t phi_start, int64_t phi_dim, int64_t mixtures, int64_t dims,
                  const Block& gq_new, const Block& dout, int64_t K, int64_t B, at::ScalarType dtype);

// The tip's kinematics (stm.fk._slots with the gradient plan) of N joint configurations per call, on scratch made
// once: q (N, 7) rows -> out (N, slots, 3) rows, slot 0 the tip, slot 1 + i its derivative by q_i.
// fk: signs, phases, index, coef, row_sums (stm.fk.TipKinematics); the plan's degree, slots, monomials.
class TipKinematics {
 public:
  TipKinematics(const std::vector<at::Tensor>& fk, int64_t degree, int64_t slots, int64_t monomials, int64_t N);
  void run(const Mat& q, const Mat& out);
  int64_t slots() const { return slots_; }

 private:
  at::Tensor signs_, phases_, index_, coef_, row_sums_;
  int64_t degree_, slots_, monomials_, N_;
  at::Tensor factors_, mono_, entries_, prod_;  // scratch: (N, F), (N, slots * monomials), (N slots, 24), (N slots, 12)
};

}  // namespace stm_cpp
