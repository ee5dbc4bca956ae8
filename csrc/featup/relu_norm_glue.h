#pragma once
// ATen-side checks shared by the CPU and CUDA implementations of tiger::relu_scale_layer_norm.
#include <ATen/ATen.h>

#include <optional>

#include "featup/relu_norm.h"

namespace tiger {
namespace featup {

constexpr const char* kReluNormOp = "tiger.relu_scale_layer_norm: ";

// The dtype of the affine, the scale and the statistics for activations of dtype dt.
inline at::ScalarType relu_norm_param_dtype(at::ScalarType dt) { return dt == at::kDouble ? at::kDouble : at::kFloat; }

inline void check_relu_norm_param(const at::Tensor& t, const at::Tensor& x, const char* name, at::IntArrayRef shape) {
  TORCH_CHECK(t.sizes() == shape, kReluNormOp, name, " must have shape ", shape, ", got ", t.sizes());
  const at::ScalarType want = relu_norm_param_dtype(x.scalar_type());
  TORCH_CHECK(t.scalar_type() == want, kReluNormOp, name, " must be ", want, " for x of ", x.scalar_type(), ", got ",
              t.scalar_type());
  TORCH_CHECK(t.device() == x.device(), kReluNormOp, name, " must be on the device of x (", x.device(), "), got ",
              t.device());
}

inline NormDims check_relu_norm(const at::Tensor& x, const std::optional<at::Tensor>& scale, const at::Tensor& weight,
                                const at::Tensor& bias) {
  TORCH_CHECK(x.dim() == 3 && x.size(2) >= 1, kReluNormOp, "x must be [B, N, D], got ", x.sizes());
  const auto dt = x.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble || dt == at::kBFloat16 || dt == at::kHalf, kReluNormOp,
              "x must be float32, float64, bfloat16 or float16, got ", dt);
  const NormDims d{x.size(0), x.size(1), x.size(2)};
  check_relu_norm_param(weight, x, "weight", {d.D});
  check_relu_norm_param(bias, x, "bias", {d.D});
  if (scale.has_value()) check_relu_norm_param(*scale, x, "scale", {d.B, d.D});
  return d;
}

inline void check_relu_norm_backward(const at::Tensor& grad_out, const at::Tensor& x, const at::Tensor& mean,
                                     const at::Tensor& rstd, const NormDims& d) {
  TORCH_CHECK(grad_out.sizes() == x.sizes() && grad_out.scalar_type() == x.scalar_type() &&
                  grad_out.device() == x.device(),
              "tiger.relu_scale_layer_norm_backward: grad_out must be like x ", x.sizes(), " ", x.scalar_type(),
              ", got ", grad_out.sizes(), " ", grad_out.scalar_type());
  check_relu_norm_param(mean, x, "mean", {d.B, d.N});
  check_relu_norm_param(rstd, x, "rstd", {d.B, d.N});
}

}  // namespace featup
}  // namespace tiger
