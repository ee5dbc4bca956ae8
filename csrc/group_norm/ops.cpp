// Schemas of the group_norm family (formulas in group_norm.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("group_norm(Tensor x, Tensor? weight, Tensor? bias, int num_groups, float eps, bool silu, "
        "Tensor? input_bias=None) -> (Tensor, Tensor, Tensor)");
  m.def(
      "group_norm_backward(Tensor grad_y, Tensor x, Tensor? weight, Tensor? bias, Tensor mean, Tensor rstd, "
      "int num_groups, bool silu, bool param_grads, Tensor? input_bias=None, Tensor? residual_grad=None) "
      "-> (Tensor, Tensor, Tensor)");
}
