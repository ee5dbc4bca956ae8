// CPU implementation of tiger::channel_bias_add: the reference semantics, x + bias (+ residual)
// computed in float (double for float64) and rounded once to x's dtype, as the CUDA kernel does.
#include <torch/library.h>

#include "channel_bias/channel_bias_glue.h"

namespace tiger {
namespace channel_bias {
namespace {

at::Tensor channel_bias_add_cpu(const at::Tensor& x, const at::Tensor& bias, const std::optional<at::Tensor>& residual) {
  check_inputs(x, bias, residual);
  const auto fmt = memory_format(is_nhwc(x));
  const auto acc = x.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  const auto b = bias.reshape({bias.dim() == 2 ? bias.size(0) : 1, x.size(1), 1, 1}).to(acc);
  auto sum = at::add(x.to(acc), b);
  if (residual.has_value() && residual->defined()) sum.add_(residual->to(acc));
  auto y = at::empty_like(x, fmt);
  y.copy_(sum);
  return y;
}

void channel_bias_add_into_cpu(const at::Tensor& x, const std::optional<at::Tensor>& bias,
                               const std::optional<at::Tensor>& residual, at::Tensor out) {
  check_into(x, bias, residual, out);
  if (!(bias.has_value() && bias->defined())) {  // a copy (+ residual), rounded once
    const auto acc = x.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
    out.copy_(residual.has_value() && residual->defined() ? at::add(x.to(acc), residual->to(acc)) : x);
    return;
  }
  out.copy_(channel_bias_add_cpu(x, *bias, residual));
}

void subpixel_interleave_into_cpu(const at::Tensor& z, const std::optional<at::Tensor>& bias, at::Tensor out) {
  check_interleave(z, bias, out);
  const int64_t N = out.size(0), C = out.size(1), H = out.size(2) / 2, W = out.size(3) / 2;
  const auto zv = z.permute({0, 2, 3, 1}).contiguous().view({N, H + 1, W + 1, 2, 2, C});
  auto y = at::empty({N, 2 * H, 2 * W, C}, out.options());  // NHWC
  const auto yv = y.view({N, H, 2, W, 2, C});
  const bool has_bias = bias.has_value() && bias->defined();
  for (int64_t a = 0; a < 2; ++a) {
    for (int64_t b = 0; b < 2; ++b) {
      const auto src = zv.slice(1, a, a + H).slice(2, b, b + W).select(4, b).select(3, a);  // [N, H, W, C]
      auto dst = yv.select(4, b).select(2, a);                                               // [N, H, W, C]
      if (has_bias) {
        at::add_out(dst, src, *bias);
      } else {
        dst.copy_(src);
      }
    }
  }
  out.copy_(y.permute({0, 3, 1, 2}));
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("channel_bias_add", &channel_bias_add_cpu);
  m.impl("channel_bias_add_into", &channel_bias_add_into_cpu);
  m.impl("subpixel_interleave_into", &subpixel_interleave_into_cpu);
}

}  // namespace channel_bias
}  // namespace tiger
