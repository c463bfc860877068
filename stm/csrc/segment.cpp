// The self-fed segment: see segment.h. (Edit this file with the header: the build is keyed on the sources only.)
#include "segment.h"

#include <ATen/Dispatch.h>

#include <memory>
#include <optional>
#include <vector>

#include "feedback_state.h"

namespace stm_cpp {
namespace {

// The layers' buffers for n steps; each layer's h before the segment into its [x, h] of the first step, its bias
// into every step's sig (the steps add their products in place: one copy per layer, not one per step), its c
// before the segment the first of its cells.
std::vector<SegLayer> segment_layers(const TensorList& ws, const TensorList& bs, const TensorList& h,
                                     const TensorList& c, int64_t n, bool low) {
  const int64_t K = h[0].size(0), B = h[0].size(1), H = h[0].size(2);
  const auto opt = h[0].options();
  std::vector<SegLayer> layers;
  for (size_t k = 0; k < ws.size(); ++k) {
    SegLayer lay;
    lay.inputs = ws[k].size(1) - H;
    lay.xh = at::empty({K, n, B, lay.inputs + H}, opt);
    if (low) lay.xh_low = at::empty({K, n, B, lay.inputs + H}, opt.dtype(at::kBFloat16));
    lay.sig = bias_rows(bs[k], n, B);
    lay.cells = run_cells(c[k], n);
    copy_rows(rows_ready(h[k]), slice(lay.xh, 1, n - 1, lay.inputs), K, B, H);
    layers.push_back(std::move(lay));
  }
  return layers;
}

// out = a @ b, or += with accumulate: gemm for float32 operands, low_bmm for bf16 ones.
void product_into(const Mat& out, const Mat& a, const Mat& b, bool accumulate) {
  if (a.dtype == at::kBFloat16) low_bmm(out, a, b, accumulate);
  else gemm(out, a, b, accumulate ? 1.0 : 0.0);
}

// The feedback head's outputs of step j from the top h (stm.packed.PackView.feedback_predictor) into the step's
// block of fb_out (the bias there), and the prediction they feed back: for an MDN head the most likely component's
// mean (stm.mdn.component_mean), its index kept for the backward.
// bf16 products: h_top into the top layer's bf16 [x, h] of step j, where the step's product reads it too.
Block feedback_prediction(const Segment& seg, int64_t j, const Block& h_top) {
  const int64_t K = seg.K, B = seg.B, H = seg.H, O = seg.w_fb.size(-1);
  const Block out = slice(seg.fb_out, 0, j);
  if (seg.low.empty()) {
    gemm(Mat(out, K, B, O), Mat(h_top, K, B, H), seg.w_fb, 1.0);
  } else {
    const auto& top = seg.layers.back();
    const Block h_low = slice(top.xh_low, 1, seg.slot(j), top.inputs);
    to_low(h_top, h_low, K, B, H);
    low_bmm(Mat(out, K, B, O), Mat(h_low, K, B, H), seg.low[0], true);
  }
  if (seg.mixtures == 0) return out;
  const Block pred = slice(seg.preds, 0, j);
  component_mean(out, seg.mixtures, seg.dims, slice(seg.idx, 0, j), pred, K, B);
  return pred;
}

// One step of the stack, bottom layer first (stm.lstm_step._stack_forward), on the segment's buffers: each layer's
// h goes straight into the next layer's [x, h] of this step (the top's into the block) and into its own [x, h]
// of the next step (after the last step: into h_last); c into the layer's cells.
void stack_step(const Segment& seg, int64_t j, const Tensor& block, const TensorList& h_last) {
  const int64_t L = static_cast<int64_t>(seg.layers.size()), n = seg.n, K = seg.K, B = seg.B, H = seg.H;
  for (int64_t k = 0; k < L; ++k) {
    const auto& lay = seg.layers[k];
    const int64_t X = lay.xh.size(-1);
    const Block sig = slice(lay.sig, 0, j), xh = slice(lay.xh, 1, seg.slot(j));
    if (seg.low.empty()) {
      gemm(Mat(sig, K, B, 4 * H), Mat(xh, K, B, X), seg.ws[k], 1.0);  // sig holds the bias
    } else {  // the step's [x, h] complete now (x from the layer below): its bf16 rows, kept for the weight gradient
      const Block xl = slice(lay.xh_low, 1, seg.slot(j));
      to_low(xh, xl, K, B, X);
      low_bmm(Mat(sig, K, B, 4 * H), Mat(xl, K, B, X), seg.low[k + 1], true);
    }
    const Block up = k + 1 < L ? slice(seg.layers[k + 1].xh, 1, seg.slot(j)) : slice(block, 2, j);
    const Block next = j + 1 < n ? slice(lay.xh, 1, seg.slot(j + 1), lay.inputs) : Block(h_last[k]);
    step_forward(sig, lay.cells.before(j), lay.cells.after(j), lay.cells.tanh_after(j), up, next, K, B, H);
  }
}

}  // namespace

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
  seg->n = n;
  seg->K = K;
  seg->B = B;
  seg->H = H;
  const auto opt = h[0].options();
  seg->layers = segment_layers(ws, bs, h, c, n, !low.empty());
  seg->fb_out = bias_rows(b_fb, n, B);
  if (seg->mixtures > 0) {
    seg->preds = at::empty({n, K, B, seg->dims}, opt);
    seg->idx = at::empty({n, K, B, 1}, opt.dtype(at::kLong));
  }
  const auto block = at::empty({K, B, n, H}, opt);
  TensorList h_last(L);
  for (int64_t k = 0; k < L; ++k) h_last[k] = at::empty({K, B, H}, opt);
  seg->qs = at::empty({n, K, B, JOINTS}, opt);
  seg->mask_q = at::empty({n, K, B, JOINTS}, opt.dtype(at::kBool));
  if (seg->gripper) seg->mask_g = at::empty({n, K, B, 1}, opt.dtype(at::kBool));
  std::optional<TipKinematics> tip;
  if (!seg->free_phi) {  // phi = tip + an offset that depends on psi alone (checked on the Python side)
    tip.emplace(fk, degree, slots, monomials, K * B);
    TORCH_CHECK(slots == JOINTS + 1, "the tip kinematics: the tip and one Jacobian row per joint");
    seg->slots = slots;
    seg->kin = at::empty({n, K, B, slots * 3}, opt);
  }
  // the constants as broadcast step blocks
  const auto mean_rows = rows_ready(mean).expand({K, B, mean.size(-1)});
  const auto lo = rows_ready(lower).expand({K, B, JOINTS}), hi = rows_ready(upper).expand({K, B, JOINTS});
  const auto psi_rows = rows_ready(psi), offsets = rows_ready(phi_offset);
  const int64_t P = psi.size(-1);
  const Tensor h_top0 = rows_ready(h[L - 1]);
  const Tensor q_first = rows_ready(q0);  // holds the memory q_prev points into before the first step
  Block q_prev = q_first;
  for (int64_t j = 0; j < n; ++j) {
    const Block pred = feedback_prediction(*seg, j, j == 0 ? Block(h_top0) : slice(block, 2, j - 1));
    // stm.model.feedback_state, the centred input straight into the bottom layer's [x, h]
    const Block x = slice(seg->layers[0].xh, 1, seg->slot(j));
    const Block q = slice(seg->qs, 0, j);
    fed_joints(q_prev, pred, lo, hi, mean_rows, q, slice(seg->mask_q, 0, j), x,
               seg->gripper ? slice(seg->mask_g, 0, j) : Block(), K, B);
    if (seg->free_phi) {
      fed_context(at_col(pred, seg->phi_start), seg->phi_dim, Block(), slice(psi_rows, 2, j), P, mean_rows,
                  seg->phi_start, x, K, B);
    } else {  // q's rows (K B, 7) -> the step's kinematics rows (K B slots, 3): the tip first, then its Jacobian
      tip->run(Mat(q.data, q.dtype, 1, K * B, JOINTS, 0, JOINTS, 1),
               Mat(slice(seg->kin, 0, j).data, q.dtype, 1, K * B * slots, 3, 0, 3, 1));
      fed_context(slice(seg->kin, 0, j), 3, slice(offsets, 2, j), slice(psi_rows, 2, j), P, mean_rows,
                  seg->phi_start, x, K, B);
    }
    stack_step(*seg, j, block, h_last);
    q_prev = q;
  }
  for (int64_t k = 0; k < L; ++k) c[k] = seg->layers[k].cells.last;
  return {block, h_last, c, seg};
}

