#pragma once
// ATen-side checks shared by the CPU and CUDA implementations of tiger::fourier_layer_norm.
#include <ATen/ATen.h>

#include <optional>

#include "featup/fourier.h"

namespace tiger {
namespace featup {

constexpr const char* kFourierOp = "tiger.fourier_layer_norm: ";

// The output dtype: out_dtype, or the inputs' dtype when none is given.
inline at::ScalarType fourier_out_dtype(const at::Tensor& inputs, std::optional<at::ScalarType> out_dtype) {
  const at::ScalarType dt = out_dtype.value_or(inputs.scalar_type());
  TORCH_CHECK(dt == inputs.scalar_type() || dt == at::kBFloat16 || dt == at::kHalf, kFourierOp,
              "out_dtype must be the inputs' dtype (", inputs.scalar_type(), "), bfloat16 or float16, got ", dt);
  return dt;
}

inline void check_fourier_param(const at::Tensor& t, const at::Tensor& inputs, const char* name,
                                at::IntArrayRef shape) {
  TORCH_CHECK(t.sizes() == shape, kFourierOp, name, " must have shape ", shape, ", got ", t.sizes());
  TORCH_CHECK(t.scalar_type() == inputs.scalar_type(), kFourierOp, name, " (", t.scalar_type(),
              ") must have the dtype of inputs (", inputs.scalar_type(), ")");
  TORCH_CHECK(t.device() == inputs.device(), kFourierOp, name, " must be on the device of inputs (",
              inputs.device(), "), got ", t.device());
}

inline FourierDims check_fourier(const at::Tensor& inputs, const at::Tensor& freqs, const at::Tensor& phase,
                                 const at::Tensor& weight, const at::Tensor& bias,
                                 const std::optional<at::Tensor>& scale) {
  TORCH_CHECK(inputs.dim() == 3 && inputs.size(2) == kFourierInputs, kFourierOp,
              "inputs must be [B, N, 5] (y, x, r, g, b per pixel), got ", inputs.sizes());
  TORCH_CHECK(inputs.scalar_type() == at::kFloat || inputs.scalar_type() == at::kDouble, kFourierOp,
              "inputs must be float32 or float64, got ", inputs.scalar_type());
  TORCH_CHECK(freqs.dim() == 1 && freqs.size(0) >= 1, kFourierOp, "freqs must be [F] with F >= 1, got ",
              freqs.sizes());
  const int64_t F = freqs.size(0), C = 2 * kFourierInputs * F + 3;
  check_fourier_param(freqs, inputs, "freqs", {F});
  check_fourier_param(phase, inputs, "phase", {2, kFourierInputs, F});
  check_fourier_param(weight, inputs, "weight", {C});
  check_fourier_param(bias, inputs, "bias", {C});
  if (scale.has_value()) check_fourier_param(*scale, inputs, "scale", {inputs.size(0), C});
  return {inputs.size(0), inputs.size(1), F, C};
}

inline void check_fourier_backward(const at::Tensor& grad_out, const at::Tensor& inputs, const at::Tensor& mean,
                                   const at::Tensor& rstd, const FourierDims& d) {
  TORCH_CHECK(grad_out.sizes() == at::IntArrayRef({d.B, d.N, d.C}) && grad_out.device() == inputs.device(),
              "tiger.fourier_layer_norm_backward: grad_out must be [B, N, C] = [", d.B, ", ", d.N, ", ", d.C,
              "] on the inputs' device, got ", grad_out.sizes(), " on ", grad_out.device());
  fourier_out_dtype(inputs, grad_out.scalar_type());
  for (auto [t, name] : {std::pair<const at::Tensor*, const char*>{&mean, "mean"}, {&rstd, "rstd"}})
    check_fourier_param(*t, inputs, name, {d.B, d.N});
}

}  // namespace featup
}  // namespace tiger
