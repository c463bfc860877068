// The LSTM stack of the C++ steps (stm/csrc/self_fed.cpp): one step's forward and backward on step blocks, and
// runs of known inputs layer by layer: per step no ATen call, the products issued to BLAS as ATen issues them
// (products.h), the gate nonlinearities as ATen computes them (vec_math.h) and the rest in plain loops.
//
// Shapes: K models of a pack, batch B. h, c per layer (K, B, H); w per layer (K, I + H, 4H) with the gate columns
// i, f, o, 2g (stm.lstm_step.gate_order); b (K, 1, 4H).
//
// A step block is a (K, B, X) tensor whose last dimension is contiguous; its K and B strides are free, so that a
// step's rows can be read from and written into a buffer of all the run's steps (a slice of it) without copies.
//
// below_autograd: the forward and backward entry points (here and in self_fed.cpp) dispatch their ATen calls below
// autograd (AutoDispatchBelowADInplaceOrView): the Python autograd Function is the graph's node, and its inner calls
// need none of autograd's per-call bookkeeping (a view's tracking, version counters), a good part of a small op's
// cost. Nothing here modifies a caller's tensor in place, so the untracked versions lose nothing.
#pragma once

#include <ATen/ATen.h>

#include <array>
#include <memory>
#include <tuple>
#include <vector>

#include "products.h"
#include "rows.h"
#include "vec_math.h"

namespace stm_cpp {

using at::Tensor;
using TensorList = std::vector<Tensor>;
using Pair = std::array<Tensor, 2>;

// Two contiguous blocks a run of steps alternates between (each step reads one and writes the other).
Pair block_pair(at::IntArrayRef sizes, const at::TensorOptions& options);

// A layer's cell states over a run of n steps, what its backward reads besides the gates' sigmoids: the local
// derivatives of the pre-activations and o (1 - tanh(c')^2) are recomputed from them there (the same arithmetic,
// so the same values) rather than stored per step: 2H values a row per step to write and read back, not 5H.
struct Cells {
  Tensor c0;    // before the first step (K, B, H), its rows contiguous
  Tensor cs;    // after steps 0 .. n - 2, (max(n - 1, 1), K, B, H)
  Tensor tcs;   // tanh of each step's new cell state, (n, K, B, H)
  Tensor last;  // after the last step (K, B, H): handed on to the next run
  int64_t n = 0;

  Block before(int64_t j) const { return j == 0 ? Block(c0) : slice(cs, 0, j - 1); }
  Block after(int64_t j) const { return j + 1 < n ? slice(cs, 0, j) : Block(last); }
  Block tanh_after(int64_t j) const { return slice(tcs, 0, j); }
};
// The cells of a run of n steps from c0 (K, B, H).
Cells run_cells(const Tensor& c0, int64_t n);

// One LSTM step forward from the gates' pre-activations sig (K, B, 4H), replaced by their sigmoids in place (what
// the backward reads): c_new, tc = tanh(c_new), h (and a copy of h in h2 where given). All are step blocks,
// written in place; c_new and tc contiguous (K, B, H).
void step_forward(const Block& sig, const Block& c, const Block& c_new, const Block& tc, const Block& h,
                  const Block& h2, int64_t K, int64_t B, int64_t H);
// One LSTM step backward: d gates and grad_c (K, B, H), the gradient of the previous cell state, from
// dh = dh_a (+ dh_b where given) and gc (none: zero); c the cell state before the step, tc tanh of the one after.
// Step blocks, the outputs written in place.
void step_backward(const Block& sig, const Block& c, const Block& tc, const Block& dh_a, const Block& dh_b,
                   const Block& gc, const Block& dgates, const Tensor& grad_c);
// t where its last dimension is contiguous, else a contiguous copy (gradients may come expanded).
Tensor rows_ready(const Tensor& t);
// A new contiguous (P, K, Q, X) tensor whose every row (p, k, q) is b[k] (b (K, 1, X)): the bias each
// product is added to. Row by row: ATen's copy of the broadcast bias costs several times as much.
Tensor bias_rows(const Tensor& b, int64_t P, int64_t Q);

// X float32 columns of a step block into a bfloat16 one, rounded to nearest even as ATen's cast: per step and layer
// an ATen copy's views and iterator set-up cost more than the conversion.
void to_low(const Block& src, const Block& dst, int64_t K, int64_t B, int64_t X);

// Known inputs (ground truth) through the stack, n steps: layer by layer, the input projection of all steps as one
// product and only the recurrent part stepped (stm.packed_lstm_step._LayerSeq, op for op). For short runs between
// self-fed segments this beats oneDNN's fused layer, whose set-up costs more than its five steps.
// Each layer's [x, h] rows (K, B, n, I + H) are written as the steps run (x by the layer below, h by the layer
// itself one step ahead): the input projection and the weight gradient read them in place. sig holds the input
// projection, each step's recurrent product added in place and its sigmoids taken there.
struct SeqLayer {
  Tensor xh, sig;     // (K, B, n, I + H), (K, B, n, 4H)
  Tensor xh_low;      // bf16 products: xh in bf16, the products' operand (undefined: float32 products)
  Cells cells;
  int64_t inputs = 0;  // I
};

struct Sequence {
  TensorList ws, w_hT;  // w_hT: each layer's recurrent weights transposed, contiguous (K, 4H, H)
  TensorList low;       // each layer's w in bf16, cast once per unroll (empty: float32 products)
  std::vector<SeqLayer> layers;
};

// A layer's weight gradient from a chunk's rows ([x, h] (K, N, I + H), d gates (K, N, 4H)): dw, db undefined: made
// here; defined: the unroll's sums so far, this chunk's added in place (stm.self_fed, _GradSums). With xh_low and
// dg_low (the rows in bf16) the product takes those.
void weight_gradient(const Mat& xh, const Mat& dg, Tensor& dw, Tensor& db, const Mat& xh_low = Mat(),
                     const Mat& dg_low = Mat());
// w_h, w_hT: per layer the recurrent rows of w, contiguous (K, H, 4H), and transposed, contiguous (K, 4H, H),
// made once per unroll by the caller (the weights are views whose rows a copy must gather: per call, one copy each
// per layer and chunk); empty lists: made here. low: each layer's w in bf16 for bf16 products (w_h, w_hT unused),
// empty for float32 ones.
std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Sequence>> sequence_forward(
    Tensor x, TensorList h, TensorList c, const TensorList& ws, const TensorList& bs, const TensorList& w_h,
    const TensorList& w_hT, const TensorList& low);
// dw, db: the weight gradients' sums to add to (empty: made here; see weight_gradient), returned.
std::tuple<TensorList, TensorList, TensorList, TensorList> sequence_backward(
    const std::shared_ptr<Sequence>& seq, const c10::optional<Tensor>& g_out_top,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c, TensorList dw,
    TensorList db);

}  // namespace stm_cpp
