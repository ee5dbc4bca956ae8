// Torch glue of the CUDA masked_logit kernels (built only with CUDA). Every allocation's size
// follows from the shapes and nothing is read back: CUDA-graph capturable.
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <optional>
#include <tuple>

#include "common/optional_tensor.h"
#include "featup/masked_logit.h"
#include "featup/masked_logit_glue.h"

namespace tiger {
namespace featup {
namespace {

at::Tensor masked_logit_cuda(const at::Tensor& x, const std::optional<at::Tensor>& keep, double keep_scale,
                             const at::Tensor& weight, const at::Tensor& bias) {
  const LogitDims d = check_masked_logit(x, keep, keep_scale, weight, &bias);
  TORCH_CHECK(x.is_cuda(), kMaskedLogitOp, "x must be on a CUDA device here, got ", x.device());
  const c10::cuda::CUDAGuard guard(x.device());
  const auto xc = x.contiguous(), w = weight.contiguous(), b = bias.contiguous();
  const auto kc = contiguous(keep);
  auto logit = at::empty({x.size(0), x.size(1)}, xc.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(xc.scalar_type(), "tiger.masked_logit", [&] {
    launch_masked_logit_forward<scalar_t>(xc.data_ptr<scalar_t>(), optional_ptr<bool>(kc),
                                          static_cast<scalar_t>(keep_scale),
                                          w.data_ptr<scalar_t>(), b.data_ptr<scalar_t>(), d,
                                          logit.data_ptr<scalar_t>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return logit;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> masked_logit_backward_cuda(const at::Tensor& grad, const at::Tensor& x,
                                                                          const std::optional<at::Tensor>& keep,
                                                                          double keep_scale, const at::Tensor& weight,
                                                                          bool x_grad) {
  const LogitDims d = check_masked_logit(x, keep, keep_scale, weight, nullptr);
  check_masked_logit_grad(grad, x);
  TORCH_CHECK(x.is_cuda(), "tiger.masked_logit_backward: x must be on a CUDA device here, got ", x.device());
  const c10::cuda::CUDAGuard guard(x.device());
  const auto g = grad.contiguous(), xc = x.contiguous(), w = weight.contiguous();
  const auto kc = contiguous(keep);
  auto grad_x = x_grad ? at::empty_like(xc) : at::empty({0}, xc.options());
  auto grad_w = at::empty({d.U}, xc.options()), grad_b = at::empty({1}, xc.options());
  if (d.P == 0) {
    grad_w.zero_();
    grad_b.zero_();
    return {grad_x, grad_w, grad_b};
  }
  const int blocks = masked_logit_blocks(d.P);
  auto partials = at::empty({blocks, d.U + 1}, xc.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(xc.scalar_type(), "tiger.masked_logit_backward", [&] {
    launch_masked_logit_backward<scalar_t>(g.data_ptr<scalar_t>(), xc.data_ptr<scalar_t>(),
                                           optional_ptr<bool>(kc), static_cast<scalar_t>(keep_scale),
                                           w.data_ptr<scalar_t>(), d,
                                           x_grad ? grad_x.data_ptr<scalar_t>() : nullptr,
                                           partials.data_ptr<scalar_t>(), blocks, grad_w.data_ptr<scalar_t>(),
                                           grad_b.data_ptr<scalar_t>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {grad_x, grad_w, grad_b};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("masked_logit", &masked_logit_cuda);
  m.impl("masked_logit_backward", &masked_logit_backward_cuda);
}

}  // namespace featup
}  // namespace tiger
