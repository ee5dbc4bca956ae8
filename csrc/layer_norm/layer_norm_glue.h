#pragma once
// Checks shared by the CPU and CUDA implementations of layer_norm_rows.
#include <ATen/ATen.h>

#include <optional>

#include "common/torch_checks.h"

namespace tiger {
namespace layer_norm {

constexpr const char* kOp = "tiger.layer_norm_rows";

inline void check_inputs(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                         double eps, const std::optional<at::Tensor>& input_bias) {
  TORCH_CHECK(x.dim() >= 1, kOp, ": x must have at least one dimension (rows of C values), got a scalar");
  TORCH_CHECK(x.is_floating_point(), kOp, ": x must be a floating-point tensor, got ", x.scalar_type());
  const int64_t C = x.size(-1);
  TORCH_CHECK(C > 0, kOp, ": x's last dimension (the normalised one) must not be empty, got ", shape_str(x.sizes()));
  TORCH_CHECK(weight.dim() == 1 && weight.size(0) == C, kOp, ": weight must be [C] = [", C, "] (x's last dimension), got ",
              shape_str(weight.sizes()));
  check_same(weight, x, kOp, "weight");
  if (bias.has_value() && bias->defined()) {
    TORCH_CHECK(bias->dim() == 1 && bias->size(0) == C, kOp, ": bias must be [C] = [", C, "], got ",
                shape_str(bias->sizes()));
    check_same(*bias, x, kOp, "bias");
  }
  if (input_bias.has_value() && input_bias->defined()) {
    TORCH_CHECK(input_bias->dim() == 1 && input_bias->size(0) == C, kOp, ": input_bias must be [C] = [", C, "], got ",
                shape_str(input_bias->sizes()));
    check_same(*input_bias, x, kOp, "input_bias");
  }
  TORCH_CHECK(eps >= 0.0, kOp, ": eps must be >= 0, got ", eps);
}

}  // namespace layer_norm
}  // namespace tiger
