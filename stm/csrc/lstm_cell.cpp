// The LSTM stack of the C++ steps: see lstm_cell.h. (Edit this file with the header: the build is keyed on the
// sources only.)
#include "lstm_cell.h"

#include <ATen/Dispatch.h>

namespace stm_cpp {
namespace {

// The LSTM cell's elementwise maths in plain loops, one pass before ATen's tanh and one after, instead of a
// dozen ATen calls: the same arithmetic, operation for operation, as those calls of stm.lstm_step (addcmul(a, b,
// c, value) is a + value * b * c), so the results are those of the Python steps. sig (R, 4H) holds the gate
// sigmoids i, f, o and sigmoid(2 g_pre), so that g = 2 s - 1; rows R = K * B, all contiguous. The pointers are
// __restrict__ (each loop's outputs are fresh tensors): without it the compiler, unable to rule out that the six
// or seven arrays overlap, leaves the loops scalar; with it they run four floats at a time, elementwise as before
// (no sum reordered, so the results are bitwise those of the scalar loops).
template <typename T>
void cell_pass1(const T* __restrict__ sig, const T* __restrict__ c, T* __restrict__ c_new, int64_t R, int64_t H) {
  for (int64_t r = 0; r < R; ++r) {
    const T* __restrict__ s = sig + r * 4 * H;
    const T* __restrict__ cr = c + r * H;
    T* __restrict__ cn = c_new + r * H;
    for (int64_t j = 0; j < H; ++j) cn[j] = s[H + j] * cr[j] + s[j] * (s[3 * H + j] * T(2) - T(1));
  }
}

// h = o tanh(c'); gd = [g, c, tanh(c'), 2 i] * s (1 - s) (the local derivatives of the pre-activations);
// o_dt = o (1 - tanh(c')^2).
template <typename T>
void cell_pass2(const T* __restrict__ sig, const T* __restrict__ c, const T* __restrict__ tc, T* __restrict__ h,
                T* __restrict__ gd, T* __restrict__ o_dt, int64_t R, int64_t H) {
  for (int64_t r = 0; r < R; ++r) {
    const T* __restrict__ s = sig + r * 4 * H;
    const T* __restrict__ cr = c + r * H;
    const T* __restrict__ tr = tc + r * H;
    T* __restrict__ hr = h + r * H;
    T* __restrict__ od = o_dt + r * H;
    T* __restrict__ d = gd + r * 4 * H;
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
void cell_backward_loop(const T* __restrict__ sig, const T* __restrict__ gd, const T* __restrict__ o_dt,
                        const T* __restrict__ dh, const T* __restrict__ gc, T* __restrict__ dgates,
                        T* __restrict__ grad_c, int64_t R, int64_t H) {
  for (int64_t r = 0; r < R; ++r) {
    const T* __restrict__ s = sig + r * 4 * H;
    const T* __restrict__ d = gd + r * 4 * H;
    const T* __restrict__ od = o_dt + r * H;
    const T* __restrict__ dhr = dh + r * H;
    T* __restrict__ dg = dgates + r * 4 * H;
    T* __restrict__ gcr = grad_c + r * H;
    if (gc != nullptr) {
      const T* __restrict__ gcin = gc + r * H;
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

}  // namespace

// A layer's weight gradient from the rows ([x, h] (K, N, I + H), d gates (K, N, 4H)) of a chunk of steps: one
// product per chunk, handed to autograd, which sums the chunks'. (Deferring all rows to one product after the
// unroll, as the Python steps do, would copy every row once more into one tensor: as much time as it saves.)
void weight_gradient(const Tensor& xh, const Tensor& dg, Tensor& dw, Tensor& db) {
  dw = at::bmm(xh.transpose(1, 2), dg);
  db = dg.sum(1, true);
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


std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Sequence>> sequence_forward(
    Tensor x, TensorList h, TensorList c, const TensorList& ws, const TensorList& bs, const TensorList& w_h_in,
    const TensorList& w_hT) {
  auto seq = std::make_shared<Sequence>();
  seq->ws = ws;
  seq->w_hT = w_hT;
  const int64_t K = x.size(0), B = x.size(1), n = x.size(2), H = h[0].size(-1);
  for (size_t k = 0; k < h.size(); ++k) {
    const int64_t I = x.size(3);
    SeqLayer lay;
    lay.x = x;
    lay.h0 = h[k];
    auto w_x = ws[k].narrow(1, 0, I);
    auto w_h = w_h_in.empty() ? ws[k].narrow(1, I, H).contiguous() : w_h_in[k];
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
    auto w_hT = seq->w_hT.empty() ? seq->ws[k].narrow(1, I, H).transpose(1, 2).contiguous() : seq->w_hT[k];
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


}  // namespace stm_cpp
