// Torch glue of the CUDA row LayerNorm (built only with CUDA). The output comes from the caching
// allocator and every size is known on the host: CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include "layer_norm/layer_norm_cuda.h"
#include "layer_norm/layer_norm_glue.h"

namespace tiger {
namespace layer_norm {
namespace {

template <typename T>
const T* ptr(const at::Tensor& t) {
  return t.defined() ? reinterpret_cast<const T*>(t.data_ptr()) : nullptr;
}

at::Tensor layer_norm_rows_cuda(const at::Tensor& x_in, const at::Tensor& weight_in,
                                const std::optional<at::Tensor>& bias_in, double eps,
                                const std::optional<at::Tensor>& input_bias_in) {
  check_inputs(x_in, weight_in, bias_in, eps, input_bias_in);
  TORCH_CHECK(x_in.is_cuda(), kOp, ": x must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const auto x = x_in.contiguous();
  const auto weight = weight_in.contiguous();
  const auto bias = bias_in.has_value() && bias_in->defined() ? bias_in->contiguous() : at::Tensor();
  const auto input_bias =
      input_bias_in.has_value() && input_bias_in->defined() ? input_bias_in->contiguous() : at::Tensor();
  auto y = at::empty_like(x, at::MemoryFormat::Contiguous);
  const int64_t C = x.size(-1), M = x.numel() / C;
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  switch (x.scalar_type()) {
    case at::kFloat:
      launch_layer_norm_rows<float>(ptr<float>(x), ptr<float>(weight), ptr<float>(bias), ptr<float>(input_bias),
                                    y.data_ptr<float>(), M, C, eps, stream);
      break;
    case at::kDouble:
      launch_layer_norm_rows<double>(ptr<double>(x), ptr<double>(weight), ptr<double>(bias), ptr<double>(input_bias),
                                     y.data_ptr<double>(), M, C, eps, stream);
      break;
    case at::kHalf:
      launch_layer_norm_rows<__half>(ptr<__half>(x), ptr<__half>(weight), ptr<__half>(bias), ptr<__half>(input_bias),
                                     reinterpret_cast<__half*>(y.data_ptr()), M, C, eps, stream);
      break;
    case at::kBFloat16:
      launch_layer_norm_rows<__nv_bfloat16>(ptr<__nv_bfloat16>(x), ptr<__nv_bfloat16>(weight),
                                            ptr<__nv_bfloat16>(bias), ptr<__nv_bfloat16>(input_bias),
                                            reinterpret_cast<__nv_bfloat16*>(y.data_ptr()), M, C, eps, stream);
      break;
    default:
      TORCH_CHECK(false, kOp, " (CUDA): x must be float32, float64, bfloat16 or float16, got ", x.scalar_type());
  }
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return y;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("layer_norm_rows", &layer_norm_rows_cuda); }

}  // namespace layer_norm
}  // namespace tiger
