// Torch glue of the CUDA fused SSIM (built only with CUDA). No host synchronisation.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "ssim/ssim.h"
#include "ssim/ssim_cuda.h"

namespace tiger {
namespace ssim {
namespace {

template <typename T>
Taps<T> device_taps(const Window& w) {
  Taps<T> t{};
  for (int i = 0; i <= 2 * w.radius; ++i) t.w[i] = T(w.taps[i]);
  t.radius = w.radius;
  return t;
}

void check_grid(const at::Tensor& img) {
  TORCH_CHECK(img.size(0) * img.size(1) <= 65535, kOp, " (CUDA): at most 65535 image planes (B*C), got ",
              img.size(0) * img.size(1));
  TORCH_CHECK(img.size(2) < (int64_t(1) << 30) && img.size(3) < (int64_t(1) << 30), kOp,
              " (CUDA): image too large: ", shape_str(img.sizes()));
}

std::tuple<at::Tensor, at::Tensor> fused_ssim_cuda(const at::Tensor& img1_in, const at::Tensor& img2_in,
                                                   at::ArrayRef<double> taps, double c1, double c2) {
  check_images(img1_in, img2_in);
  TORCH_CHECK(img1_in.is_cuda(), kOp, " (CUDA): images must be on a CUDA device");
  check_grid(img1_in);
  const Window w = check_taps(taps);
  const c10::cuda::CUDAGuard guard(img1_in.device());
  const auto img1 = img1_in.contiguous(), img2 = img2_in.contiguous();
  auto out = at::empty_like(img1);
  auto dm = at::empty({3, img1.size(0), img1.size(1), img1.size(2), img1.size(3)}, img1.options());
  const int64_t planes = img1.size(0) * img1.size(1);
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(img1.scalar_type(), "fused_ssim_cuda", [&] {
    using T = scalar_t;
    const cudaError_t err = launch_ssim_forward<T>(img1.data_ptr<T>(), img2.data_ptr<T>(), planes, int(img1.size(2)),
                                                   int(img1.size(3)), device_taps<T>(w), T(c1), T(c2),
                                                   out.data_ptr<T>(), dm.data_ptr<T>(), stream);
    TORCH_CHECK(err == cudaSuccess, kOp, ": CUDA error: ", cudaGetErrorString(err));
  });
  return {out, dm};
}

at::Tensor fused_ssim_backward_cuda(const at::Tensor& grad_in, const at::Tensor& img1_in, const at::Tensor& img2_in,
                                    const at::Tensor& dm_in, at::ArrayRef<double> taps) {
  check_backward(grad_in, img1_in, img2_in, dm_in);
  TORCH_CHECK(img1_in.is_cuda(), "tiger.fused_ssim_backward (CUDA): tensors must be on a CUDA device");
  check_grid(img1_in);
  const Window w = check_taps(taps);
  const c10::cuda::CUDAGuard guard(img1_in.device());
  const auto grad = grad_in.contiguous(), img1 = img1_in.contiguous(), img2 = img2_in.contiguous(),
             dm = dm_in.contiguous();
  auto dx = at::empty_like(img1);
  const int64_t planes = img1.size(0) * img1.size(1);
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(img1.scalar_type(), "fused_ssim_backward_cuda", [&] {
    using T = scalar_t;
    const cudaError_t err = launch_ssim_backward<T>(grad.data_ptr<T>(), img1.data_ptr<T>(), img2.data_ptr<T>(),
                                                    dm.data_ptr<T>(), planes, int(img1.size(2)), int(img1.size(3)),
                                                    device_taps<T>(w), dx.data_ptr<T>(), stream);
    TORCH_CHECK(err == cudaSuccess, "tiger.fused_ssim_backward: CUDA error: ", cudaGetErrorString(err));
  });
  return dx;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("fused_ssim", &fused_ssim_cuda);
  m.impl("fused_ssim_backward", &fused_ssim_backward_cuda);
}

}  // namespace ssim
}  // namespace tiger
