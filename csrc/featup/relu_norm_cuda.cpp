// Torch glue of the CUDA relu_scale_layer_norm kernels (built only with CUDA). Every allocation's
// size follows from the shapes and nothing is read back: CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include <optional>
#include <tuple>

#include "common/optional_tensor.h"
#include "featup/relu_norm.h"
#include "featup/relu_norm_glue.h"
#include "featup/stored_types_cuda.h"

namespace tiger {
namespace featup {
namespace {


void check_cuda(const at::Tensor& x, const NormDims& d, const char* op) {
  TORCH_CHECK(x.is_cuda(), op, " (CUDA): x must be on a CUDA device");
  TORCH_CHECK(d.D <= kMaxNormChannels, op, " (CUDA): at most ", kMaxNormChannels, " channels, got ", d.D);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> relu_norm_cuda(const at::Tensor& x,
                                                              const std::optional<at::Tensor>& scale,
                                                              const at::Tensor& weight, const at::Tensor& bias,
                                                              double eps) {
  const NormDims d = check_relu_norm(x, scale, weight, bias);
  check_cuda(x, d, "tiger.relu_scale_layer_norm");
  const c10::cuda::CUDAGuard guard(x.device());
  const auto xc = x.contiguous(), w = weight.contiguous(), b = bias.contiguous();
  const auto s = contiguous(scale);
  auto out = at::empty_like(xc);
  auto mean = at::empty({d.B, d.N}, w.options()), rstd = at::empty({d.B, d.N}, w.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch_cuda_stored_types(xc.scalar_type(), kReluNormOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    launch_relu_norm_forward<X, T>(reinterpret_cast<const X*>(xc.data_ptr()), optional_ptr<T>(s), w.data_ptr<T>(),
                                   b.data_ptr<T>(), d, eps, reinterpret_cast<X*>(out.data_ptr()), mean.data_ptr<T>(),
                                   rstd.data_ptr<T>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, mean, rstd};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> relu_norm_backward_cuda(const at::Tensor& grad_out, const at::Tensor& x,
                                                                       const std::optional<at::Tensor>& scale,
                                                                       const at::Tensor& weight, const at::Tensor& mean,
                                                                       const at::Tensor& rstd) {
  const NormDims d = check_relu_norm(x, scale, weight, weight);
  check_relu_norm_backward(grad_out, x, mean, rstd, d);
  check_cuda(x, d, "tiger.relu_scale_layer_norm_backward");
  const c10::cuda::CUDAGuard guard(x.device());
  const auto g = grad_out.contiguous(), xc = x.contiguous(), w = weight.contiguous(), mu = mean.contiguous(),
             rs = rstd.contiguous();
  const auto s = contiguous(scale);
  auto grad_x = at::empty_like(xc);
  auto grad_w = at::empty({d.D}, w.options()), grad_b = at::empty({d.D}, w.options());
  const int64_t pixels = d.B * d.N;
  if (pixels == 0) {
    grad_w.zero_();
    grad_b.zero_();
    return {grad_x, grad_w, grad_b};
  }
  const int blocks = relu_norm_backward_blocks(pixels);
  auto partials = at::empty({blocks, 2 * d.D}, w.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch_cuda_stored_types(xc.scalar_type(), kReluNormOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    launch_relu_norm_backward<X, T>(reinterpret_cast<const X*>(g.data_ptr()), reinterpret_cast<const X*>(xc.data_ptr()),
                                    optional_ptr<T>(s), w.data_ptr<T>(), mu.data_ptr<T>(), rs.data_ptr<T>(), d,
                                    reinterpret_cast<X*>(grad_x.data_ptr()), partials.data_ptr<T>(), blocks,
                                    grad_w.data_ptr<T>(), grad_b.data_ptr<T>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {grad_x, grad_w, grad_b};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("relu_scale_layer_norm", &relu_norm_cuda);
  m.impl("relu_scale_layer_norm_backward", &relu_norm_backward_cuda);
}

}  // namespace featup
}  // namespace tiger