namespace {

// What the backward's steps write, made once per call: per layer d gates (the weight gradient's rows, in xh's
// order), their bf16 copies, d [x, h] of a step, the cell state's gradient (alternating blocks), and where each
// layer's d h lies (gh: the layer's d [x, h] from column gh_col, the first step's incoming gradient, or dh0).
struct Backward {
  TensorList dg, dg_low, dxh, dh0, gh;
  std::vector<int64_t> gh_col;
  std::vector<Pair> gcs;
  Tensor zeros, fb_dh;  // zero d h (none from above), the head's d h of a step

  Block dh(size_t k) const { return gh[k].defined() ? at_col(Block(gh[k]), gh_col[k]) : Block(); }
};

// The backward of step j of the stack, top layer first (stm.lstm_step._stack_backward): gc in and out per layer,
// d h through bw.gh; g_top, the gradient of the top h from the block (none: zero); d gates into the layers' rows;
// returns the bottom layer's d [x, h] (none unless need_x). With bf16 products the d gates also into dg_low.
Block stack_step_backward(const Segment& seg, int64_t j, Backward& bw, TensorList& gc, const Block& g_top,
                          bool need_x) {
  const int64_t L = static_cast<int64_t>(seg.layers.size()), K = seg.K, B = seg.B, H = seg.H;
  Block below = g_top;  // d h from above: the layer above's d [x, h], its first H columns
  for (int64_t k = L - 1; k >= 0; --k) {
    const auto& lay = seg.layers[k];
    const auto& gc_new = bw.gcs[k][j % 2];
    const int64_t d_in = lay.inputs;
    const Block own = bw.dh(k);
    Block dh_a = own.data != nullptr ? own : below, dh_b = own.data != nullptr ? below : Block();
    if (dh_a.data == nullptr) {
      if (!bw.zeros.defined()) bw.zeros = at::zeros({K, B, H}, gc_new.options());
      dh_a = bw.zeros;
    }
    Block dgates = slice(bw.dg[k], 1, seg.slot(j));
    step_backward(slice(lay.sig, 0, j), lay.cells.before(j), lay.cells.tanh_after(j), dh_a, dh_b, gc[k], dgates,
                  gc_new);
    gc[k] = gc_new;
    Mat w(seg.ws[k]);
    if (!seg.low.empty()) {
      w = Mat(seg.low[k + 1]);
      const Block dl = slice(bw.dg_low[k], 1, seg.slot(j));
      to_low(dgates, dl, K, B, 4 * H);
      dgates = dl;
    }
    if (k > 0 || need_x) {
      product_into(bw.dxh[k], Mat(dgates, K, B, 4 * H), w.t(), false);
      below = Block(bw.dxh[k]);
      bw.gh[k] = bw.dxh[k];
      bw.gh_col[k] = d_in;
    } else {  // a detached input: only the recurrent part
      below = Block();
      product_into(bw.dh0[k], Mat(dgates, K, B, 4 * H), w.rows(d_in, H).t(), false);
      bw.gh[k] = bw.dh0[k];
      bw.gh_col[k] = 0;
    }
  }
  return below;
}

// dst += src over (K, B) rows of X columns (gh + the head's d h, as ATen's add).
void add_rows_into(const Block& dst, const Block& src, int64_t K, int64_t B, int64_t X) {
  AT_DISPATCH_FLOATING_TYPES(dst.dtype, "add_rows_into", [&] {
    const auto d = rows<scalar_t>(dst), s = rows<scalar_t>(src);
    for (int64_t k = 0; k < K; ++k) {
      for (int64_t b = 0; b < B; ++b) {
        scalar_t* __restrict__ o = d.at(k, b);
        const scalar_t* __restrict__ a = s.at(k, b);
        for (int64_t c = 0; c < X; ++c) o[c] = o[c] + a[c];
      }
    }
  });
}

}  // namespace

