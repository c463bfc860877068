// The LSTM stack of the C++ steps (stm/csrc/self_fed.cpp): one step of all layers, forward and backward, and
// runs of known inputs layer by layer, on ATen products and the cell's elementwise maths in plain loops.
//
// Shapes: K models of a pack, batch B. h, c per layer (K, B, H); w per layer (K, I + H, 4H) with the gate columns
// i, f, o, 2g (stm.lstm_step.gate_order); b (K, 1, 4H).
#pragma once

#include <ATen/ATen.h>

#include <memory>
#include <tuple>
#include <vector>

namespace stm_cpp {

using at::Tensor;
using TensorList = std::vector<Tensor>;

struct Layer {
  Tensor xh, gd, o_dt, sig;  // the step's [x, h], local derivatives (stm.lstm_step._stack_forward), gate sigmoids
};

// Known inputs (ground truth) through the stack, n steps: layer by layer, the input projection of all steps as one
// product and only the recurrent part stepped (stm.packed_lstm_step._LayerSeq, op for op). For short runs between
// self-fed segments this beats oneDNN's fused layer, whose set-up costs more than its five steps.
struct SeqLayer {
  Tensor x, h0, out;             // input (K, B, n, I), initial h, outputs (K, B, n, H)
  TensorList gd, o_dt, sig;      // per step
};

struct Sequence {
  TensorList ws, w_hT;  // w_hT: each layer's recurrent weights transposed, contiguous (K, 4H, H)
  std::vector<SeqLayer> layers;
};

void weight_gradient(const Tensor& xh, const Tensor& dg, Tensor& dw, Tensor& db);
Tensor stack_forward(Tensor inp, TensorList& h, TensorList& c, const TensorList& ws, const TensorList& bs,
                     std::vector<Layer>& saved);
Tensor stack_backward(TensorList& gh, TensorList& gc, const TensorList& ws, const std::vector<Layer>& saved,
                      bool need_x, TensorList& dgs);
// w_h, w_hT: per layer the recurrent rows of w, contiguous (K, H, 4H), and transposed, contiguous (K, 4H, H),
// made once per unroll by the caller (the weights are views whose rows a copy must gather: per call, one copy each
// per layer and chunk); empty lists: made here.
std::tuple<Tensor, TensorList, TensorList, std::shared_ptr<Sequence>> sequence_forward(
    Tensor x, TensorList h, TensorList c, const TensorList& ws, const TensorList& bs, const TensorList& w_h,
    const TensorList& w_hT);
std::tuple<TensorList, TensorList, TensorList, TensorList> sequence_backward(
    const std::shared_ptr<Sequence>& seq, const c10::optional<Tensor>& g_out_top,
    const std::vector<c10::optional<Tensor>>& g_h, const std::vector<c10::optional<Tensor>>& g_c);

}  // namespace stm_cpp
