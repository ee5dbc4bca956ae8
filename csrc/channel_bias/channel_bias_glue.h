#pragma once
// Checks shared by the CPU and CUDA implementations of channel_bias_add (layout: common/memory_format.h).
#include <ATen/ATen.h>

#include <optional>

#include "common/memory_format.h"
#include "common/torch_checks.h"

namespace tiger {
namespace channel_bias {

constexpr const char* kOp = "tiger.channel_bias_add";

inline void check_inputs(const at::Tensor& x, const at::Tensor& bias, const std::optional<at::Tensor>& residual) {
  TORCH_CHECK(x.dim() == 4, kOp, ": x must be [N, C, H, W], got ", shape_str(x.sizes()));
  const bool per_channel = bias.dim() == 1 && bias.size(0) == x.size(1);
  const bool per_sample = bias.dim() == 2 && bias.size(0) == x.size(0) && bias.size(1) == x.size(1);
  TORCH_CHECK(per_channel || per_sample, kOp, ": bias must be [C] = [", x.size(1), "] or [N, C] = [", x.size(0), ", ",
              x.size(1), "] (one value per channel of x, or per sample and channel), got ", shape_str(bias.sizes()));
  TORCH_CHECK(x.is_floating_point(), kOp, ": x must be a floating-point tensor, got ", x.scalar_type());
  check_same(bias, x, kOp, "bias");
  if (residual.has_value() && residual->defined()) {
    TORCH_CHECK(residual->sizes() == x.sizes(), kOp, ": residual must have x's shape ", shape_str(x.sizes()),
                ", got ", shape_str(residual->sizes()));
    check_same(*residual, x, kOp, "residual");
  }
}

}  // namespace channel_bias
}  // namespace tiger
