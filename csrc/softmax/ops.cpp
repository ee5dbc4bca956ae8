// Schema of the softmax family: softmax over the last dimension of row-major rows, the VAE
// attention's [B, L, L] scores of the guidances (tiger/edit/guidance/diffusers_models.py).
//   softmax_rows(x [..., L]) -> [..., L]: exp(x - max) / sum(exp(x - max)) per row, in float
//     (double for float64), rounded once to x's dtype (what torch.softmax computes);
//   softmax_rows_backward(y [..., L], grad_y [..., L]) -> [..., L]: y * (grad_y - sum(grad_y * y))
//     per row, in float, rounded once (torch's softmax backward).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("softmax_rows(Tensor x) -> Tensor");
  m.def("softmax_rows_backward(Tensor y, Tensor grad_y) -> Tensor");
}