std::tuple<TensorList, TensorList, Tensor, Tensor, TensorList, TensorList> segment_backward(
    const std::shared_ptr<Segment>& seg, const c10::optional<Tensor>& g_block,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c, TensorList dw,
    TensorList db) {
  const at::AutoDispatchBelowADInplaceOrView below_autograd;  // see lstm_step.h, below_autograd
  const int64_t L = static_cast<int64_t>(g_h.size()), n = seg->n, K = seg->K, B = seg->B, H = seg->H;
  dw.resize(L);
  db.resize(L);
  const auto& top = seg->layers[L - 1];
  const auto opt = top.cells.c0.options();
  const bool low = !seg->low.empty(), need_x = !seg->detach;
  Backward bw;
  bw.dg.resize(L);
  bw.dg_low.resize(L);
  bw.dxh.resize(L);
  bw.dh0.resize(L);
  bw.gh.resize(L);
  bw.gh_col.assign(L, 0);
  bw.gcs.resize(L);
  TensorList gc(L);
  for (int64_t k = 0; k < L; ++k) {
    if (g_h[k].has_value()) bw.gh[k] = rows_ready(*g_h[k]);
    if (g_c[k].has_value()) gc[k] = rows_ready(*g_c[k]);
    bw.dg[k] = at::empty({K, n, B, 4 * H}, opt);  // rows in xh's order
    if (low) bw.dg_low[k] = at::empty({K, n, B, 4 * H}, opt.dtype(at::kBFloat16));
    if (k > 0 || need_x) bw.dxh[k] = at::empty({K, B, seg->layers[k].inputs + H}, opt);
    else bw.dh0[k] = at::empty({K, B, H}, opt);
    bw.gcs[k] = block_pair({K, B, H}, opt);
  }
  const Tensor gb = g_block.has_value() ? rows_ready(*g_block) : Tensor();
  const int64_t outs = seg->w_fb.size(-1);
  const Tensor douts = seg->detach ? Tensor() : at::zeros({K, n, B, outs}, opt);  // the head's, in xh's order
  const Tensor douts_low = low && need_x ? at::empty({K, n, B, outs}, opt.dtype(at::kBFloat16)) : Tensor();
  if (need_x) bw.fb_dh = at::empty({K, B, H}, opt);
  const auto gqs = block_pair({K, B, JOINTS}, opt);
  Block gq;  // gradient of the q a step leaves for the next
  for (int64_t j = n - 1; j >= 0; --j) {
    const Block dxh = stack_step_backward(*seg, j, bw, gc, gb.defined() ? slice(gb, 2, j) : Block(), need_x);
    if (!need_x) continue;
    const Block dout = slice(douts, 1, seg->slot(j));
    // back through stm.model.feedback_state and the head's component choice (gather)
    const auto& gq_new = gqs[j % 2];
    fed_backward(dxh, gq, seg->free_phi ? Block() : at_col(slice(seg->kin, 0, j), 3), slice(seg->mask_q, 0, j),
                 seg->gripper ? slice(seg->mask_g, 0, j) : Block(),
                 seg->mixtures > 0 ? slice(seg->idx, 0, j) : Block(), seg->phi_start,
                 seg->free_phi ? seg->phi_dim : 0, seg->mixtures, seg->dims, gq_new, dout, K, B,
                 opt.dtype().toScalarType());
    gq = gq_new;
    // the head's product, added to the top layer's d h (its own buffer: the step's d [x, h])
    if (low) {
      const Block dl = slice(douts_low, 1, seg->slot(j));
      to_low(dout, dl, K, B, outs);
      low_bmm(bw.fb_dh, Mat(dl, K, B, outs), Mat(seg->low[0]).t(), false);
    } else {
      gemm(bw.fb_dh, Mat(dout, K, B, outs), Mat(seg->w_fb).t());
    }
    add_rows_into(bw.dh(L - 1), bw.fb_dh, K, B, H);
  }
  for (int64_t k = 0; k < L; ++k) {
    const auto& lay = seg->layers[k];
    weight_gradient(rows_of(lay.xh), rows_of(bw.dg[k]), dw[k], db[k], low ? rows_of(lay.xh_low) : Mat(),
                    low ? rows_of(bw.dg_low[k]) : Mat());
  }
  Tensor dw_fb, db_fb;
  if (need_x) {  // one product for all the segment's steps
    const auto& xh = low ? top.xh_low : top.xh;
    dw_fb = product(rows_of(xh).cols(top.inputs, H).t(), rows_of(low ? douts_low : douts));
    db_fb = douts.view({K, n * B, outs}).sum(1, true);
  }
  TensorList dh(L);
  for (int64_t k = 0; k < L; ++k)
    if (bw.gh[k].defined()) dh[k] = bw.gh_col[k] ? bw.gh[k].narrow(-1, bw.gh_col[k], H) : bw.gh[k];
  return {dh, gc, dw_fb, db_fb, dw, db};
}

}  // namespace stm_cpp
