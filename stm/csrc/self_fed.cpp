// The self-fed steps of the auto-conditioned unroll (stm.autoconditioning), a whole segment of them per call:
// per step the feedback head's prediction, the fed-back state (joint integration, clamping, gripper rounding,
// the tip's forward kinematics) and the L-layer LSTM stack step, forward; and the backward of all of it.
//
// Why C++: a self-fed step is ~330 small ATen calls (forward and backward); issued from Python each pays
// several microseconds of binding and autograd bookkeeping, more than its arithmetic at these sizes. Here the
// same ATen calls run in the same order on the same shapes, so the forward is bitwise that of the Python path
// (stm.lstm_step, stm.fk, stm.model.feedback_state) and the backward differs only in the order in which a few
// gradient contributions are summed. The weight gradient is not computed per step: one product per layer and
// chunk of steps (`weight_gradient`).
//
// Shapes: K models of a pack, batch B. h, c per layer (K, B, H); w per layer (K, I + H, 4H) with the gate
// columns i, f, o, 2g; b (K, 1, 4H); the feedback head w_fb (K, H, O), b_fb (K, 1, O).
#include <torch/extension.h>

#include <memory>
#include <vector>

using at::Tensor;
using TensorList = std::vector<Tensor>;

namespace {

constexpr int64_t JOINTS = 7;

struct Layer {
  Tensor xh, gd, o_dt, sig;  // the step's [x, h], local derivatives (stm.lstm_step._stack_forward), gate sigmoids
};

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

// A layer's weight gradient from the rows ([x, h] (K, N, I + H), d gates (K, N, 4H)) of a chunk of steps: one
// product per chunk, handed to autograd, which sums the chunks'. (Deferring all rows to one product after the
// unroll, as the Python steps do, would copy every row once more into one tensor: as much time as it saves.)
void weight_gradient(const Tensor& xh, const Tensor& dg, Tensor& dw, Tensor& db) {
  dw = at::bmm(xh.transpose(1, 2), dg);
  db = dg.sum(1, true);
}

// The LSTM cell's elementwise maths in plain loops, one pass before ATen's tanh and one after, instead of a
// dozen ATen calls: the same arithmetic, operation for operation, as those calls of stm.lstm_step (addcmul(a, b,
// c, value) is a + value * b * c), so the results are those of the Python steps. sig (R, 4H) holds the gate
// sigmoids i, f, o and sigmoid(2 g_pre), so that g = 2 s - 1; rows R = K * B, all contiguous.
template <typename T>
void cell_pass1(const T* sig, const T* c, T* c_new, int64_t R, int64_t H) {
  for (int64_t r = 0; r < R; ++r) {
    const T* s = sig + r * 4 * H;
    const T* cr = c + r * H;
    T* cn = c_new + r * H;
    for (int64_t j = 0; j < H; ++j) cn[j] = s[H + j] * cr[j] + s[j] * (s[3 * H + j] * T(2) - T(1));
  }
}

// h = o tanh(c'); gd = [g, c, tanh(c'), 2 i] * s (1 - s) (the local derivatives of the pre-activations);
// o_dt = o (1 - tanh(c')^2).
template <typename T>
void cell_pass2(const T* sig, const T* c, const T* tc, T* h, T* gd, T* o_dt, int64_t R, int64_t H) {
  for (int64_t r = 0; r < R; ++r) {
    const T* s = sig + r * 4 * H;
    const T* cr = c + r * H;
    const T* tr = tc + r * H;
    T* hr = h + r * H;
    T* od = o_dt + r * H;
    T* d = gd + r * 4 * H;
    for (int64_t j = 0; j < H; ++j) {
      const T si = s[j], sf = s[H + j], so = s[2 * H + j], sg = s[3 * H + j];
      const T hv = so * tr[j];
      hr[j] = hv;
      od[j] = so + (-hv) * tr[j];
      d[j] = (sg * T(2) - T(1)) * (si + (-si) * si);
      d[H + j] = cr[j] * (sf + (-sf) * sf);
      d[2 * H + j] = tr[j] * (so + (-so) * so);
      d[3 * H + j] = (si * T(2)) * (sg + (-sg) * sg);
    }
  }
}

// dc = gc + o_dt dh (o_dt dh without gc); d gates = [dc, dc, dh, dc] * gd; the cell state's gradient dc f.
template <typename T>
void cell_backward_loop(const T* sig, const T* gd, const T* o_dt, const T* dh, const T* gc, T* dgates, T* grad_c,
                        int64_t R, int64_t H) {
  for (int64_t r = 0; r < R; ++r) {
    const T* s = sig + r * 4 * H;
    const T* d = gd + r * 4 * H;
    const T* od = o_dt + r * H;
    const T* dhr = dh + r * H;
    T* dg = dgates + r * 4 * H;
    T* gcr = grad_c + r * H;
    if (gc != nullptr) {
      const T* gcin = gc + r * H;
      for (int64_t j = 0; j < H; ++j) {
        const T dc = gcin[j] + od[j] * dhr[j];
        dg[j] = dc * d[j];
        dg[H + j] = dc * d[H + j];
        dg[2 * H + j] = dhr[j] * d[2 * H + j];
        dg[3 * H + j] = dc * d[3 * H + j];
        gcr[j] = dc * s[H + j];
      }
    } else {
      for (int64_t j = 0; j < H; ++j) {
        const T dc = od[j] * dhr[j];
        dg[j] = dc * d[j];
        dg[H + j] = dc * d[H + j];
        dg[2 * H + j] = dhr[j] * d[2 * H + j];
        dg[3 * H + j] = dc * d[3 * H + j];
        gcr[j] = dc * s[H + j];
      }
    }
  }
}

// One cell forward from the gate sigmoids: h', c', and the saved gd, o_dt (sig is saved too: f).
void cell_forward(const Tensor& sig, const Tensor& c_in, Tensor& h, Tensor& c_new, Tensor& gd, Tensor& o_dt) {
  const auto c = c_in.contiguous();
  const int64_t H = c.size(-1), R = c.numel() / H;
  c_new = at::empty_like(c);
  AT_DISPATCH_FLOATING_TYPES(sig.scalar_type(), "cell_pass1", [&] {
    cell_pass1<scalar_t>(sig.data_ptr<scalar_t>(), c.data_ptr<scalar_t>(), c_new.data_ptr<scalar_t>(), R, H);
  });
  const auto tc = at::tanh(c_new);
  h = at::empty_like(c);
  o_dt = at::empty_like(c);
  gd = at::empty_like(sig);
  AT_DISPATCH_FLOATING_TYPES(sig.scalar_type(), "cell_pass2", [&] {
    cell_pass2<scalar_t>(sig.data_ptr<scalar_t>(), c.data_ptr<scalar_t>(), tc.data_ptr<scalar_t>(),
                         h.data_ptr<scalar_t>(), gd.data_ptr<scalar_t>(), o_dt.data_ptr<scalar_t>(), R, H);
  });
}

// One cell backward: d gates (K, B, 4H) and the gradient of the previous cell state, from dh (defined) and gc.
std::pair<Tensor, Tensor> cell_backward(const Tensor& sig, const Tensor& gd, const Tensor& o_dt, const Tensor& dh_in,
                                        const Tensor& gc_in) {
  const auto dh = dh_in.contiguous();
  const Tensor gc = gc_in.defined() ? gc_in.contiguous() : Tensor();
  const int64_t H = o_dt.size(-1), R = o_dt.numel() / H;
  auto dgates = at::empty_like(sig);
  auto grad_c = at::empty_like(o_dt);
  AT_DISPATCH_FLOATING_TYPES(sig.scalar_type(), "cell_backward", [&] {
    cell_backward_loop<scalar_t>(sig.data_ptr<scalar_t>(), gd.data_ptr<scalar_t>(), o_dt.data_ptr<scalar_t>(),
                                 dh.data_ptr<scalar_t>(), gc.defined() ? gc.data_ptr<scalar_t>() : nullptr,
                                 dgates.data_ptr<scalar_t>(), grad_c.data_ptr<scalar_t>(), R, H);
  });
  return {dgates, grad_c};
}

// One step of the stack, bottom layer first (stm.lstm_step._stack_forward).
Tensor stack_forward(Tensor inp, TensorList& h, TensorList& c, const TensorList& ws, const TensorList& bs,
                     std::vector<Layer>& saved) {
  for (size_t k = 0; k < h.size(); ++k) {
    auto xh = at::cat({inp, h[k]}, -1);
    auto sig = at::baddbmm(bs[k], xh, ws[k]);
    sig.sigmoid_();
    Tensor c_new, gd, o_dt;
    cell_forward(sig, c[k], inp, c_new, gd, o_dt);
    saved.push_back({xh, gd, o_dt, sig});
    h[k] = inp;
    c[k] = c_new;
  }
  return inp;
}

// The backward of one step, top layer first (stm.lstm_step._stack_backward): gh, gc in, the gradients of the
// step's inputs out; dgs[k] = layer k's d gates; returns d x (undefined unless need_x).
Tensor stack_backward(TensorList& gh, TensorList& gc, const TensorList& ws, const std::vector<Layer>& saved,
                      bool need_x, TensorList& dgs) {
  const int64_t L = static_cast<int64_t>(saved.size());
  Tensor below;
  for (int64_t k = L - 1; k >= 0; --k) {
    const auto& s = saved[k];
    Tensor dh;
    if (!gh[k].defined()) {
      dh = below.defined() ? below : at::zeros_like(s.o_dt);
    } else {
      dh = below.defined() ? gh[k] + below : gh[k];
    }
    auto dg_gc = cell_backward(s.sig, s.gd, s.o_dt, dh, gc[k]);
    const auto& dgates = dg_gc.first;
    gc[k] = dg_gc.second;
    const int64_t H = s.o_dt.size(-1);
    const int64_t d_in = s.xh.size(-1) - H;
    if (k > 0 || need_x) {
      auto dxh = at::matmul(dgates, ws[k].transpose(-2, -1));
      below = dxh.narrow(-1, 0, d_in);
      gh[k] = dxh.narrow(-1, d_in, H);
    } else {  // a detached input: only the recurrent part
      below = Tensor();
      gh[k] = at::matmul(dgates, ws[k].narrow(-2, d_in, H).transpose(-2, -1));
    }
    dgs[k] = dgates;
  }
  return below;
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

// Known inputs (ground truth) through the stack, n steps: layer by layer, the input projection of all steps as one
// product and only the recurrent part stepped (stm.packed_lstm_step._LayerSeq, op for op). For short runs between
// self-fed segments this beats oneDNN's fused layer, whose set-up costs more than its five steps.
struct SeqLayer {
  Tensor x, h0, out;             // input (K, B, n, I), initial h, outputs (K, B, n, H)
  TensorList gd, o_dt, sig;      // per step
};

struct Sequence {
  TensorList ws;
  std::vector<SeqLayer> layers;
};

std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Sequence>> sequence_forward(
    Tensor x, TensorList h, TensorList c, const TensorList& ws, const TensorList& bs) {
  auto seq = std::make_shared<Sequence>();
  seq->ws = ws;
  const int64_t K = x.size(0), B = x.size(1), n = x.size(2), H = h[0].size(-1);
  for (size_t k = 0; k < h.size(); ++k) {
    const int64_t I = x.size(3);
    SeqLayer lay;
    lay.x = x;
    lay.h0 = h[k];
    auto w_x = ws[k].narrow(1, 0, I);
    auto w_h = ws[k].narrow(1, I, H).contiguous();
    auto proj = at::baddbmm(bs[k], x.reshape({K, B * n, I}), w_x).view({K, B, n, 4 * H});
    Tensor hk = h[k], ck = c[k];
    TensorList hs;
    for (int64_t t = 0; t < n; ++t) {
      auto sig = at::baddbmm(proj.select(2, t), hk, w_h);
      sig.sigmoid_();
      Tensor h_new, c_new, gd, o_dt;
      cell_forward(sig, ck, h_new, c_new, gd, o_dt);
      lay.gd.push_back(gd);
      lay.o_dt.push_back(o_dt);
      lay.sig.push_back(sig);
      hs.push_back(h_new);
      hk = h_new;
      ck = c_new;
    }
    lay.out = at::stack(hs, 2);
    x = lay.out;
    h[k] = hk;
    c[k] = ck;
    seq->layers.push_back(std::move(lay));
  }
  return {x, h, c, seq};
}

// Gradients of the initial h, c and of w, b per layer; the inputs' gradient is not needed (known inputs).
std::tuple<TensorList, TensorList, TensorList, TensorList> sequence_backward(
    const std::shared_ptr<Sequence>& seq, const c10::optional<Tensor>& g_out_top,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c) {
  const int64_t L = static_cast<int64_t>(seq->layers.size());
  TensorList dh0(L), dc0(L), dw(L), db(L);
  Tensor g_out = g_out_top.has_value() ? *g_out_top : Tensor();
  for (int64_t k = L - 1; k >= 0; --k) {
    const auto& lay = seq->layers[k];
    const int64_t K = lay.x.size(0), B = lay.x.size(1), n = lay.x.size(2), I = lay.x.size(3);
    const int64_t H = lay.h0.size(-1);
    auto w_hT = seq->ws[k].narrow(1, I, H).transpose(1, 2).contiguous();
    Tensor dh_rec = g_h[k].has_value() ? *g_h[k] : at::zeros_like(lay.h0);
    Tensor dc = g_c[k].has_value() ? *g_c[k] : at::zeros_like(lay.h0);
    TensorList dgs(n);
    for (int64_t t = n - 1; t >= 0; --t) {
      auto dh = g_out.defined() ? dh_rec + g_out.select(2, t) : dh_rec;
      auto dg_gc = cell_backward(lay.sig[t], lay.gd[t], lay.o_dt[t], dh, dc);
      dgs[t] = dg_gc.first;
      dc = dg_gc.second;
      dh_rec = at::bmm(dg_gc.first, w_hT);
    }
    auto dg = at::stack(dgs, 2).view({K, B * n, 4 * H});
    auto h_prev = at::cat({lay.h0.unsqueeze(2), lay.out.narrow(2, 0, n - 1)}, 2).reshape({K, B * n, H});
    weight_gradient(at::cat({lay.x.reshape({K, B * n, I}), h_prev}, -1), dg, dw[k], db[k]);
    if (k > 0) g_out = at::bmm(dg, seq->ws[k].narrow(1, 0, I).transpose(1, 2)).view({K, B, n, I});
    dh0[k] = dh_rec;
    dc0[k] = dc;
  }
  return {dh0, dc0, dw, db};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  pybind11::class_<Segment, std::shared_ptr<Segment>>(module, "Segment");
  module.def("segment_forward", &segment_forward, "self-fed segment, forward");
  module.def("segment_backward", &segment_backward, "self-fed segment, backward");
  pybind11::class_<Sequence, std::shared_ptr<Sequence>>(module, "Sequence");
  module.def("sequence_forward", &sequence_forward, "known inputs through the stack, forward");
  module.def("sequence_backward", &sequence_backward, "known inputs through the stack, backward");
}
