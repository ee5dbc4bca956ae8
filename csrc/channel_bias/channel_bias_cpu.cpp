// CPU implementation of tiger::channel_bias_add: the reference semantics (ATen's broadcast add,
// which computes in float for reduced-precision dtypes and rounds once).
#include <torch/library.h>

#include "channel_bias/channel_bias_glue.h"

namespace tiger {
namespace channel_bias {
namespace {

at::Tensor channel_bias_add_cpu(const at::Tensor& x, const at::Tensor& bias) {
  check_inputs(x, bias);
  const auto fmt = memory_format(is_nhwc(x));
  auto y = at::empty_like(x, fmt);
  at::add_out(y, x, bias.reshape({1, -1, 1, 1}));
  return y;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) { m.impl("channel_bias_add", &channel_bias_add_cpu); }

}  // namespace channel_bias
}  // namespace tiger
