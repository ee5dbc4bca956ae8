// Torch glue of the CUDA fourier_layer_norm kernels (built only with CUDA). Every allocation's
// size follows from the shapes and nothing is read back: CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include <optional>
#include <tuple>

#include "common/optional_tensor.h"
#include "featup/fourier.h"
#include "featup/fourier_glue.h"

namespace tiger {
namespace featup {
namespace {

// Calls f(T{}, O{}) with the CUDA types the kernels are instantiated for: T float or double (the
// inputs), O = T, __nv_bfloat16 or __half (the output and its gradient).
template <typename Fn>
void dispatch_cuda_types(at::ScalarType in_dt, at::ScalarType out_dt, Fn&& f) {
  auto with_out = [&](auto t) {
    using T = decltype(t);
    if (out_dt == in_dt) {
      f(T{}, T{});
    } else if (out_dt == at::kBFloat16) {
      f(T{}, __nv_bfloat16{});
    } else {
      f(T{}, __half{});
    }
  };
  if (in_dt == at::kDouble) {
    with_out(double{});
  } else {
    with_out(float{});
  }
}

void check_cuda(const at::Tensor& inputs, const FourierDims& d, const char* op) {
  TORCH_CHECK(inputs.is_cuda(), op, " (CUDA): inputs must be on a CUDA device");
  TORCH_CHECK(d.C <= kMaxFourierChannels, op, " (CUDA): at most ", kMaxFourierChannels, " channels (",
              (kMaxFourierChannels - 3) / 10, " frequencies), got ", d.C);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> fourier_cuda(const at::Tensor& inputs, const at::Tensor& freqs,
                                                            const at::Tensor& phase, const at::Tensor& weight,
                                                            const at::Tensor& bias,
                                                            const std::optional<at::Tensor>& scale, double eps,
                                                            std::optional<at::ScalarType> out_dtype) {
  const FourierDims d = check_fourier(inputs, freqs, phase, weight, bias, scale);
  const at::ScalarType odt = fourier_out_dtype(inputs, out_dtype);
  check_cuda(inputs, d, "tiger.fourier_layer_norm");
  const c10::cuda::CUDAGuard guard(inputs.device());
  const auto in = inputs.contiguous(), fr = freqs.contiguous(), ph = phase.contiguous(), w = weight.contiguous(),
             b = bias.contiguous();
  const auto s = contiguous(scale);
  auto out = at::empty({d.B, d.N, d.C}, in.options().dtype(odt));
  auto mean = at::empty({d.B, d.N}, in.options()), rstd = at::empty({d.B, d.N}, in.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch_cuda_types(in.scalar_type(), odt, [&](auto t, auto o) {
    using T = decltype(t);
    using O = decltype(o);
    launch_fourier_forward<T, O>(in.data_ptr<T>(), fr.data_ptr<T>(), ph.data_ptr<T>(), w.data_ptr<T>(),
                                 b.data_ptr<T>(), optional_ptr<T>(s), d, eps, reinterpret_cast<O*>(out.data_ptr()),
                                 mean.data_ptr<T>(), rstd.data_ptr<T>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, mean, rstd};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> fourier_backward_cuda(
    const at::Tensor& grad_out, const at::Tensor& inputs, const at::Tensor& freqs, const at::Tensor& phase,
    const at::Tensor& weight, const std::optional<at::Tensor>& scale, const at::Tensor& mean, const at::Tensor& rstd,
    bool input_grad) {
  const FourierDims d = check_fourier(inputs, freqs, phase, weight, weight, scale);
  check_fourier_backward(grad_out, inputs, mean, rstd, d);
  check_cuda(inputs, d, "tiger.fourier_layer_norm_backward");
  const c10::cuda::CUDAGuard guard(inputs.device());
  const auto g = grad_out.contiguous(), in = inputs.contiguous(), fr = freqs.contiguous(), ph = phase.contiguous(),
             w = weight.contiguous(), mu = mean.contiguous(), rs = rstd.contiguous();
  const auto s = contiguous(scale);
  const int64_t pixels = d.B * d.N;
  auto grad_in = input_grad ? at::empty({d.B, d.N, kFourierInputs}, in.options()) : at::empty({0}, in.options());
  auto grad_phase = at::empty({2, kFourierInputs, d.F}, in.options());
  auto grad_weight = at::empty({d.C}, in.options()), grad_bias = at::empty({d.C}, in.options());
  if (pixels == 0) {
    grad_phase.zero_();
    grad_weight.zero_();
    grad_bias.zero_();
    return {grad_in, grad_phase, grad_weight, grad_bias};
  }
  const int blocks = fourier_backward_blocks(pixels);
  auto partials = at::empty({blocks, 3 * d.C}, in.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch_cuda_types(in.scalar_type(), g.scalar_type(), [&](auto t, auto o) {
    using T = decltype(t);
    using O = decltype(o);
    launch_fourier_backward<T, O>(reinterpret_cast<const O*>(g.data_ptr()), in.data_ptr<T>(), fr.data_ptr<T>(),
                                  ph.data_ptr<T>(), w.data_ptr<T>(), optional_ptr<T>(s), mu.data_ptr<T>(),
                                  rs.data_ptr<T>(), d, input_grad ? grad_in.data_ptr<T>() : nullptr,
                                  partials.data_ptr<T>(), blocks, grad_phase.data_ptr<T>(),
                                  grad_weight.data_ptr<T>(), grad_bias.data_ptr<T>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {grad_in, grad_phase, grad_weight, grad_bias};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("fourier_layer_norm", &fourier_cuda);
  m.impl("fourier_layer_norm_backward", &fourier_backward_cuda);
}

}  // namespace featup
}  // namespace tiger
