// The self-fed steps of the auto-conditioned unroll (stm.autoconditioning), a whole segment of them per call:
// per step the feedback head's prediction, the fed-back state (joint integration, clamping, gripper rounding,
// the tip's forward kinematics) and the L-layer LSTM stack step, forward; and the backward of all of it.
//
// Why C++: a self-fed step is ~330 small ATen calls (forward and backward); issued from Python each pays
// several microseconds of binding and autograd bookkeeping, more than its arithmetic at these sizes. Here the
// same ATen calls (the LSTM step's and the fed-back state's elementwise ones: the same arithmetic in loops,
// lstm_step.h, feedback_state.h) run in the same order on the same shapes, so the forward is that of the Python
// path (stm.lstm_step, stm.fk, stm.model.feedback_state) and the backward differs only in the order in which a few
// gradient contributions are summed. The weight gradient is not computed per step: one product per layer and
// chunk of steps (`weight_gradient`). What the steps write goes into buffers of the whole segment (SegLayer),
// the products' outputs included (out= calls): no per-step allocations, and the weight gradients' rows are already
// in place, not gathered by a cat at the end. The LSTM stack itself: lstm_step.h.
//
// bf16 products (TrainConfig.matmul_dtype "bfloat16"; Segment::low): the LSTM stack's and the feedback head's
// products, forward and backward, and the weight gradients take bf16 operands (the weights cast once per unroll, on
// the Python side; [x, h] and d gates per step into bf16 buffers) and give float32 (lstm_step.h, low_bmm); the
// state, the gate maths, the fed-back state and the tip's kinematics stay float32.
//
// Shapes: K models of a pack, batch B. h, c per layer (K, B, H); w per layer (K, I + H, 4H) with the gate
// columns i, f, o, 2g; b (K, 1, 4H); the feedback head w_fb (K, H, O), b_fb (K, 1, O).
#include <torch/extension.h>

#include <memory>
#include <vector>

#include "feedback_state.h"
#include "lstm_step.h"
#include "mdn_nll.h"

using stm_cpp::Block;
using stm_cpp::block_pair;
using stm_cpp::step_backward;
using stm_cpp::step_forward;
using stm_cpp::fed_backward;
using stm_cpp::fed_context;
using stm_cpp::fed_joints;
using stm_cpp::JOINTS;
using stm_cpp::low_bmm;
using stm_cpp::Pair;
using stm_cpp::product;
using stm_cpp::rows_ready;
using stm_cpp::Sequence;
using stm_cpp::slice;
using stm_cpp::Tensor;
using stm_cpp::TensorList;
using stm_cpp::to_low;
using stm_cpp::weight_gradient;

