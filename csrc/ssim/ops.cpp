// Schema of the fused SSIM family: the SSIM map of two [B, C, H, W] images with a separable
// window (taps: odd count <= 11, zero padding), the three derivative maps its backward needs,
// and that backward (gradient for img1 only: img2 is the fixed target).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("fused_ssim(Tensor img1, Tensor img2, float[] taps, float c1, float c2) -> (Tensor, Tensor)");
  m.def("fused_ssim_backward(Tensor grad, Tensor img1, Tensor img2, Tensor dmoments, float[] taps) -> Tensor");
}
