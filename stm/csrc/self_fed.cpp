// The C++ steps' Python module (stm.self_fed, stm.mdn_fused): the self-fed segment (segment.h), the ground-truth
// layer sequence (lstm_step.h) and the fused mixture NLL (mdn_nll.h), forward and backward.
//
// Why C++: a self-fed step is ~330 small ATen calls (forward and backward); issued from Python each pays several
// microseconds of binding and autograd bookkeeping, more than its arithmetic at these sizes, and issued from C++
// each still pays ATen's dispatch, views and checks. Here a step makes no ATen call: BLAS products issued as ATen
// issues them (products.h), the gates' sigmoid and tanh and the tip's sine as ATen computes them (vec_math.h), and
// plain loops over the step's rows for the rest, on buffers made once per segment or chunk.
#include <torch/extension.h>

#include "lstm_step.h"
#include "mdn_nll.h"
#include "segment.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  pybind11::class_<stm_cpp::Segment, std::shared_ptr<stm_cpp::Segment>>(module, "Segment");
  module.def("segment_forward", &stm_cpp::segment_forward, "self-fed segment, forward");
  module.def("segment_backward", &stm_cpp::segment_backward, "self-fed segment, backward");
  pybind11::class_<stm_cpp::Sequence, std::shared_ptr<stm_cpp::Sequence>>(module, "Sequence");
  module.def("sequence_forward", &stm_cpp::sequence_forward, "known inputs through the stack, forward");
  module.def("sequence_backward", &stm_cpp::sequence_backward, "known inputs through the stack, backward");
  module.def("mdn_nll_forward", &stm_cpp::mdn_nll_forward, "mixture NLL per row (and what its backward needs)");
  module.def("mdn_nll_backward", &stm_cpp::mdn_nll_backward, "mixture NLL, gradient of the raw head outputs");
}
