// The LSTM stack of the C++ steps: see lstm_step.h. (Edit this file with the header: the build is keyed on the
// sources only.)
#include "lstm_step.h"

#include "rows.h"
#include "vec_math.h"

#include <ATen/Dispatch.h>

#include <algorithm>
#include <cstdint>
#include <cstring>

namespace stm_cpp {
namespace {

// The LSTM step's elementwise maths in plain loops, one pass before ATen's tanh and one after, instead of a
// dozen ATen calls: the same arithmetic, operation for operation, as those calls of stm.lstm_step (addcmul(a, b,
// c, value) is a + value * b * c), so the results are those of the Python steps. s holds a row's gate sigmoids
// i, f, o and sigmoid(2 g_pre), so that g = 2 s - 1. The pointers are __restrict__ (each row's outputs are
// other memory than its inputs): without it the compiler, unable to rule out that the arrays overlap, leaves the
// loops scalar; with it they run four floats at a time, elementwise as before (no sum reordered, so the results
// are bitwise those of the scalar loops).
template <typename T>
void pass1_row(const T* __restrict__ s, const T* __restrict__ cr, T* __restrict__ cn, int64_t H) {
  for (int64_t j = 0; j < H; ++j) cn[j] = s[H + j] * cr[j] + s[j] * (s[3 * H + j] * T(2) - T(1));
}

// h = o tanh(c') (also into h2 with COPY: a store in the loop is cheaper than a memcpy per row).
template <typename T, bool COPY>
void pass2_row(const T* __restrict__ s, const T* __restrict__ tr, T* __restrict__ hr, T* __restrict__ h2,
               int64_t H) {
  for (int64_t j = 0; j < H; ++j) {
    const T hv = s[2 * H + j] * tr[j];
    hr[j] = hv;
    if (COPY) h2[j] = hv;
  }
}

// dh = dh_a (+ dh_b); dc = gc + o_dt dh (o_dt dh without gc), o_dt = o (1 - tanh(c')^2); d gates = [dc, dc, dh,
// dc] * [g, c, tanh(c'), 2 i] * s (1 - s) (the local derivatives of the pre-activations); the cell state's
// gradient dc f. The derivatives recomputed from s, c and tanh(c') as the forward computed them before they were
// dropped from its stores (the same operations in the same order: the same values). Templated on which inputs
// exist, so that the loop has no branch and stays vectorised.
template <typename T, bool HAS_GC, bool HAS_DH_B>
void backward_row(const T* __restrict__ s, const T* __restrict__ cr, const T* __restrict__ tr,
                  const T* __restrict__ dha, const T* __restrict__ dhb, const T* __restrict__ gcin,
                  T* __restrict__ dg, T* __restrict__ gcr, int64_t H) {
  for (int64_t j = 0; j < H; ++j) {
    const T si = s[j], sf = s[H + j], so = s[2 * H + j], sg = s[3 * H + j], t = tr[j];
    const T od = so + (-(so * t)) * t;
    const T dh = HAS_DH_B ? dha[j] + dhb[j] : dha[j];
    const T dc = HAS_GC ? gcin[j] + od * dh : od * dh;
    dg[j] = dc * ((sg * T(2) - T(1)) * (si + (-si) * si));
    dg[H + j] = dc * (cr[j] * (sf + (-sf) * sf));
    dg[2 * H + j] = dh * (t * (so + (-so) * so));
    dg[3 * H + j] = dc * ((si * T(2)) * (sg + (-sg) * sg));
    gcr[j] = dc * sf;
  }
}

template <typename T, bool HAS_GC, bool HAS_DH_B>
void backward_rows(const Rows<T>& sig, const Rows<T>& c, const Rows<T>& tc, const Rows<T>& dha,
                   const Rows<T>& dhb, const Rows<T>& gc, const Rows<T>& dg, const Rows<T>& gcr, int64_t K,
                   int64_t B, int64_t H) {
  for (int64_t k = 0; k < K; ++k) {
    for (int64_t b = 0; b < B; ++b) {
      backward_row<T, HAS_GC, HAS_DH_B>(sig.at(k, b), c.at(k, b), tc.at(k, b), dha.at(k, b),
                                        HAS_DH_B ? dhb.at(k, b) : nullptr, HAS_GC ? gc.at(k, b) : nullptr,
                                        dg.at(k, b), gcr.at(k, b), H);
    }
  }
}

}  // namespace

Cells run_cells(const Tensor& c0, int64_t n) {
  Cells cells;
  cells.c0 = rows_ready(c0);
  const int64_t K = c0.size(0), B = c0.size(1), H = c0.size(2);
  cells.cs = at::empty({std::max<int64_t>(n - 1, 1), K, B, H}, c0.options());
  cells.tcs = at::empty({n, K, B, H}, c0.options());
  cells.last = at::empty({K, B, H}, c0.options());
  cells.n = n;
  return cells;
}

Pair block_pair(at::IntArrayRef sizes, const at::TensorOptions& options) {
  return {at::empty(sizes, options), at::empty(sizes, options)};
}

Tensor rows_ready(const Tensor& t) { return t.stride(-1) == 1 ? t : t.contiguous(); }

Tensor bias_rows(const Tensor& b, int64_t P, int64_t Q) {
  const auto bc = b.contiguous();
  const int64_t K = bc.size(0), X = bc.size(-1);
  TORCH_CHECK(bc.numel() == K * X, "bias_rows: a (K, 1, X) bias");
  auto out = at::empty({P, K, Q, X}, bc.options());
  const auto* src = static_cast<const char*>(bc.data_ptr());
  auto* dst = static_cast<char*>(out.data_ptr());
  const int64_t row = X * static_cast<int64_t>(bc.element_size());
  for (int64_t p = 0; p < P; ++p)
    for (int64_t k = 0; k < K; ++k)
      for (int64_t q = 0; q < Q; ++q) std::memcpy(dst + ((p * K + k) * Q + q) * row, src + k * row, row);
  return out;
}

namespace {

// c10::BFloat16's rounding (to nearest even; NaN to a quiet NaN) on the bits, branch-free so that the loop
// vectorises (through the constructor it stays scalar).
inline uint16_t bf16_bits(float f) {
  uint32_t u = 0;
  std::memcpy(&u, &f, sizeof u);
  const auto rounded = static_cast<uint16_t>((u + 0x7FFFU + ((u >> 16) & 1U)) >> 16);
  return f != f ? static_cast<uint16_t>(0x7FC0) : rounded;  // NOLINT(misc-redundant-expression): NaN
}

}  // namespace

void to_low(const Block& src, const Block& dst, int64_t K, int64_t B, int64_t X) {
  const auto s = rows<float>(src);
  const auto d = rows<at::BFloat16>(dst);
  for (int64_t k = 0; k < K; ++k) {
    for (int64_t b = 0; b < B; ++b) {
      const float* __restrict__ in = s.at(k, b);
      auto* __restrict__ out = reinterpret_cast<uint16_t*>(d.at(k, b));
      for (int64_t j = 0; j < X; ++j) out[j] = bf16_bits(in[j]);
    }
  }
}

void step_forward(const Block& sig, const Block& c, const Block& c_new, const Block& tc, const Block& h,
                  const Block& h2, int64_t K, int64_t B, int64_t H) {
  TORCH_CHECK((K == 1 || (c_new.sk == B * H && tc.sk == B * H)) && (B == 1 || (c_new.sb == H && tc.sb == H)),
              "step_forward: c_new, tc contiguous");
  sigmoid_block(sig, K, B, 4 * H);
  AT_DISPATCH_FLOATING_TYPES(sig.dtype, "step_pass1", [&] {
    const auto s = rows<scalar_t>(sig), cr = rows<scalar_t>(c), cn = rows<scalar_t>(c_new);
    for (int64_t k = 0; k < K; ++k)
      for (int64_t b = 0; b < B; ++b) pass1_row<scalar_t>(s.at(k, b), cr.at(k, b), cn.at(k, b), H);
  });
  tanh_into(c_new.data, tc.data, K * B * H, c_new.dtype);
  AT_DISPATCH_FLOATING_TYPES(sig.dtype, "step_pass2", [&] {
    const auto s = rows<scalar_t>(sig), tr = rows<scalar_t>(tc), hr = rows<scalar_t>(h), h2r = rows<scalar_t>(h2);
    for (int64_t k = 0; k < K; ++k) {
      for (int64_t b = 0; b < B; ++b) {
        if (h2r.p != nullptr) pass2_row<scalar_t, true>(s.at(k, b), tr.at(k, b), hr.at(k, b), h2r.at(k, b), H);
        else pass2_row<scalar_t, false>(s.at(k, b), tr.at(k, b), hr.at(k, b), nullptr, H);
      }
    }
  });
}

void step_backward(const Block& sig, const Block& c, const Block& tc, const Block& dh_a, const Block& dh_b,
                   const Block& gc, const Block& dgates, const Tensor& grad_c) {
  const int64_t K = grad_c.size(0), B = grad_c.size(1), H = grad_c.size(2);
  const bool has_gc = gc.data != nullptr, has_dh_b = dh_b.data != nullptr;
  AT_DISPATCH_FLOATING_TYPES(grad_c.scalar_type(), "step_backward", [&] {
    using T = scalar_t;
    const auto s = rows<T>(sig), cr = rows<T>(c), tr = rows<T>(tc), a = rows<T>(dh_a), b = rows<T>(dh_b),
               g = rows<T>(gc), dg = rows<T>(dgates), gr = rows<T>(grad_c);
    if (has_gc && has_dh_b) backward_rows<T, true, true>(s, cr, tr, a, b, g, dg, gr, K, B, H);
    else if (has_gc) backward_rows<T, true, false>(s, cr, tr, a, b, g, dg, gr, K, B, H);
    else if (has_dh_b) backward_rows<T, false, true>(s, cr, tr, a, b, g, dg, gr, K, B, H);
    else backward_rows<T, false, false>(s, cr, tr, a, b, g, dg, gr, K, B, H);
  });
}

namespace {

// db (K, 1, X) += the sum of the rows of dg (K, N, X), in a plain loop: ATen's sum and add cost a copy and a pass
// more.
template <typename T>
void add_rows(const T* __restrict__ src, T* __restrict__ dst, int64_t X) {
  for (int64_t j = 0; j < X; ++j) dst[j] += src[j];
}

void add_row_sums(const Mat& dg, const Tensor& db) {
  TORCH_CHECK(dg.sc == 1 && db.is_contiguous() && db.scalar_type() == dg.dtype,
              "add_row_sums: rows of (K, N, X) into (K, 1, X)");
  const int64_t K = dg.K, N = dg.R, X = dg.C;
  AT_DISPATCH_FLOATING_TYPES(dg.dtype, "add_row_sums", [&] {
    const auto* src = static_cast<const scalar_t*>(dg.p);
    auto* dst = db.data_ptr<scalar_t>();
    for (int64_t k = 0; k < K; ++k)
      for (int64_t r = 0; r < N; ++r) add_rows<scalar_t>(src + k * dg.sk + r * dg.sr, dst + k * X, X);
  });
}

}  // namespace

// One product per chunk. Summed in place over an unroll's chunks (the product's beta = 1) rather than each handed to
// autograd, which adds them: one pass over the gradient per chunk and layer less. (Deferring all rows to one product
// after the unroll, as the Python steps do, would copy every row once more into one tensor: as much time as it
// saves.)
void weight_gradient(const Mat& xh, const Mat& dg, Tensor& dw, Tensor& db, const Mat& xh_low, const Mat& dg_low) {
  const bool low = xh_low.p != nullptr, first = !dw.defined();
  if (first) {
    const auto opt = at::TensorOptions().dtype(dg.dtype);
    dw = at::empty({dg.K, low ? xh_low.C : xh.C, dg.C}, opt);
    db = at::zeros({dg.K, 1, dg.C}, opt);
  }
  if (low) low_bmm(dw, xh_low.t(), dg_low, !first);
  else gemm(dw, xh.t(), dg, first ? 0.0 : 1.0);
  add_row_sums(dg, db);
}

namespace {

// The layers' [x, h] buffers of a sequence: x of the bottom layer and each layer's initial h copied in; the
// rest is written by the steps.
std::vector<SeqLayer> sequence_layers(const Tensor& x, const TensorList& h, const TensorList& ws) {
  const int64_t K = x.size(0), B = x.size(1), n = x.size(2), H = h[0].size(-1);
  std::vector<SeqLayer> layers(h.size());
  for (size_t k = 0; k < h.size(); ++k) {
    auto& lay = layers[k];
    lay.inputs = ws[k].size(1) - H;
    lay.xh = at::empty({K, B, n, lay.inputs + H}, x.options());
    lay.xh.select(2, 0).narrow(-1, lay.inputs, H).copy_(h[k]);
  }
  layers[0].xh.narrow(-1, 0, layers[0].inputs).copy_(x);
  return layers;
}

// Layer k of a sequence, all n steps: each step's h into the next layer's x (the top's into out) and into its own
// [x, h] of the next step (after the last: h_last); c alternates between two blocks, the last returned.
// With w_low (w in bf16) the products take bf16 operands: xh's in xh_low, the x part of all steps at once, the h
// part step by step.
Tensor sequence_layer(std::vector<SeqLayer>& layers, size_t k, const Tensor& c0, const Tensor& w, const Tensor& b,
                      const Tensor& w_h, const Tensor& w_low, const Tensor& out, const Tensor& h_last) {
  auto& lay = layers[k];
  const int64_t K = lay.xh.size(0), B = lay.xh.size(1), n = lay.xh.size(2), I = lay.inputs, H = h_last.size(-1);
  auto x = lay.xh.narrow(-1, 0, I).view({K, B * n, I});
  if (w_low.defined()) {  // the bias in float32, the input projection added to it
    lay.xh_low = at::empty(lay.xh.sizes(), lay.xh.options().dtype(at::kBFloat16));
    auto x_low = lay.xh_low.narrow(-1, 0, I);
    x_low.copy_(lay.xh.narrow(-1, 0, I));
    lay.sig = bias_rows(b, 1, B * n).view({K, B * n, 4 * H});
    low_bmm(lay.sig, x_low.view({K, B * n, I}), w_low.narrow(1, 0, I), true);
    lay.sig = lay.sig.view({K, B, n, 4 * H});
  } else {
    lay.sig = bias_rows(b, 1, B * n).view({K, B * n, 4 * H});
    at::baddbmm_out(lay.sig, lay.sig, x, w.narrow(1, 0, I));
    lay.sig = lay.sig.view({K, B, n, 4 * H});
  }
  lay.cells = run_cells(c0, n);
  const Mat w_rec = w_low.defined() ? Mat(w_low).rows(I, H) : Mat(w_h);
  for (int64_t t = 0; t < n; ++t) {
    const Block sig = slice(lay.sig, 2, t);
    if (w_low.defined()) {
      to_low(slice(lay.xh, 2, t, I), slice(lay.xh_low, 2, t, I), K, B, H);
      low_bmm(Mat(sig, K, B, 4 * H), Mat(slice(lay.xh_low, 2, t, I), K, B, H), w_rec, true);
    } else {  // the projection in place
      gemm(Mat(sig, K, B, 4 * H), Mat(slice(lay.xh, 2, t, I), K, B, H), w_rec, 1.0);
    }
    const Block up = k + 1 < layers.size() ? slice(layers[k + 1].xh, 2, t) : slice(out, 2, t);
    const Block next = t + 1 < n ? slice(lay.xh, 2, t + 1, I) : Block(h_last);
    step_forward(sig, lay.cells.before(t), lay.cells.after(t), lay.cells.tanh_after(t), up, next, K, B, H);
  }
  return lay.cells.last;
}

}  // namespace

std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Sequence>> sequence_forward(
    Tensor x, TensorList h, TensorList c, const TensorList& ws, const TensorList& bs, const TensorList& w_h_in,
    const TensorList& w_hT, const TensorList& low) {
  const at::AutoDispatchBelowADInplaceOrView below_autograd;  // see lstm_step.h
  auto seq = std::make_shared<Sequence>();
  seq->ws = ws;
  seq->w_hT = w_hT;
  seq->low = low;
  const int64_t K = x.size(0), B = x.size(1), n = x.size(2), H = h[0].size(-1);
  seq->layers = sequence_layers(x, h, ws);
  const auto out = at::empty({K, B, n, H}, x.options());
  for (size_t k = 0; k < h.size(); ++k) {
    const int64_t I = seq->layers[k].inputs;
    const Tensor w_low = low.empty() ? Tensor() : low[k];
    auto w_h = w_low.defined() ? Tensor() : w_h_in.empty() ? ws[k].narrow(1, I, H).contiguous() : w_h_in[k];
    h[k] = at::empty({K, B, H}, x.options());
    c[k] = sequence_layer(seq->layers, k, c[k], ws[k], bs[k], w_h, w_low, out, h[k]);
  }
  return {out, h, c, seq};
}

// Gradients of the initial h, c and of w, b per layer; the inputs' gradient is not needed (known inputs).
std::tuple<TensorList, TensorList, TensorList, TensorList> sequence_backward(
    const std::shared_ptr<Sequence>& seq, const c10::optional<Tensor>& g_out_top,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c, TensorList dw,
    TensorList db) {
  const at::AutoDispatchBelowADInplaceOrView below_autograd;  // see lstm_step.h
  const int64_t L = static_cast<int64_t>(seq->layers.size());
  TensorList dh0(L), dc0(L);
  dw.resize(L);
  db.resize(L);
  Tensor g_out = g_out_top.has_value() ? rows_ready(*g_out_top) : Tensor();
  for (int64_t k = L - 1; k >= 0; --k) {
    const auto& lay = seq->layers[k];
    const int64_t K = lay.xh.size(0), B = lay.xh.size(1), n = lay.xh.size(2), I = lay.inputs;
    const int64_t H = lay.cells.c0.size(-1);
    const auto opt = lay.cells.c0.options();
    const Tensor w_low = seq->low.empty() ? Tensor() : seq->low[k];
    auto w_hT = w_low.defined()     ? w_low.narrow(1, I, H).transpose(1, 2)
                : seq->w_hT.empty() ? seq->ws[k].narrow(1, I, H).transpose(1, 2).contiguous()
                                    : seq->w_hT[k];
    Tensor dh_rec = g_h[k].has_value() ? rows_ready(*g_h[k]) : at::zeros({K, B, H}, opt);
    Tensor dc = g_c[k].has_value() ? rows_ready(*g_c[k]) : Tensor();
    // d gates straight into the rows of the weight gradient; dh, dc alternating between two blocks each
    const auto dg = at::empty({K, B, n, 4 * H}, opt);
    const auto dg_low = w_low.defined() ? at::empty({K, B, n, 4 * H}, opt.dtype(at::kBFloat16)) : Tensor();
    auto dhs = block_pair({K, B, H}, opt);
    const auto dcs = block_pair({K, B, H}, opt);
    const Mat w_recT(w_hT);
    for (int64_t t = n - 1; t >= 0; --t) {
      const Block dg_t = slice(dg, 2, t);
      step_backward(slice(lay.sig, 2, t), lay.cells.before(t), lay.cells.tanh_after(t), dh_rec,
                    g_out.defined() ? slice(g_out, 2, t) : Block(), dc, dg_t, dcs[t % 2]);
      dc = dcs[t % 2];
      if (w_low.defined()) {
        to_low(dg_t, slice(dg_low, 2, t), K, B, 4 * H);
        low_bmm(dhs[t % 2], Mat(slice(dg_low, 2, t), K, B, 4 * H), w_recT, false);
      } else {
        gemm(dhs[t % 2], Mat(dg_t, K, B, 4 * H), w_recT);
      }
      dh_rec = dhs[t % 2];
    }
    const Mat dg_rows = rows_of(dg);
    if (k > 0) g_out = at::empty({K, B, n, I}, opt);  // the layer below's d h: d x of all steps, one product
    if (w_low.defined()) {
      const Mat dl_rows = rows_of(dg_low);
      weight_gradient(Mat(), dg_rows, dw[k], db[k], rows_of(lay.xh_low), dl_rows);
      if (k > 0) low_bmm(rows_of(g_out), dl_rows, Mat(w_low).rows(0, I).t(), false);
    } else {
      weight_gradient(rows_of(lay.xh), dg_rows, dw[k], db[k]);
      if (k > 0) gemm(rows_of(g_out), dg_rows, Mat(seq->ws[k]).rows(0, I).t());
    }
    dh0[k] = dh_rec;
    dc0[k] = dc.defined() ? dc : at::zeros({K, B, H}, opt);
  }
  return {dh0, dc0, dw, db};
}

}  // namespace stm_cpp
