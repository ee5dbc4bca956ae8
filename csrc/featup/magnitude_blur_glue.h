#pragma once
// ATen-side checks shared by the CPU and CUDA implementations of tiger::magnitude_blur.
#include <ATen/ATen.h>

#include <cmath>
#include <optional>

#include "featup/magnitude_blur.h"

namespace tiger {
namespace featup {

constexpr const char* kMagnitudeBlurOp = "tiger.magnitude_blur: ";

// The outputs' dtype for features of dtype dt.
inline at::ScalarType blur_out_dtype(at::ScalarType dt) { return dt == at::kDouble ? at::kDouble : at::kFloat; }

inline BlurDims check_magnitude_blur(const at::Tensor& x, int64_t radius, double sigma) {
  TORCH_CHECK(x.dim() == 3, kMagnitudeBlurOp, "x must be [H, W, C], got ", x.sizes());
  const auto dt = x.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble || dt == at::kBFloat16 || dt == at::kHalf, kMagnitudeBlurOp,
              "x must be float32, float64, bfloat16 or float16, got ", dt);
  TORCH_CHECK(radius >= 0 && radius <= kMaxBlurRadius, kMagnitudeBlurOp, "radius must be in [0, ", kMaxBlurRadius,
              "], got ", radius);
  TORCH_CHECK(std::isfinite(sigma) && sigma > 0, kMagnitudeBlurOp, "sigma must be positive, got ", sigma);
  TORCH_CHECK(x.size(2) >= 1, kMagnitudeBlurOp, "x must have at least one channel, got ", x.sizes());
  TORCH_CHECK(radius < x.size(0) && radius < x.size(1), kMagnitudeBlurOp, "reflect padding by radius ", radius,
              " needs H and W > radius, got x ", x.sizes());
  return BlurDims{x.size(0), x.size(1), x.size(2), static_cast<int>(radius)};
}

inline void check_magnitude_blur_backward(const at::Tensor& grad_blurred, const std::optional<at::Tensor>& grad_magnitude,
                                          const at::Tensor& x, const at::Tensor& magnitude, const BlurDims& d) {
  const auto out_dt = blur_out_dtype(x.scalar_type());
  const char* op = "tiger.magnitude_blur_backward: ";
  auto check = [&](const at::Tensor& t, const char* name, at::IntArrayRef shape) {
    TORCH_CHECK(t.sizes() == shape, op, name, " must have shape ", shape, ", got ", t.sizes());
    TORCH_CHECK(t.scalar_type() == out_dt, op, name, " must be ", out_dt, " for x of ", x.scalar_type(), ", got ",
                t.scalar_type());
    TORCH_CHECK(t.device() == x.device(), op, name, " must be on the device of x (", x.device(), "), got ",
                t.device());
  };
  check(grad_blurred, "grad_blurred", {d.H, d.W, d.C + 1});
  check(magnitude, "magnitude", {d.H, d.W});
  if (grad_magnitude.has_value()) check(*grad_magnitude, "grad_magnitude", {d.H, d.W});
}

// gaussian_taps(2 radius + 1, sigma) in double, rounded once to T.
template <typename T>
BlurTaps<T> blur_taps(int radius, double sigma) {
  double g[2 * kMaxBlurRadius + 1];
  double sum = 0;
  for (int t = -radius; t <= radius; ++t) {
    g[t + radius] = std::exp(-double(t * t) / (2 * sigma * sigma));
    sum += g[t + radius];
  }
  BlurTaps<T> taps{};
  for (int i = 0; i <= 2 * radius; ++i) taps.g[i] = static_cast<T>(g[i] / sum);
  return taps;
}

}  // namespace featup
}  // namespace tiger