namespace {

struct Step {
  Tensor idx;  // the mixture component fed back (MDN head)
  Tensor jac;  // d tip / d q (K, B, JOINTS * 3)
};

// A layer's values over the segment's n steps, in buffers written step by step (lstm_step.h's step blocks).
// xh holds the rows of the layer's weight gradient, [x, h] per step, in the order the backward visits the steps
// (step j at slot n - 1 - j): the product reads them in place, and the top layer's h part is what the feedback
// head read (the rows of its weight gradient).
struct SegLayer {
  Tensor xh;             // (K, n, B, I + H)
  Tensor xh_low;         // bf16 products: xh in bf16, each step's rows cast before its product
  Tensor sig, gd, o_dt;  // per step (n, K, B, 4H), (n, K, B, 4H), (n, K, B, H)
  int64_t inputs = 0;    // I
};

// What the backward needs of one segment's forward; the Python side holds it between the two.
struct Segment {
  TensorList ws;
  Tensor w_fb;
  TensorList low;  // bf16 products: w_fb, then each layer's w, in bf16 (empty: float32 products)
  Tensor fb_out;   // bf16 products: the feedback head's outputs per step (n, K, B, O), the bias written in
  std::vector<Step> steps;
  std::vector<SegLayer> layers;
  Tensor qs;      // the fed-back q per step (n, K, B, JOINTS): the forward's, one block per step
  Tensor mask_q;  // where q_prev + dq was within the joint limits (clamp passes the gradient) (n, K, B, JOINTS)
  Tensor mask_g;  // where the gripper prediction was within [0, 1] (n, K, B, 1)
  int64_t mixtures = 0, dims = 0, phi_start = 0, phi_dim = 0;
  bool gripper = false, free_phi = false, detach = false;
  int64_t slot(int64_t j) const { return static_cast<int64_t>(steps.size()) - 1 - j; }
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
  auto mono = stm_cpp::monomial_products(factors, index, degree);  // (N, slots * monomials)
  auto entries = at::mm(mono.view({N * slots, monomials}), coef);
  auto out = at::mm(entries.narrow(1, 0, 12) * entries.narrow(1, 12, 12), row_sums).view({N, slots, 3});
  return {out.select(1, 0), out.narrow(1, 1, slots - 1)};
}

// The layers' buffers for n steps; each layer's h before the segment into its [x, h] of the first step, its bias
// into every step's sig (the steps add their products in place: one copy per layer, not one per step).
std::vector<SegLayer> segment_layers(const TensorList& ws, const TensorList& bs, const TensorList& h, int64_t n,
                                     bool low) {
  const int64_t K = h[0].size(0), B = h[0].size(1), H = h[0].size(2);
  const auto opt = h[0].options();
  std::vector<SegLayer> layers;
  for (size_t k = 0; k < ws.size(); ++k) {
    SegLayer lay;
    lay.inputs = ws[k].size(1) - H;
    lay.xh = at::empty({K, n, B, lay.inputs + H}, opt);
    if (low) lay.xh_low = at::empty({K, n, B, lay.inputs + H}, opt.dtype(at::kBFloat16));
    lay.sig = stm_cpp::bias_rows(bs[k], n, B);
    lay.gd = at::empty({n, K, B, 4 * H}, opt);
    lay.o_dt = at::empty({n, K, B, H}, opt);
    lay.xh.select(1, n - 1).narrow(-1, lay.inputs, H).copy_(h[k]);
    layers.push_back(std::move(lay));
  }
  return layers;
}

// The feedback head's prediction from the top h (stm.packed.PackView.feedback_predictor); for an MDN head the most
// likely component's mean (stm.mdn.component_mean), its index kept for the backward.
// bf16 products: h_top into the top layer's bf16 [x, h] of step j, where the step's product reads it too.
Tensor feedback_prediction(const Segment& seg, int64_t j, const Tensor& h_top, const Tensor& w_fb, const Tensor& b_fb,
                           Step& st) {
  Tensor out;
  if (seg.low.empty()) {
    out = at::baddbmm(b_fb, h_top, w_fb);
  } else {
    const auto& top = seg.layers.back();
    const int64_t H = h_top.size(-1);
    to_low(rows_ready(h_top), slice(top.xh_low, 1, seg.slot(j), top.inputs), h_top.size(0), h_top.size(1), H);
    out = seg.fb_out[j];
    low_bmm(out, top.xh_low.select(1, seg.slot(j)).narrow(-1, top.inputs, H), seg.low[0], true);
  }
  const int64_t m = seg.mixtures, dims = seg.dims;
  if (m == 0) return out;
  const int64_t K = out.size(0), B = out.size(1);
  auto mu = out.narrow(-1, m, m * dims).unflatten(-1, {m, dims});
  st.idx = out.narrow(-1, 0, m).argmax(-1, true);
  return at::gather(mu, -2, st.idx.unsqueeze(-1).expand({K, B, 1, dims})).squeeze(-2);
}

// One step of the stack, bottom layer first (stm.lstm_step._stack_forward), on the segment's buffers: each layer's
// h goes straight into the next layer's [x, h] of this step (the top's into the block) and into its own [x, h]
// of the next step (after the last step: into h_last); c alternates between two blocks per layer (c_blocks[k]).
void stack_step(const Segment& seg, int64_t j, TensorList& c, const std::vector<Pair>& c_blocks, const Tensor& tc,
                const Tensor& block, const TensorList& h_last) {
  const int64_t L = static_cast<int64_t>(seg.layers.size()), n = static_cast<int64_t>(seg.steps.size());
  for (int64_t k = 0; k < L; ++k) {
    const auto& lay = seg.layers[k];
    auto sig = lay.sig[j];
    if (seg.low.empty()) {
      at::baddbmm_out(sig, sig, lay.xh.select(1, seg.slot(j)), seg.ws[k]);  // sig holds the bias
    } else {  // the step's [x, h] complete now (x from the layer below): its bf16 rows, kept for the weight gradient
      to_low(slice(lay.xh, 1, seg.slot(j)), slice(lay.xh_low, 1, seg.slot(j)), sig.size(0), sig.size(1),
             lay.xh.size(-1));
      low_bmm(sig, lay.xh_low.select(1, seg.slot(j)), seg.low[k + 1], true);
    }
    sig.sigmoid_();
    const Block up = k + 1 < L ? slice(seg.layers[k + 1].xh, 1, seg.slot(j)) : slice(block, 2, j);
    const Block next = j + 1 < n ? slice(lay.xh, 1, seg.slot(j + 1), lay.inputs) : Block(h_last[k]);
    const auto& c_new = c_blocks[k][j % 2];
    step_forward(sig, c[k], c_new, tc, slice(lay.gd, 0, j), slice(lay.o_dt, 0, j), up, next);
    c[k] = c_new;
  }
}

// ints: degree, slots, monomials (the FK plan), mixtures (0: deterministic head), dims (prediction columns
// used), gripper, free_phi, phi_start, phi_dim, detach.
std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Segment>> segment_forward(
    TensorList h, TensorList c, const TensorList& ws, const TensorList& bs, const Tensor& w_fb, const Tensor& b_fb,
    const Tensor& q0, const Tensor& psi, const Tensor& phi_offset, const Tensor& mean, const Tensor& lower,
    const Tensor& upper, const TensorList& fk, const std::vector<int64_t>& ints, const TensorList& low) {
  const at::AutoDispatchBelowADInplaceOrView below_autograd;  // see lstm_step.h, below_autograd
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
  seg->low = low;
  const int64_t K = q0.size(0), B = q0.size(1), n = psi.size(2);
  const int64_t L = static_cast<int64_t>(h.size()), H = h[0].size(-1);
  seg->steps.resize(n);
  seg->layers = segment_layers(ws, bs, h, n, !low.empty());
  if (!low.empty()) seg->fb_out = stm_cpp::bias_rows(b_fb, n, B);
  const auto block = at::empty({K, B, n, H}, h[0].options());
  const auto tc = at::empty({K, B, H}, h[0].options());
  std::vector<Pair> c_blocks(L);
  TensorList h_last(L);
  for (int64_t k = 0; k < L; ++k) {
    c_blocks[k] = block_pair({K, B, H}, h[0].options());
    h_last[k] = at::empty({K, B, H}, h[0].options());
    c[k] = rows_ready(c[k]);
  }
  const auto bool_opt = h[0].options().dtype(at::kBool);
  seg->qs = at::empty({n, K, B, JOINTS}, h[0].options());
  seg->mask_q = at::empty({n, K, B, JOINTS}, bool_opt);
  if (seg->gripper) seg->mask_g = at::empty({n, K, B, 1}, bool_opt);
  // the constants as broadcast step blocks
  const auto mean_rows = rows_ready(mean).expand({K, B, mean.size(-1)});
  const auto lo = rows_ready(lower).expand({K, B, JOINTS}), hi = rows_ready(upper).expand({K, B, JOINTS});
  const auto psi_rows = rows_ready(psi), offsets = rows_ready(phi_offset);
  const int64_t P = psi.size(-1);
  Tensor q_prev = rows_ready(q0);
  for (int64_t j = 0; j < n; ++j) {
    Step& st = seg->steps[j];
    const auto pred = feedback_prediction(*seg, j, j == 0 ? h[L - 1] : block.select(2, j - 1), w_fb, b_fb, st);
    // stm.model.feedback_state, the centred input straight into the bottom layer's [x, h]
    const Block x = slice(seg->layers[0].xh, 1, seg->slot(j));
    const auto q = seg->qs[j];
    fed_joints(q_prev, pred, lo, hi, mean_rows, q, slice(seg->mask_q, 0, j), x,
               seg->gripper ? slice(seg->mask_g, 0, j) : Block());
    if (seg->free_phi) {
      fed_context(pred.narrow(-1, seg->phi_start, seg->phi_dim), Block(), slice(psi_rows, 2, j), P, mean_rows,
                  seg->phi_start, x);
    } else {  // phi = tip + an offset that depends on psi alone (checked on the Python side)
      auto tj = tip_kinematics(q.view({-1, JOINTS}), fk, degree, slots, monomials);
      TORCH_CHECK(tj.second.size(1) == JOINTS, "the tip kinematics' Jacobian: one row per joint");
      st.jac = tj.second.reshape({K, B, JOINTS * 3});
      fed_context(tj.first.view({K, B, 3}), slice(offsets, 2, j), slice(psi_rows, 2, j), P, mean_rows,
                  seg->phi_start, x);
    }
    stack_step(*seg, j, c, c_blocks, tc, block, h_last);
    q_prev = q;
  }
  return {block, h_last, c, seg};
}

// The backward of step j of the stack, top layer first (stm.lstm_step._stack_backward): gh, gc in (gc alternating
// between two blocks per layer, gcs[k]), the gradients of the step's inputs out, and g_top, the gradient of the
// top h from the block (none: zero); d gates into the layers' rows dg[k]; returns the bottom layer's d [x, h],
// d x in its first columns (undefined unless need_x). With bf16 products the d gates also into dg_low[k].
Tensor stack_step_backward(const Segment& seg, int64_t j, TensorList& gh, TensorList& gc, const Block& g_top,
                           const TensorList& dg, const TensorList& dg_low, const std::vector<Pair>& gcs,
                           bool need_x) {
  const int64_t L = static_cast<int64_t>(seg.layers.size());
  Block below = g_top;  // d h from above: the layer above's d [x, h], its first H columns
  Tensor dxh, zeros;
  for (int64_t k = L - 1; k >= 0; --k) {
    const auto& lay = seg.layers[k];
    const auto& gc_new = gcs[k][j % 2];
    const int64_t H = gc_new.size(-1), d_in = lay.inputs;
    Block dh_a = gh[k].defined() ? Block(gh[k]) : below, dh_b = gh[k].defined() ? below : Block();
    if (dh_a.data == nullptr) {
      zeros = at::zeros_like(gc_new);
      dh_a = zeros;
    }
    auto dgates = dg[k].select(1, seg.slot(j));
    step_backward(slice(lay.sig, 0, j), slice(lay.gd, 0, j), slice(lay.o_dt, 0, j), dh_a, dh_b, gc[k], dgates,
                  gc_new);
    gc[k] = gc_new;
    Tensor w = seg.ws[k];
    if (!seg.low.empty()) {
      w = seg.low[k + 1];
      to_low(slice(dg[k], 1, seg.slot(j)), slice(dg_low[k], 1, seg.slot(j)), gc_new.size(0), gc_new.size(1),
             4 * H);
      dgates = dg_low[k].select(1, seg.slot(j));
    }
    if (k > 0 || need_x) {
      dxh = product(dgates, w.transpose(1, 2));
      below = dxh;
      gh[k] = dxh.narrow(-1, d_in, H);
    } else {  // a detached input: only the recurrent part
      below = Block();
      dxh = Tensor();
      gh[k] = product(dgates, w.narrow(1, d_in, H).transpose(1, 2));
    }
  }
  return dxh;
}

// Gradients of the segment's inputs from those of its outputs (undefined where none reached them):
// d h, d c per layer (of the state before the segment), d w_fb, d b_fb (undefined with detached feedback),
// and d w, d b per layer: added to dw, db where they are given (the unroll's sums, lstm_step.h weight_gradient).
std::tuple<TensorList, TensorList, Tensor, Tensor, TensorList, TensorList> segment_backward(
    const std::shared_ptr<Segment>& seg, const c10::optional<Tensor>& g_block,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c, TensorList dw,
    TensorList db) {
  const at::AutoDispatchBelowADInplaceOrView below_autograd;  // see lstm_step.h, below_autograd
  const int64_t L = static_cast<int64_t>(g_h.size()), n = static_cast<int64_t>(seg->steps.size());
  dw.resize(L);
  db.resize(L);
  const auto& top = seg->layers[L - 1];
  const int64_t K = top.o_dt.size(1), B = top.o_dt.size(2), H = top.o_dt.size(3);
  const auto opt = top.o_dt.options();
  const bool low = !seg->low.empty();
  TensorList gh(L), gc(L), dg(L), dg_low(L);
  std::vector<Pair> gcs(L);
  for (int64_t k = 0; k < L; ++k) {
    if (g_h[k].has_value()) gh[k] = rows_ready(*g_h[k]);
    if (g_c[k].has_value()) gc[k] = rows_ready(*g_c[k]);
    dg[k] = at::empty({K, n, B, 4 * H}, opt);  // rows in xh's order
    if (low) dg_low[k] = at::empty({K, n, B, 4 * H}, opt.dtype(at::kBFloat16));
    gcs[k] = block_pair({K, B, H}, opt);
  }
  const Tensor gb = g_block.has_value() ? rows_ready(*g_block) : Tensor();
  const int64_t outs = seg->w_fb.size(-1);
  const Tensor douts = seg->detach ? Tensor() : at::zeros({K, n, B, outs}, opt);  // the head's, in xh's order
  const Tensor douts_low = low && !seg->detach ? at::empty({K, n, B, outs}, opt.dtype(at::kBFloat16)) : Tensor();
  const auto gqs = block_pair({K, B, JOINTS}, opt);
  Tensor gq;  // gradient of the q a step leaves for the next
  for (int64_t j = n - 1; j >= 0; --j) {
    const auto dxh = stack_step_backward(*seg, j, gh, gc, gb.defined() ? slice(gb, 2, j) : Block(), dg, dg_low,
                                         gcs, !seg->detach);
    if (seg->detach) continue;
    const auto dout = douts.select(1, seg->slot(j));
    // back through stm.model.feedback_state and the head's component choice (gather)
    const auto& st = seg->steps[j];
    const auto& gq_new = gqs[j % 2];
    fed_backward(dxh, gq, st.jac, slice(seg->mask_q, 0, j), seg->gripper ? slice(seg->mask_g, 0, j) : Block(),
                 st.idx, seg->phi_start, seg->free_phi ? seg->phi_dim : 0, seg->mixtures, seg->dims, gq_new, dout);
    gq = gq_new;
    if (low) {
      to_low(dout, slice(douts_low, 1, seg->slot(j)), K, B, outs);
      gh[L - 1] = gh[L - 1] + product(douts_low.select(1, seg->slot(j)), seg->low[0].transpose(1, 2));
    } else {
      gh[L - 1] = gh[L - 1] + at::bmm(dout, seg->w_fb.transpose(1, 2));
    }
  }
  for (int64_t k = 0; k < L; ++k) {
    const auto& lay = seg->layers[k];
    const auto dg_rows = dg[k].view({K, n * B, 4 * H});
    weight_gradient(lay.xh.view({K, n * B, -1}), dg_rows, dw[k], db[k],
                    low ? lay.xh_low.view({K, n * B, -1}) : Tensor(),
                    low ? dg_low[k].view({K, n * B, 4 * H}) : Tensor());
  }
  Tensor dw_fb, db_fb;
  if (!seg->detach) {  // one product for all the segment's steps
    const auto rows = douts.view({K, n * B, outs});
    const auto& xh = low ? top.xh_low : top.xh;
    dw_fb = product(xh.narrow(-1, top.inputs, H).view({K, n * B, H}).transpose(1, 2),
                    low ? douts_low.view({K, n * B, outs}) : rows);
    db_fb = rows.sum(1, true);
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
