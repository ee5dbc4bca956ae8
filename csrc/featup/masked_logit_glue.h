#pragma once
// ATen-side checks shared by the CPU and CUDA implementations of tiger::masked_logit.
#include <ATen/ATen.h>

#include <cmath>
#include <optional>

#include "featup/masked_logit.h"

namespace tiger {
namespace featup {

constexpr const char* kMaskedLogitOp = "tiger.masked_logit: ";

// bias may be null (the backward has none).
inline LogitDims check_masked_logit(const at::Tensor& x, const std::optional<at::Tensor>& keep, double keep_scale,
                                    const at::Tensor& weight, const at::Tensor* bias) {
  TORCH_CHECK(x.dim() == 3 && x.size(2) >= 1, kMaskedLogitOp, "x must be [H, W, U], got ", x.sizes());
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, kMaskedLogitOp,
              "x must be float32 or float64, got ", x.scalar_type());
  const int64_t H = x.size(0), W = x.size(1), U = x.size(2);
  auto check = [&](const at::Tensor& t, const char* name, at::IntArrayRef shape, at::ScalarType dtype) {
    TORCH_CHECK(t.sizes() == shape, kMaskedLogitOp, name, " must have shape ", shape, ", got ", t.sizes());
    TORCH_CHECK(t.scalar_type() == dtype, kMaskedLogitOp, name, " must be ", dtype, " (x is ", x.scalar_type(),
                "), got ", t.scalar_type());
    TORCH_CHECK(t.device() == x.device(), kMaskedLogitOp, name, " must be on the device of x (", x.device(),
                "), got ", t.device());
  };
  if (keep.has_value()) check(*keep, "keep", {U, H, W}, at::kBool);
  TORCH_CHECK(std::isfinite(keep_scale), kMaskedLogitOp, "keep_scale must be finite, got ", keep_scale);
  check(weight, "weight", {U}, x.scalar_type());
  if (bias) check(*bias, "bias", {1}, x.scalar_type());
  return LogitDims{H * W, U};
}

// The backward's incoming gradient: [H, W] in x's dtype, on x's device.
inline void check_masked_logit_grad(const at::Tensor& grad, const at::Tensor& x) {
  TORCH_CHECK(grad.sizes() == at::IntArrayRef({x.size(0), x.size(1)}) && grad.scalar_type() == x.scalar_type() &&
                  grad.device() == x.device(),
              "tiger.masked_logit_backward: grad must be [H, W] = [", x.size(0), ", ", x.size(1), "] in x's dtype (",
              x.scalar_type(), ") on its device (", x.device(), "), got ", grad.sizes(), " ", grad.scalar_type(), " on ",
              grad.device());
}

}  // namespace featup
}  // namespace tiger
