#pragma once
// Fused SSIM: the map and its img1-gradient in one pass each (CPU and CUDA).
//
// fused_ssim: img1, img2 [B, C, H, W] float32/float64, taps: the normalised 1-D window
//   (odd count <= 11, applied along rows and columns, zero padding), c1, c2: SSIM's constants
//   -> ssim [B, C, H, W], dmoments [3, B, C, H, W] (d ssim / d mu1, / d e11, / d e12 per pixel,
//   see ssim_math.h).
// fused_ssim_backward: grad [B, C, H, W] (d loss / d ssim), img1, img2, dmoments, taps
//   -> d loss / d img1 [B, C, H, W].
#include <ATen/ATen.h>

#include <vector>

#include "common/torch_checks.h"
#include "ssim/ssim_math.h"

namespace tiger {
namespace ssim {

constexpr const char* kOp = "tiger.fused_ssim";

struct Window {
  double taps[kMaxWindow];
  int radius;
};

inline Window check_taps(at::ArrayRef<double> taps) {
  TORCH_CHECK(taps.size() % 2 == 1 && taps.size() <= size_t(kMaxWindow), kOp,
              ": taps must be an odd number (at most ", kMaxWindow, ") of window weights, got ", taps.size());
  Window w{};
  for (size_t i = 0; i < taps.size(); ++i) w.taps[i] = taps[i];
  w.radius = int(taps.size() / 2);
  return w;
}

inline void check_images(const at::Tensor& img1, const at::Tensor& img2) {
  TORCH_CHECK(img1.dim() == 4, kOp, ": img1 must be [B, C, H, W], got ", shape_str(img1.sizes()));
  TORCH_CHECK(img2.sizes() == img1.sizes(), kOp, ": img2 must have img1's shape ", shape_str(img1.sizes()),
              ", got ", shape_str(img2.sizes()));
  TORCH_CHECK(img1.scalar_type() == at::kFloat || img1.scalar_type() == at::kDouble, kOp,
              ": images must be float32 or float64, got ", img1.scalar_type());
  check_same(img2, img1, kOp, "img2");
}

inline void check_backward(const at::Tensor& grad, const at::Tensor& img1, const at::Tensor& img2,
                           const at::Tensor& dmoments) {
  check_images(img1, img2);
  TORCH_CHECK(grad.sizes() == img1.sizes(), "tiger.fused_ssim_backward: grad must be ",
              shape_str(img1.sizes()), ", got ", shape_str(grad.sizes()));
  check_same(grad, img1, "tiger.fused_ssim_backward", "grad");
  TORCH_CHECK(dmoments.dim() == 5 && dmoments.size(0) == 3 && dmoments.sizes().slice(1) == img1.sizes(),
              "tiger.fused_ssim_backward: dmoments must be [3, ", img1.size(0), ", ", img1.size(1), ", ",
              img1.size(2), ", ", img1.size(3), "], got ", shape_str(dmoments.sizes()));
  check_same(dmoments, img1, "tiger.fused_ssim_backward", "dmoments");
}

}  // namespace ssim
}  // namespace tiger
