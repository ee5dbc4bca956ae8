// Torch glue of the CUDA spherical-harmonics kernels (built only with CUDA on).
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "common/torch_checks.h"
#include "sh.h"
#include "sh_cuda.h"

namespace tiger {

namespace {
// Coefficient rows readable in place: a contiguous [K, 3] block per Gaussian (rows may be
// strided, e.g. the first bands of a scene's sh_rest).
at::Tensor row_blocks(const at::Tensor& c) {
  const bool ok = c.stride(2) == 1 && (c.size(1) <= 1 || c.stride(1) == 3);
  return ok ? c : c.contiguous();
}

// Both coefficient tensors in place (float32, staged kernels); else the joined copy.
bool in_place(const at::Tensor& dirs, const at::Tensor& coeffs, const std::optional<at::Tensor>& rest) {
  const int64_t k = coeffs.size(1) + (rest.has_value() ? rest->size(1) : 0);
  return rest.has_value() && dirs.scalar_type() == at::kFloat && sh_staged_applies(k);
}
}  // namespace

at::Tensor sh_to_color_cuda(const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree,
                            const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest) {
  const char* op = "tiger.sh_to_color";
  check_sh_inputs(op, dirs, coeffs_in, degree, visible, rest);
  const c10::cuda::CUDAGuard guard(dirs.device());
  const int64_t n = dirs.size(0);
  auto out = at::zeros({n, 3}, dirs.options());
  const auto d = dirs.contiguous();
  const auto v = visible.has_value() ? visible->contiguous() : at::Tensor();
  const bool* vis = v.defined() ? v.data_ptr<bool>() : nullptr;
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  cudaError_t err = cudaSuccess;
  if (in_place(dirs, coeffs_in, rest)) {
    const auto c0 = row_blocks(coeffs_in), c1 = row_blocks(*rest);
    err = sh_to_color_split_cuda_launch(d.data_ptr<float>(), c0.data_ptr<float>(), n > 0 ? c0.stride(0) : 0,
                                        c0.size(1), c1.data_ptr<float>(), n > 0 ? c1.stride(0) : 0, c1.size(1), n,
                                        int(degree), vis, out.data_ptr<float>(), stream);
  } else {
    const auto c = joined_coeffs(coeffs_in, rest).contiguous();
    AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_cuda", [&] {
      using T = scalar_t;
      err = sh_to_color_cuda_launch<T>(d.data_ptr<T>(), c.data_ptr<T>(), n, c.size(1), int(degree), vis,
                                       out.data_ptr<T>(), stream);
    });
  }
  TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_to_color_backward_cuda(
    const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree, const std::optional<at::Tensor>& visible,
    const at::Tensor& v_colors, const std::optional<at::Tensor>& rest) {
  const char* op = "tiger.sh_to_color_backward";
  check_sh_inputs(op, dirs, coeffs_in, degree, visible, rest);
  check_shape(v_colors, op, "v_colors", {dirs.size(0), 3});
  check_same(v_colors, dirs, op, "v_colors");
  const c10::cuda::CUDAGuard guard(dirs.device());
  const int64_t n = dirs.size(0);
  auto v_dirs = at::zeros({n, 3}, dirs.options());
  const auto d = dirs.contiguous(), g = v_colors.contiguous();
  const auto v = visible.has_value() ? visible->contiguous() : at::Tensor();
  const bool* vis = v.defined() ? v.data_ptr<bool>() : nullptr;
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  cudaError_t err = cudaSuccess;
  if (in_place(dirs, coeffs_in, rest)) {
    const auto c0 = row_blocks(coeffs_in), c1 = row_blocks(*rest);
    // the staged kernel writes every row of both gradients: no zero fill
    auto v0 = at::empty({n, c0.size(1), 3}, dirs.options()), v1 = at::empty({n, c1.size(1), 3}, dirs.options());
    err = sh_to_color_backward_split_cuda_launch(
        d.data_ptr<float>(), c0.data_ptr<float>(), n > 0 ? c0.stride(0) : 0, c0.size(1), c1.data_ptr<float>(),
        n > 0 ? c1.stride(0) : 0, c1.size(1), n, int(degree), vis, g.data_ptr<float>(), v_dirs.data_ptr<float>(),
        v0.data_ptr<float>(), v1.data_ptr<float>(), stream);
    TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
    return {v_dirs, v0, v1};
  }
  const auto c = joined_coeffs(coeffs_in, rest).contiguous();
  const int64_t k = c.size(1);
  const bool all_rows = dirs.scalar_type() == at::kFloat && sh_staged_applies(k);
  auto v_coeffs = all_rows ? at::empty({n, k, 3}, dirs.options()) : at::zeros({n, k, 3}, dirs.options());
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_backward_cuda", [&] {
    using T = scalar_t;
    err = sh_to_color_backward_cuda_launch<T>(d.data_ptr<T>(), c.data_ptr<T>(), n, k, int(degree), vis,
                                              g.data_ptr<T>(), v_dirs.data_ptr<T>(), v_coeffs.data_ptr<T>(), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
  auto [v_c0, v_rest] = split_coeff_grads(v_coeffs, coeffs_in, rest);
  return {v_dirs, v_c0, v_rest};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("sh_to_color", &sh_to_color_cuda);
  m.impl("sh_to_color_backward", &sh_to_color_backward_cuda);
}

}  // namespace tiger
