#pragma once
// ATen-side checks shared by the CPU and CUDA implementations of tiger::adaptive_conv.
#include <ATen/ATen.h>

namespace tiger {
namespace jbu {

struct Dims {
  int64_t B, C, H, W, K;
};

inline Dims check_adaptive_conv(const at::Tensor& input, const at::Tensor& filters) {
  TORCH_CHECK(input.dim() == 4, "tiger.adaptive_conv: input must be [B, C, H + K - 1, W + K - 1], got ",
              input.sizes());
  TORCH_CHECK(filters.dim() == 5 && filters.size(3) == filters.size(4),
              "tiger.adaptive_conv: filters must be [B, H, W, K, K], got ", filters.sizes());
  TORCH_CHECK(input.scalar_type() == at::kFloat || input.scalar_type() == at::kDouble,
              "tiger.adaptive_conv: input must be float32 or float64, got ", input.scalar_type());
  TORCH_CHECK(filters.scalar_type() == input.scalar_type(), "tiger.adaptive_conv: filters (",
              filters.scalar_type(), ") must have the dtype of input (", input.scalar_type(), ")");
  TORCH_CHECK(filters.device() == input.device(), "tiger.adaptive_conv: input and filters must be on one device");
  Dims d{filters.size(0), input.size(1), filters.size(1), filters.size(2), filters.size(3)};
  TORCH_CHECK(d.K >= 1, "tiger.adaptive_conv: filters must have K >= 1");
  TORCH_CHECK(input.size(0) == d.B && input.size(2) == d.H + d.K - 1 && input.size(3) == d.W + d.K - 1,
              "tiger.adaptive_conv: input must be [B, C, H + K - 1, W + K - 1] = [", d.B, ", C, ",
              d.H + d.K - 1, ", ", d.W + d.K - 1, "] for filters ", filters.sizes(), ", got ", input.sizes());
  return d;
}

}  // namespace jbu
}  // namespace tiger
