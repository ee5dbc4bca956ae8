#pragma once
// Checks shared by the CPU and CUDA implementations of channel_bias_add (layout: common/memory_format.h).
#include <ATen/ATen.h>

#include <optional>

#include "common/memory_format.h"
#include "common/torch_checks.h"

namespace tiger {
namespace channel_bias {

constexpr const char* kOp = "tiger.channel_bias_add";
constexpr const char* kOp_into = "tiger.channel_bias_add_into";

inline void check_bias(const at::Tensor& x, const at::Tensor& bias) {
  const bool per_channel = bias.dim() == 1 && bias.size(0) == x.size(1);
  const bool per_sample = bias.dim() == 2 && bias.size(0) == x.size(0) && bias.size(1) == x.size(1);
  TORCH_CHECK(per_channel || per_sample, kOp, ": bias must be [C] = [", x.size(1), "] or [N, C] = [", x.size(0), ", ",
              x.size(1), "] (one value per channel of x, or per sample and channel), got ", shape_str(bias.sizes()));
  check_same(bias, x, kOp, "bias");
}

inline void check_x_residual(const at::Tensor& x, const std::optional<at::Tensor>& residual) {
  TORCH_CHECK(x.dim() == 4, kOp, ": x must be [N, C, H, W], got ", shape_str(x.sizes()));
  TORCH_CHECK(x.is_floating_point(), kOp, ": x must be a floating-point tensor, got ", x.scalar_type());
  if (residual.has_value() && residual->defined()) {
    TORCH_CHECK(residual->sizes() == x.sizes(), kOp, ": residual must have x's shape ", shape_str(x.sizes()),
                ", got ", shape_str(residual->sizes()));
    check_same(*residual, x, kOp, "residual");
  }
}

inline void check_inputs(const at::Tensor& x, const at::Tensor& bias, const std::optional<at::Tensor>& residual) {
  check_x_residual(x, residual);
  check_bias(x, bias);
}

// channel_bias_add_into: x [N, C, H, W], bias [C] / [N, C] or absent, residual as in check_inputs,
// out x's shape, dtype and device (any strides).
inline void check_into(const at::Tensor& x, const std::optional<at::Tensor>& bias,
                       const std::optional<at::Tensor>& residual, const at::Tensor& out) {
  check_x_residual(x, residual);
  if (bias.has_value() && bias->defined()) check_bias(x, *bias);
  TORCH_CHECK(out.sizes() == x.sizes(), kOp_into, ": out must have x's shape ", shape_str(x.sizes()), ", got ",
              shape_str(out.sizes()));
  check_same(out, x, kOp_into, "out");
}

// The row stride R of out when its elements lie as rows of R >= C elements per pixel, channels
// first within a row (strides [H·W·R, 1, W·R, R] on every dimension longer than 1: a channel slice
// of a wider channels-last map, or a channels-last map itself); 0 for any other layout.
inline int64_t nhwc_row_stride(const at::Tensor& out) {
  const int64_t N = out.size(0), C = out.size(1), H = out.size(2), W = out.size(3);
  int64_t R = C;
  if (W > 1) {
    R = out.stride(3);
  } else if (H > 1) {
    R = out.stride(2);
  } else if (N > 1) {
    R = out.stride(0);
  }
  const bool ok = R >= C && (C == 1 || out.stride(1) == 1) && (W == 1 || out.stride(3) == R) &&
                  (H == 1 || out.stride(2) == W * R) && (N == 1 || out.stride(0) == H * W * R);
  return ok ? R : 0;
}

constexpr const char* kOp_interleave = "tiger.subpixel_interleave_into";

// subpixel_interleave_into: z [N, 4C, H+1, W+1], bias [C] or absent, out [N, C, 2H, 2W], one dtype and device.
inline void check_interleave(const at::Tensor& z, const std::optional<at::Tensor>& bias, const at::Tensor& out) {
  TORCH_CHECK(z.dim() == 4 && out.dim() == 4, kOp_interleave, ": z and out must be [N, C, H, W], got ",
              shape_str(z.sizes()), " and ", shape_str(out.sizes()));
  const int64_t N = out.size(0), C = out.size(1), H = out.size(2) / 2, W = out.size(3) / 2;
  TORCH_CHECK(out.size(2) % 2 == 0 && out.size(3) % 2 == 0 && z.size(0) == N && z.size(1) == 4 * C &&
                  z.size(2) == H + 1 && z.size(3) == W + 1,
              kOp_interleave, ": z must be [N, 4C, H+1, W+1] = [", N, ", ", 4 * C, ", ", H + 1, ", ", W + 1,
              "] for out [N, C, 2H, 2W] = ", shape_str(out.sizes()), ", got ", shape_str(z.sizes()));
  TORCH_CHECK(z.is_floating_point(), kOp_interleave, ": z must be a floating-point tensor, got ", z.scalar_type());
  check_same(out, z, kOp_interleave, "out");
  if (bias.has_value() && bias->defined()) {
    TORCH_CHECK(bias->dim() == 1 && bias->size(0) == C, kOp_interleave, ": bias must be [C] = [", C, "], got ",
                shape_str(bias->sizes()));
    check_same(*bias, z, kOp_interleave, "bias");
  }
}

}  // namespace channel_bias
}  // namespace tiger
