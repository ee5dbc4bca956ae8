// Schemas of the jbu family (formula in jbu.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("adaptive_conv(Tensor input, Tensor filters) -> Tensor");
  m.def(
      "adaptive_conv_backward(Tensor grad_out, Tensor input, Tensor filters, bool need_input, "
      "bool need_filters) -> (Tensor, Tensor)");
}
