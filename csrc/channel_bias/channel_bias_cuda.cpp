// Torch glue of the CUDA channel-bias kernel (built only with CUDA). No host synchronisation:
// CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include <optional>

#include "channel_bias/channel_bias_cuda.h"
#include "channel_bias/channel_bias_glue.h"

namespace tiger {
namespace channel_bias {
namespace {

at::Tensor channel_bias_add_cuda(const at::Tensor& x_in, const at::Tensor& bias_in,
                                 const std::optional<at::Tensor>& residual_in) {
  check_inputs(x_in, bias_in, residual_in);
  TORCH_CHECK(x_in.is_cuda(), kOp, ": x must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const bool nhwc = is_nhwc(x_in);
  const auto fmt = memory_format(nhwc);
  const auto x = x_in.contiguous(fmt);
  const auto bias = bias_in.contiguous();
  const bool has_residual = residual_in.has_value() && residual_in->defined();
  const auto residual = has_residual ? residual_in->contiguous(fmt) : at::Tensor();  // x's layout
  auto y = at::empty_like(x, fmt);
  const int64_t C = x.size(1), inner = nhwc ? 1 : x.size(2) * x.size(3);
  const int64_t plane = C * x.size(2) * x.size(3);
  const bool per_sample = bias.dim() == 2;
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  switch (x.scalar_type()) {
    case at::kFloat:
      launch_channel_bias<float>(x.data_ptr<float>(), bias.data_ptr<float>(),
                                 has_residual ? residual.data_ptr<float>() : nullptr, y.data_ptr<float>(), x.numel(), C,
                                 inner, plane, per_sample, nhwc, stream);
      break;
    case at::kHalf:
      launch_channel_bias<__half>(reinterpret_cast<const __half*>(x.data_ptr()),
                                  reinterpret_cast<const __half*>(bias.data_ptr()),
                                  has_residual ? reinterpret_cast<const __half*>(residual.data_ptr()) : nullptr,
                                  reinterpret_cast<__half*>(y.data_ptr()), x.numel(), C, inner, plane, per_sample,
                                  nhwc, stream);
      break;
    case at::kBFloat16:
      launch_channel_bias<__nv_bfloat16>(
          reinterpret_cast<const __nv_bfloat16*>(x.data_ptr()), reinterpret_cast<const __nv_bfloat16*>(bias.data_ptr()),
          has_residual ? reinterpret_cast<const __nv_bfloat16*>(residual.data_ptr()) : nullptr,
          reinterpret_cast<__nv_bfloat16*>(y.data_ptr()), x.numel(), C, inner, plane, per_sample, nhwc, stream);
      break;
    default:
      TORCH_CHECK(false, kOp, " (CUDA): x must be float32, bfloat16 or float16, got ", x.scalar_type());
  }
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return y;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("channel_bias_add", &channel_bias_add_cuda); }

}  // namespace channel_bias
}  // namespace tiger
