// Torch glue of the CUDA magnitude_blur kernels (built only with CUDA). Every allocation's size
// follows from the shapes and nothing is read back: CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include <optional>
#include <tuple>

#include "common/optional_tensor.h"
#include "featup/magnitude_blur.h"
#include "featup/magnitude_blur_glue.h"
#include "featup/stored_types_cuda.h"

namespace tiger {
namespace featup {
namespace {

// The kernels' grids: one row of blocks per image row, 32-bit indices within a row.
void check_cuda_extent(const BlurDims& d, const char* op) {
  TORCH_CHECK(d.H <= 65535, op, "(CUDA): at most 65535 rows, got ", d.H);
  TORCH_CHECK(d.W * (d.C + 1) < (int64_t(1) << 31), op, "(CUDA): a row of W (C + 1) = ", d.W * (d.C + 1),
              " elements must stay below 2^31");
}


std::tuple<at::Tensor, at::Tensor> magnitude_blur_cuda(const at::Tensor& x, int64_t radius, double sigma) {
  const BlurDims d = check_magnitude_blur(x, radius, sigma);
  TORCH_CHECK(x.is_cuda(), kMagnitudeBlurOp, "x must be on a CUDA device here, got ", x.device());
  check_cuda_extent(d, kMagnitudeBlurOp);
  const c10::cuda::CUDAGuard guard(x.device());
  const auto xc = x.contiguous();
  const auto opts = xc.options().dtype(blur_out_dtype(xc.scalar_type()));
  auto blurred = at::empty({d.H, d.W, d.C + 1}, opts), magnitude = at::empty({d.H, d.W}, opts);
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch_cuda_stored_types(xc.scalar_type(), kMagnitudeBlurOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    launch_magnitude_blur_forward<X, T>(reinterpret_cast<const X*>(xc.data_ptr()), d, blur_taps<T>(d.radius, sigma),
                                        blurred.data_ptr<T>(), magnitude.data_ptr<T>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {blurred, magnitude};
}

at::Tensor magnitude_blur_backward_cuda(const at::Tensor& grad_blurred, const std::optional<at::Tensor>& grad_magnitude,
                                        const at::Tensor& x, const at::Tensor& magnitude, int64_t radius,
                                        double sigma) {
  const BlurDims d = check_magnitude_blur(x, radius, sigma);
  check_magnitude_blur_backward(grad_blurred, grad_magnitude, x, magnitude, d);
  TORCH_CHECK(x.is_cuda(), "tiger.magnitude_blur_backward: x must be on a CUDA device here, got ", x.device());
  check_cuda_extent(d, "tiger.magnitude_blur_backward: ");
  const c10::cuda::CUDAGuard guard(x.device());
  const auto g = grad_blurred.contiguous(), xc = x.contiguous(), m = magnitude.contiguous();
  const auto gm = contiguous(grad_magnitude);
  auto grad_x = at::empty_like(xc);
  auto scale = at::empty({d.H, d.W}, m.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch_cuda_stored_types(xc.scalar_type(), kMagnitudeBlurOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    launch_magnitude_blur_backward<X, T>(g.data_ptr<T>(), optional_ptr<T>(gm),
                                         reinterpret_cast<const X*>(xc.data_ptr()), m.data_ptr<T>(), d,
                                         blur_taps<T>(d.radius, sigma), scale.data_ptr<T>(),
                                         reinterpret_cast<X*>(grad_x.data_ptr()), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return grad_x;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("magnitude_blur", &magnitude_blur_cuda);
  m.impl("magnitude_blur_backward", &magnitude_blur_backward_cuda);
}

}  // namespace featup
}  // namespace tiger
