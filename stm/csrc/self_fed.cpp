// The self-fed steps of the auto-conditioned unroll (stm.autoconditioning), a whole segment of them per call:
// per step the feedback head's prediction, the fed-back state (joint integration, clamping, gripper rounding,
// the tip's forward kinematics) and the L-layer LSTM stack step, forward; and the backward of all of it.
//
// Why C++: a self-fed step is ~330 small ATen calls (forward and backward); issued from Python each pays
// several microseconds of binding and autograd bookkeeping, more than its arithmetic at these sizes. Here the
// same ATen calls (the LSTM cell's elementwise ones: the same arithmetic in loops) run in the same order on the
// same shapes, so the forward is that of the Python path (stm.lstm_step, stm.fk, stm.model.feedback_state) and
// the backward differs only in the order in which a few gradient contributions are summed. The weight gradient is not computed per step: one product per layer and
// chunk of steps (`weight_gradient`). The LSTM stack itself: lstm_cell.h.
//
// Shapes: K models of a pack, batch B. h, c per layer (K, B, H); w per layer (K, I + H, 4H) with the gate
// columns i, f, o, 2g; b (K, 1, 4H); the feedback head w_fb (K, H, O), b_fb (K, 1, O).
#include <torch/extension.h>

#include <memory>
#include <vector>

#include "lstm_cell.h"
#include "mdn_nll.h"

using stm_cpp::Layer;
using stm_cpp::Sequence;
using stm_cpp::stack_backward;
using stm_cpp::stack_forward;
using stm_cpp::Tensor;
using stm_cpp::TensorList;
using stm_cpp::weight_gradient;

