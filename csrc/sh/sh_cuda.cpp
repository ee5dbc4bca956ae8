// Torch glue of the CUDA spherical-harmonics kernels (built only with CUDA on).
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "common/torch_checks.h"
#include "sh.h"
#include "sh_cuda.h"

namespace tiger {

at::Tensor sh_to_color_cuda(const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                            const std::optional<at::Tensor>& visible) {
  const char* op = "tiger.sh_to_color";
  check_sh_inputs(op, dirs, coeffs, degree, visible);
  const c10::cuda::CUDAGuard guard(dirs.device());
  const int64_t n = dirs.size(0), k = coeffs.size(1);
  auto out = at::zeros({n, 3}, dirs.options());
  const auto d = dirs.contiguous(), c = coeffs.contiguous();
  const auto v = visible.has_value() ? visible->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_cuda", [&] {
    using T = scalar_t;
    const cudaError_t err = sh_to_color_cuda_launch<T>(
        d.data_ptr<T>(), c.data_ptr<T>(), n, k, int(degree), v.defined() ? v.data_ptr<bool>() : nullptr,
        out.data_ptr<T>(), c10::cuda::getCurrentCUDAStream().stream());
    TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> sh_to_color_backward_cuda(const at::Tensor& dirs,
                                                             const at::Tensor& coeffs,
                                                             int64_t degree,
                                                             const std::optional<at::Tensor>& visible,
                                                             const at::Tensor& v_colors) {
  const char* op = "tiger.sh_to_color_backward";
  check_sh_inputs(op, dirs, coeffs, degree, visible);
  check_shape(v_colors, op, "v_colors", {dirs.size(0), 3});
  check_same(v_colors, dirs, op, "v_colors");
  const c10::cuda::CUDAGuard guard(dirs.device());
  const int64_t n = dirs.size(0), k = coeffs.size(1);
  auto v_dirs = at::zeros({n, 3}, dirs.options());
  auto v_coeffs = at::zeros({n, k, 3}, dirs.options());
  const auto d = dirs.contiguous(), c = coeffs.contiguous(), g = v_colors.contiguous();
  const auto v = visible.has_value() ? visible->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_backward_cuda", [&] {
    using T = scalar_t;
    const cudaError_t err = sh_to_color_backward_cuda_launch<T>(
        d.data_ptr<T>(), c.data_ptr<T>(), n, k, int(degree), v.defined() ? v.data_ptr<bool>() : nullptr,
        g.data_ptr<T>(), v_dirs.data_ptr<T>(), v_coeffs.data_ptr<T>(),
        c10::cuda::getCurrentCUDAStream().stream());
    TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
  });
  return {v_dirs, v_coeffs};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("sh_to_color", &sh_to_color_cuda);
  m.impl("sh_to_color_backward", &sh_to_color_backward_cuda);
}

}  // namespace tiger
