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

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("channel_bias_add", &channel_bias_add_cpu);
  m.impl("channel_bias_add_into", &channel_bias_add_into_cpu);
}

}  // namespace channel_bias
}  // namespace tiger
