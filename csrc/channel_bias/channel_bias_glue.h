#pragma once
// Checks shared by the CPU and CUDA implementations of channel_bias_add (layout: common/memory_format.h).
#include <ATen/ATen.h>

#include "common/memory_format.h"
#include "common/torch_checks.h"

namespace tiger {
namespace channel_bias {

constexpr const char* kOp = "tiger.channel_bias_add";

inline void check_inputs(const at::Tensor& x, const at::Tensor& bias) {
  TORCH_CHECK(x.dim() == 4, kOp, ": x must be [N, C, H, W], got ", shape_str(x.sizes()));
  TORCH_CHECK(bias.dim() == 1 && bias.size(0) == x.size(1), kOp, ": bias must be [C] = [", x.size(1),
              "] (one value per channel of x), got ", shape_str(bias.sizes()));
  TORCH_CHECK(x.is_floating_point(), kOp, ": x must be a floating-point tensor, got ", x.scalar_type());
  check_same(bias, x, kOp, "bias");
}

}  // namespace channel_bias
}  // namespace tiger
