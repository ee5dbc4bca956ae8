// Schemas of the featup family (formula in featup.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def(
      "jittered_window_attention(Tensor features, Tensor logit_map, Tensor coord_y, Tensor coord_x, "
      "Tensor w, Tensor b, Tensor mask, int stride_h, int stride_w) -> (Tensor, Tensor)");
  m.def(
      "jittered_window_attention_backward(Tensor grad_out, Tensor features, Tensor logit_map, "
      "Tensor coord_y, Tensor coord_x, Tensor w, Tensor b, Tensor mask, Tensor attn, int stride_h, "
      "int stride_w) -> (Tensor, Tensor, Tensor, Tensor)");
}
