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

template <typename T>
const T* ptr(const at::Tensor& t) {
  return t.defined() ? reinterpret_cast<const T*>(t.data_ptr()) : nullptr;
}

// y (x's layout, or NHWC rows out_row elements apart) = x + bias (+ residual); x, bias and
// residual contiguous in x's layout, bias undefined for a plain copy.
void launch(const at::Tensor& x, const at::Tensor& bias, const at::Tensor& residual, void* y, int64_t out_row,
            bool nhwc) {
  const int64_t C = x.size(1), inner = nhwc ? 1 : x.size(2) * x.size(3);
  const int64_t plane = C * x.size(2) * x.size(3);
  const bool per_sample = bias.defined() && bias.dim() == 2;
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  switch (x.scalar_type()) {
    case at::kFloat:
      launch_channel_bias<float>(ptr<float>(x), ptr<float>(bias), ptr<float>(residual), static_cast<float*>(y),
                                 x.numel(), C, inner, plane, out_row, per_sample, nhwc, stream);
      break;
    case at::kHalf:
      launch_channel_bias<__half>(ptr<__half>(x), ptr<__half>(bias), ptr<__half>(residual), static_cast<__half*>(y),
                                  x.numel(), C, inner, plane, out_row, per_sample, nhwc, stream);
      break;
    case at::kBFloat16:
      launch_channel_bias<__nv_bfloat16>(ptr<__nv_bfloat16>(x), ptr<__nv_bfloat16>(bias), ptr<__nv_bfloat16>(residual),
                                         static_cast<__nv_bfloat16*>(y), x.numel(), C, inner, plane, out_row,
                                         per_sample, nhwc, stream);
      break;
    default:
      TORCH_CHECK(false, kOp, " (CUDA): x must be float32, bfloat16 or float16, got ", x.scalar_type());
  }
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

at::Tensor channel_bias_add_cuda(const at::Tensor& x_in, const at::Tensor& bias_in,
                                 const std::optional<at::Tensor>& residual_in) {
  check_inputs(x_in, bias_in, residual_in);
  TORCH_CHECK(x_in.is_cuda(), kOp, ": x must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const bool nhwc = is_nhwc(x_in);
  const auto fmt = memory_format(nhwc);
  const auto x = x_in.contiguous(fmt);
  const bool has_residual = residual_in.has_value() && residual_in->defined();
  const auto residual = has_residual ? residual_in->contiguous(fmt) : at::Tensor();  // x's layout
  auto y = at::empty_like(x, fmt);
  launch(x, bias_in.contiguous(), residual, y.data_ptr(), x.size(1), nhwc);
  return y;
}

void channel_bias_add_into_cuda(const at::Tensor& x_in, const std::optional<at::Tensor>& bias_in,
                                const std::optional<at::Tensor>& residual_in, at::Tensor out) {
  check_into(x_in, bias_in, residual_in, out);
  TORCH_CHECK(x_in.is_cuda(), kOp_into, ": x must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const bool has_bias = bias_in.has_value() && bias_in->defined();
  const bool has_residual = residual_in.has_value() && residual_in->defined();
  const int64_t out_row = nhwc_row_stride(out);
  if (out_row == 0) {  // any other output layout: the op's result, copied
    const auto bias = has_bias ? *bias_in : at::zeros({x_in.size(1)}, x_in.options());
    out.copy_(channel_bias_add_cuda(x_in, bias, residual_in));
    return;
  }
  const auto fmt = at::MemoryFormat::ChannelsLast;
  const auto x = x_in.contiguous(fmt);  // rows of C, whatever x's own layout
  const auto residual = has_residual ? residual_in->contiguous(fmt) : at::Tensor();
  launch(x, has_bias ? bias_in->contiguous() : at::Tensor(), residual, out.data_ptr(), out_row, /*nhwc=*/true);
}

void subpixel_interleave_into_cuda(const at::Tensor& z_in, const std::optional<at::Tensor>& bias_in, at::Tensor out) {
  check_interleave(z_in, bias_in, out);
  TORCH_CHECK(z_in.is_cuda(), kOp_interleave, ": z must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(z_in.device());
  const int64_t N = out.size(0), C = out.size(1), H = out.size(2) / 2, W = out.size(3) / 2;
  const int64_t out_row = nhwc_row_stride(out);
  auto y = out_row ? out : at::empty(out.sizes(), out.options().memory_format(at::MemoryFormat::ChannelsLast));
  const auto z = z_in.contiguous(at::MemoryFormat::ChannelsLast);
  const bool has_bias = bias_in.has_value() && bias_in->defined();
  const auto bias = has_bias ? bias_in->contiguous() : at::Tensor();
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t row = out_row ? out_row : C;
  switch (z.scalar_type()) {
    case at::kFloat:
      launch_subpixel_interleave<float>(ptr<float>(z), ptr<float>(bias), static_cast<float*>(y.data_ptr()), N, C, H,
                                        W, row, stream);
      break;
    case at::kHalf:
      launch_subpixel_interleave<__half>(ptr<__half>(z), ptr<__half>(bias), static_cast<__half*>(y.data_ptr()), N, C,
                                         H, W, row, stream);
      break;
    case at::kBFloat16:
      launch_subpixel_interleave<__nv_bfloat16>(ptr<__nv_bfloat16>(z), ptr<__nv_bfloat16>(bias),
                                                static_cast<__nv_bfloat16*>(y.data_ptr()), N, C, H, W, row, stream);
      break;
    default:
      TORCH_CHECK(false, kOp_interleave, " (CUDA): z must be float32, bfloat16 or float16, got ", z.scalar_type());
  }
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (!out_row) out.copy_(y);
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("channel_bias_add", &channel_bias_add_cuda);
  m.impl("channel_bias_add_into", &channel_bias_add_into_cuda);
  m.impl("subpixel_interleave_into", &subpixel_interleave_into_cuda);
}

}  // namespace channel_bias
}  // namespace tiger