namespace {

constexpr int64_t JOINTS = 7;

struct Step {
  std::vector<Layer> layers;
  Tensor h_top_in;  // the top hidden state the head read
  Tensor idx;       // the mixture component fed back (MDN head)
  Tensor mask_q;    // where q_prev + dq was within the joint limits (clamp passes the gradient)
  Tensor mask_g;    // where the gripper prediction was within [0, 1]
  Tensor jac;       // d tip / d q (N, JOINTS, 3)
};

// What the backward needs of one segment's forward; the Python side holds it between the two.
struct Segment {
  TensorList ws;
  Tensor w_fb;
  std::vector<Step> steps;
  int64_t mixtures = 0, dims = 0, phi_start = 0, phi_dim = 0;
  bool gripper = false, free_phi = false, detach = false;
};

// Tip position (N, 3) and Jacobian (N, JOINTS, 3) of q (N, JOINTS): stm.fk._slots with the gradient plan.
std::pair<Tensor, Tensor> tip_kinematics(const Tensor& q, const TensorList& fk, int64_t degree, int64_t slots,
                                         int64_t monomials) {
  const auto& signs = fk[0];
  const auto& phases = fk[1];
  const auto& index = fk[2];
  const auto& coef = fk[3];
  const auto& row_sums = fk[4];
  const int64_t N = q.size(0);
  auto factors = at::sin(at::addmm(phases, q, signs));
  auto mono = factors.index_select(1, index).view({N, degree, slots * monomials}).prod(1);
  auto entries = at::mm(mono.view({N * slots, monomials}), coef);
  auto out = at::mm(entries.narrow(1, 0, 12) * entries.narrow(1, 12, 12), row_sums).view({N, slots, 3});
  return {out.select(1, 0), out.narrow(1, 1, slots - 1)};
}

// ints: degree, slots, monomials (the FK plan), mixtures (0: deterministic head), dims (prediction columns
// used), gripper, free_phi, phi_start, phi_dim, detach.
std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Segment>> segment_forward(
    TensorList h, TensorList c, const TensorList& ws, const TensorList& bs, const Tensor& w_fb, const Tensor& b_fb,
    const Tensor& q0, const Tensor& psi, const Tensor& phi_offset, const Tensor& mean, const Tensor& lower,
    const Tensor& upper, const TensorList& fk, const std::vector<int64_t>& ints) {
  auto seg = std::make_shared<Segment>();
  const int64_t degree = ints[0], slots = ints[1], monomials = ints[2];
  seg->mixtures = ints[3];
  seg->dims = ints[4];
  seg->gripper = ints[5] != 0;
  seg->free_phi = ints[6] != 0;
  seg->phi_start = ints[7];
  seg->phi_dim = ints[8];
  seg->detach = ints[9] != 0;
  seg->ws = ws;
  seg->w_fb = w_fb;
  const int64_t K = q0.size(0), B = q0.size(1), n = psi.size(2), m = seg->mixtures, dims = seg->dims;
  const int64_t L = static_cast<int64_t>(h.size());
  TensorList block;
  Tensor q_prev = q0;
  for (int64_t j = 0; j < n; ++j) {
    Step st;
    st.h_top_in = h[L - 1];
    auto out = at::baddbmm(b_fb, h[L - 1], w_fb);  // stm.packed.PackView.feedback_predictor
    Tensor pred;
    if (m > 0) {  // the most likely component's mean (stm.mdn.component_mean)
      auto mu = out.narrow(-1, m, m * dims).unflatten(-1, {m, dims});
      st.idx = out.narrow(-1, 0, m).argmax(-1, true);
      pred = at::gather(mu, -2, st.idx.unsqueeze(-1).expand({K, B, 1, dims})).squeeze(-2);
    } else {
      pred = out;
    }
    // stm.model.feedback_state
    auto z = q_prev + pred.narrow(-1, 0, JOINTS);
    auto q = at::clamp(z, lower, upper);
    st.mask_q = at::logical_and(z >= lower, z <= upper);
    TensorList parts{q - q_prev};
    if (seg->gripper) {
      auto g_raw = pred.select(-1, JOINTS);
      auto g = g_raw.clamp(0.0, 1.0);
      st.mask_g = at::logical_and(g_raw >= 0.0, g_raw <= 1.0);
      parts.push_back((g + (at::round(g) - g)).unsqueeze(-1));  // straight-through rounding
    }
    if (seg->free_phi) {
      parts.push_back(pred.narrow(-1, seg->phi_start, seg->phi_dim));
    } else {  // phi = tip + an offset that depends on psi alone (checked on the Python side)
      auto tj = tip_kinematics(q.reshape({-1, JOINTS}), fk, degree, slots, monomials);
      st.jac = tj.second;
      parts.push_back(tj.first.reshape({K, B, 3}) + phi_offset.select(2, j));
    }
    parts.push_back(psi.select(2, j));
    auto x = at::cat(parts, -1) - mean;
    stack_forward(x, h, c, ws, bs, st.layers);
    block.push_back(h[L - 1]);
    seg->steps.push_back(std::move(st));
    q_prev = q;
  }
  return {at::stack(block, 2), h, c, seg};
}

// Gradients of the segment's inputs from those of its outputs (undefined where none reached them):
// d h, d c per layer (of the state before the segment), d w_fb, d b_fb (undefined with detached feedback),
// and d w, d b per layer.
std::tuple<TensorList, TensorList, Tensor, Tensor, TensorList, TensorList> segment_backward(
    const std::shared_ptr<Segment>& seg, const c10::optional<Tensor>& g_block,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c) {
  const int64_t L = static_cast<int64_t>(g_h.size()), n = static_cast<int64_t>(seg->steps.size());
  const int64_t m = seg->mixtures, dims = seg->dims;
  TensorList gh(L), gc(L), dgs(L);
  for (int64_t k = 0; k < L; ++k) {
    if (g_h[k].has_value()) gh[k] = *g_h[k];
    if (g_c[k].has_value()) gc[k] = *g_c[k];
  }
  std::vector<TensorList> xh_rows(L), dg_rows(L);
  TensorList h_in, d_out;  // per step, for the feedback head's weight gradient
  Tensor gq;               // gradient of the q a step leaves for the next
  for (int64_t j = n - 1; j >= 0; --j) {
    const auto& st = seg->steps[j];
    if (g_block.has_value()) {
      auto gb = g_block->select(2, j);
      gh[L - 1] = gh[L - 1].defined() ? gh[L - 1] + gb : gb;
    }
    auto dx = stack_backward(gh, gc, seg->ws, st.layers, !seg->detach, dgs);
    for (int64_t k = 0; k < L; ++k) {
      xh_rows[k].push_back(st.layers[k].xh);
      dg_rows[k].push_back(dgs[k]);
    }
    if (seg->detach) continue;
    // back through stm.model.feedback_state: x = [q - q_prev, grip, phi, psi] - mean
    auto ds_dq = dx.narrow(-1, 0, JOINTS);
    Tensor dq = gq.defined() ? gq + ds_dq : ds_dq;
    if (!seg->free_phi) {
      auto dtip = dx.narrow(-1, seg->phi_start, 3).reshape({-1, 3});
      dq = dq + (st.jac * dtip.unsqueeze(1)).sum(-1).view(ds_dq.sizes());
    }
    auto dz = at::where(st.mask_q, dq, at::zeros({}, dq.options()));
    gq = dz - ds_dq;
    TensorList dparts{dz};
    if (seg->gripper) {
      auto dg = dx.narrow(-1, JOINTS, 1);
      dparts.push_back(at::where(st.mask_g.unsqueeze(-1), dg, at::zeros({}, dg.options())));
    }
    if (seg->free_phi) dparts.push_back(dx.narrow(-1, seg->phi_start, seg->phi_dim));
    auto dpred = at::cat(dparts, -1);
    Tensor dout;
    if (m > 0) {  // gather's backward: into the chosen component's mean columns
      const int64_t K = dpred.size(0), B = dpred.size(1);
      dout = at::zeros({K, B, m + m * dims}, dpred.options());
      dout.narrow(-1, m, m * dims).unflatten(-1, {m, dims}).scatter_(
          -2, st.idx.unsqueeze(-1).expand({K, B, 1, dims}), dpred.unsqueeze(-2));
    } else {
      dout = dpred;
    }
    gh[L - 1] = gh[L - 1] + at::bmm(dout, seg->w_fb.transpose(1, 2));
    h_in.push_back(st.h_top_in);
    d_out.push_back(dout);
  }
  TensorList dw(L), db(L);
  for (int64_t k = 0; k < L; ++k) weight_gradient(at::cat(xh_rows[k], -2), at::cat(dg_rows[k], -2), dw[k], db[k]);
  Tensor dw_fb, db_fb;
  if (!seg->detach) {  // one product for all the segment's steps
    auto douts = at::cat(d_out, 1);
    dw_fb = at::bmm(at::cat(h_in, 1).transpose(1, 2), douts);
    db_fb = douts.sum(1, true);
  }
  return {gh, gc, dw_fb, db_fb, dw, db};
}
}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  pybind11::class_<Segment, std::shared_ptr<Segment>>(module, "Segment");
  module.def("segment_forward", &segment_forward, "self-fed segment, forward");
  module.def("segment_backward", &segment_backward, "self-fed segment, backward");
  pybind11::class_<Sequence, std::shared_ptr<Sequence>>(module, "Sequence");
  module.def("sequence_forward", &stm_cpp::sequence_forward, "known inputs through the stack, forward");
  module.def("sequence_backward", &stm_cpp::sequence_backward, "known inputs through the stack, backward");
  module.def("mdn_nll_forward", &stm_cpp::mdn_nll_forward, "mixture NLL per row (and what its backward needs)");
  module.def("mdn_nll_backward", &stm_cpp::mdn_nll_backward, "mixture NLL, gradient of the raw head outputs");
}
