// CPU implementation of tiger::layer_norm_rows: the reference semantics (two-pass mean and
// variance in float, double for float64, one rounding of the result), as the CUDA kernel does.
#include <torch/library.h>

#include "layer_norm/layer_norm_glue.h"

namespace tiger {
namespace layer_norm {
namespace {

at::Tensor layer_norm_rows_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                               double eps, const std::optional<at::Tensor>& input_bias) {
  check_inputs(x, weight, bias, eps, input_bias);
  const auto acc = x.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  auto xf = x.to(acc);
  if (input_bias.has_value() && input_bias->defined()) xf = xf + input_bias->to(acc);
  const auto mean = xf.mean(-1, /*keepdim=*/true);
  const auto centred = xf - mean;
  const auto var = (centred * centred).mean(-1, /*keepdim=*/true);
  auto y = centred * (var + eps).rsqrt() * weight.to(acc);
  if (bias.has_value() && bias->defined()) y = y + bias->to(acc);
  return y.to(x.scalar_type()).contiguous();
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) { m.impl("layer_norm_rows", &layer_norm_rows_cpu); }

}  // namespace layer_norm
}  // namespace tiger
