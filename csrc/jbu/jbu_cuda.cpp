// Torch glue of the CUDA adaptive_conv kernels (built only with CUDA).
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAStream.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <tuple>

#include "jbu/jbu.h"
#include "jbu/jbu_glue.h"

namespace tiger {
namespace jbu {
namespace {

at::Tensor adaptive_conv_cuda(const at::Tensor& input_in, const at::Tensor& filters_in) {
  const Dims d = check_adaptive_conv(input_in, filters_in);
  TORCH_CHECK(input_in.is_cuda(), "tiger.adaptive_conv (CUDA): input must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(input_in.device());
  const auto input = input_in.contiguous();
  const auto filters = filters_in.contiguous();
  auto out = at::empty({d.B, d.C, d.H, d.W}, input.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "tiger.adaptive_conv", [&] {
    launch_adaptive_conv_forward<scalar_t>(input.data_ptr<scalar_t>(), filters.data_ptr<scalar_t>(), d.B, d.C,
                                           d.H, d.W, d.K, out.data_ptr<scalar_t>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

std::tuple<at::Tensor, at::Tensor> adaptive_conv_backward_cuda(const at::Tensor& grad_out_in,
                                                               const at::Tensor& input_in,
                                                               const at::Tensor& filters_in, bool need_input,
                                                               bool need_filters) {
  const Dims d = check_adaptive_conv(input_in, filters_in);
  TORCH_CHECK(grad_out_in.sizes() == at::IntArrayRef({d.B, d.C, d.H, d.W}),
              "tiger.adaptive_conv_backward: grad_out must be [B, C, H, W] = [", d.B, ", ", d.C, ", ", d.H,
              ", ", d.W, "], got ", grad_out_in.sizes());
  const c10::cuda::CUDAGuard guard(input_in.device());
  const auto go = grad_out_in.to(input_in.scalar_type()).contiguous();
  const auto input = input_in.contiguous();
  const auto filters = filters_in.contiguous();
  auto gi = need_input ? at::empty_like(input) : at::zeros_like(input);
  auto gf = need_filters ? at::empty_like(filters) : at::zeros_like(filters);
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "tiger.adaptive_conv_backward", [&] {
    if (need_input)
      launch_adaptive_conv_grad_input<scalar_t>(go.data_ptr<scalar_t>(), filters.data_ptr<scalar_t>(), d.B, d.C,
                                                d.H, d.W, d.K, gi.data_ptr<scalar_t>(), stream);
    if (need_filters)
      launch_adaptive_conv_grad_filters<scalar_t>(go.data_ptr<scalar_t>(), input.data_ptr<scalar_t>(), d.B, d.C,
                                                  d.H, d.W, d.K, gf.data_ptr<scalar_t>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {gi, gf};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("adaptive_conv", &adaptive_conv_cuda);
  m.impl("adaptive_conv_backward", &adaptive_conv_backward_cuda);
}

}  // namespace jbu
}  // namespace tiger
