// Schemas of the featup family (formulas in featup.h, fourier.h, relu_norm.h, magnitude_blur.h and
// masked_logit.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def(
      "jittered_window_attention(Tensor features, Tensor logit_map, Tensor coord_y, Tensor coord_x, "
      "Tensor w, Tensor b, Tensor mask, int stride_h, int stride_w, str variant=\"baseline\") -> (Tensor, Tensor)");
  m.def(
      "jittered_window_attention_backward(Tensor grad_out, Tensor features, Tensor logit_map, "
      "Tensor coord_y, Tensor coord_x, Tensor w, Tensor b, Tensor mask, Tensor attn, int stride_h, "
      "int stride_w, str variant=\"baseline\") -> (Tensor, Tensor, Tensor, Tensor)");
  m.def(
      "fourier_layer_norm(Tensor inputs, Tensor freqs, Tensor phase, Tensor weight, Tensor bias, "
      "Tensor? scale, float eps, ScalarType? out_dtype) -> (Tensor, Tensor, Tensor)");
  m.def(
      "fourier_layer_norm_backward(Tensor grad_out, Tensor inputs, Tensor freqs, Tensor phase, "
      "Tensor weight, Tensor? scale, Tensor mean, Tensor rstd, bool input_grad) "
      "-> (Tensor, Tensor, Tensor, Tensor)");
  m.def(
      "relu_scale_layer_norm(Tensor x, Tensor? scale, Tensor weight, Tensor bias, float eps) "
      "-> (Tensor, Tensor, Tensor)");
  m.def(
      "relu_scale_layer_norm_backward(Tensor grad_out, Tensor x, Tensor? scale, Tensor weight, Tensor mean, "
      "Tensor rstd) -> (Tensor, Tensor, Tensor)");
  m.def("magnitude_blur(Tensor x, int radius, float sigma) -> (Tensor, Tensor)");
  m.def(
      "magnitude_blur_backward(Tensor grad_blurred, Tensor? grad_magnitude, Tensor x, Tensor magnitude, "
      "int radius, float sigma) -> Tensor");
  m.def("masked_logit(Tensor x, Tensor? keep, float keep_scale, Tensor weight, Tensor bias) -> Tensor");
  m.def(
      "masked_logit_backward(Tensor grad, Tensor x, Tensor? keep, float keep_scale, Tensor weight, bool x_grad) "
      "-> (Tensor, Tensor, Tensor)");
}
