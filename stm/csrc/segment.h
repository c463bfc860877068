// The self-fed steps of the auto-conditioned unroll (stm.autoconditioning), a whole segment of them per call:
// per step the feedback head's prediction, the fed-back state (joint integration, clamping, gripper rounding,
// the tip's forward kinematics) and the L-layer LSTM stack step, forward; and the backward of all of it
// (segment.cpp; self_fed.cpp binds it).
//
// Per step no ATen call: the products go to BLAS as ATen's would (products.h), the gate nonlinearities and the
// tip's sine are computed as ATen computes them (vec_math.h), the rest runs in plain loops over the step's rows
// (lstm_step.h, feedback_state.h), on buffers of the whole segment made once per call (SegLayer, Segment). The
// arithmetic is that of the ATen calls the Python path makes (stm.lstm_step, stm.fk, stm.model.feedback_state), in
// the same order, so the forward is that path's and the backward differs only in the order in which a few gradient
// contributions are summed. The weight gradients are not computed per step: one product per layer and chunk of
// steps (`weight_gradient`), whose rows the steps wrote in place.
//
// bf16 products (TrainConfig.matmul_dtype "bfloat16"; Segment::low): the LSTM stack's and the feedback head's
// products, forward and backward, and the weight gradients take bf16 operands (the weights cast once per unroll, on
// the Python side; [x, h] and d gates per step into bf16 buffers) and give float32 (products.h, low_bmm); the
// state, the gate maths, the fed-back state and the tip's kinematics stay float32.
//
// Shapes: K models of a pack, batch B. h, c per layer (K, B, H); w per layer (K, I + H, 4H) with the gate
// columns i, f, o, 2g; b (K, 1, 4H); the feedback head w_fb (K, H, O), b_fb (K, 1, O).
#pragma once

#include <ATen/ATen.h>

#include <memory>
#include <tuple>
#include <vector>

#include "lstm_step.h"

namespace stm_cpp {

// A layer's values over the segment's n steps, in buffers written step by step (lstm_step.h's step blocks).
// xh holds the rows of the layer's weight gradient, [x, h] per step, in the order the backward visits the steps
// (step j at slot n - 1 - j): the product reads them in place, and the top layer's h part is what the feedback
// head read (the rows of its weight gradient).
struct SegLayer {
  Tensor xh;             // (K, n, B, I + H)
  Tensor xh_low;         // bf16 products: xh in bf16, each step's rows cast before its product
  Tensor sig;            // per step (n, K, B, 4H)
  Cells cells;           // the cell states per step
  int64_t inputs = 0;    // I
};

// What the backward needs of one segment's forward; the Python side holds it between the two.
struct Segment {
  TensorList ws;
  Tensor w_fb;
  TensorList low;  // bf16 products: w_fb, then each layer's w, in bf16 (empty: float32 products)
  Tensor fb_out;   // the feedback head's outputs per step (n, K, B, O), the bias written in before the product
  Tensor preds;    // MDN head: the chosen component's mean per step (n, K, B, dims)
  Tensor idx;      // MDN head: the chosen component per step (n, K, B, 1), int64
  Tensor kin;      // grounded phi: the tip kinematics' rows per step (n, K, B, slots x 3): the tip, its Jacobian
  std::vector<SegLayer> layers;
  Tensor qs;      // the fed-back q per step (n, K, B, JOINTS): the forward's, one block per step
  Tensor mask_q;  // where q_prev + dq was within the joint limits (clamp passes the gradient) (n, K, B, JOINTS)
  Tensor mask_g;  // where the gripper prediction was within [0, 1] (n, K, B, 1)
  int64_t n = 0, K = 0, B = 0, H = 0, mixtures = 0, dims = 0, phi_start = 0, phi_dim = 0, slots = 0;
  bool gripper = false, free_phi = false, detach = false;
  int64_t slot(int64_t j) const { return n - 1 - j; }
};

// ints: degree, slots, monomials (the FK plan), mixtures (0: deterministic head), dims (prediction columns
// used), gripper, free_phi, phi_start, phi_dim, detach. Returns the top hidden states (K, B, n, H) and each layer's
// h, c after the last step.
std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Segment>> segment_forward(
    TensorList h, TensorList c, const TensorList& ws, const TensorList& bs, const Tensor& w_fb, const Tensor& b_fb,
    const Tensor& q0, const Tensor& psi, const Tensor& phi_offset, const Tensor& mean, const Tensor& lower,
    const Tensor& upper, const TensorList& fk, const std::vector<int64_t>& ints, const TensorList& low);

// Gradients of the segment's inputs from those of its outputs (undefined where none reached them):
// d h, d c per layer (of the state before the segment), d w_fb, d b_fb (undefined with detached feedback),
// and d w, d b per layer: added to dw, db where they are given (the unroll's sums, lstm_step.h weight_gradient).
std::tuple<TensorList, TensorList, Tensor, Tensor, TensorList, TensorList> segment_backward(
    const std::shared_ptr<Segment>& seg, const c10::optional<Tensor>& g_block,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c, TensorList dw,
    TensorList db);

}  // namespace stm_cpp
