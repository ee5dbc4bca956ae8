// Schemas of the masked_average family (formulas in masked_average.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("masked_average(Tensor features, Tensor ids, int num_masks) -> (Tensor, Tensor, Tensor)");
  m.def(
      "masked_average_backward(Tensor grad_out, Tensor grad_means, Tensor ids, Tensor counts) -> "
      "Tensor");
}
