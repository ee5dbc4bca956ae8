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

// The staged kernels' two row sources: coeffs and (when given) rest, both read in place.
struct StagedSources {
  at::Tensor c0, c1;  // c1 undefined without rest
  int64_t pitch(const at::Tensor& c) const { return c.defined() && c.size(0) > 0 ? c.stride(0) : 0; }
  const float* ptr1() const { return c1.defined() ? c1.data_ptr<float>() : nullptr; }
  int64_t k1() const { return c1.defined() ? c1.size(1) : 0; }
};

// float32 rows that fit the staged kernels (the default) go there, coefficients in place; the
// rest (float64, the ops' _staged=False, very long rows) through the plain kernels on a joined
// copy.
bool staged(const at::Tensor& dirs, const at::Tensor& coeffs, const std::optional<at::Tensor>& rest,
            bool wanted) {
  const int64_t k = coeffs.size(1) + (rest.has_value() ? rest->size(1) : 0);
  return wanted && dirs.scalar_type() == at::kFloat && sh_staged_fits(k);
}

StagedSources staged_sources(const at::Tensor& coeffs, const std::optional<at::Tensor>& rest) {
  return {row_blocks(coeffs), rest.has_value() ? row_blocks(*rest) : at::Tensor()};
}
}  // namespace

at::Tensor sh_to_color_cuda(const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree,
                            const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest,
                            bool staged_wanted, const std::optional<at::Tensor>& trainable) {
  const char* op = "tiger.sh_to_color";
  const ShViews sv = check_sh_inputs(op, dirs, coeffs_in, degree, visible, rest);
  const int64_t views = sv.views, n = sv.n;
  check_row_mask(trainable, n, dirs, op, "trainable", "dirs");
  const c10::cuda::CUDAGuard guard(dirs.device());
  auto out = at::zeros(dirs.sizes(), dirs.options());  // [N,3] or [V,N,3]; invisible rows keep 0
  const auto d = dirs.contiguous();
  const auto v = visible.has_value() ? visible->contiguous() : at::Tensor();
  const bool* vis = v.defined() ? v.data_ptr<bool>() : nullptr;
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  cudaError_t err = cudaSuccess;
  if (staged(dirs, coeffs_in, rest, staged_wanted)) {
    const StagedSources s = staged_sources(coeffs_in, rest);
    err = sh_to_color_staged_cuda_launch(d.data_ptr<float>(), s.c0.data_ptr<float>(), s.pitch(s.c0), s.c0.size(1),
                                        s.ptr1(), s.pitch(s.c1), s.k1(), views, n, int(degree), vis,
                                        out.data_ptr<float>(), stream);
  } else {
    const auto c = joined_coeffs(coeffs_in, rest).contiguous();
    AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_cuda", [&] {
      using T = scalar_t;
      err = sh_to_color_cuda_launch<T>(d.data_ptr<T>(), c.data_ptr<T>(), views, n, c.size(1), int(degree), vis,
                                       out.data_ptr<T>(), stream);
    });
  }
  TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_to_color_backward_cuda(
    const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree, const std::optional<at::Tensor>& visible,
    const at::Tensor& v_colors, const std::optional<at::Tensor>& rest, bool staged_wanted,
    const std::optional<at::Tensor>& trainable) {
  const char* op = "tiger.sh_to_color_backward";
  const ShViews sv = check_sh_inputs(op, dirs, coeffs_in, degree, visible, rest);
  const int64_t views = sv.views, n = sv.n;
  check_row_mask(trainable, n, dirs, op, "trainable", "dirs");
  check_per_view(v_colors, dirs, op, "v_colors", dirs.scalar_type(), true);
  const c10::cuda::CUDAGuard guard(dirs.device());
  auto v_dirs = at::zeros(dirs.sizes(), dirs.options());
  const auto d = dirs.contiguous(), g = v_colors.contiguous();
  // The kernels walk the (view, row) pairs visible in that view and trainable (both masks read
  // as they are: no [V,N] mask is built for the shared [N] one).
  const auto v = visible.has_value() ? visible->contiguous() : at::Tensor();
  const bool* vis = v.defined() ? v.data_ptr<bool>() : nullptr;
  const auto t = trainable.has_value() ? trainable->contiguous() : at::Tensor();
  const bool* tr = t.defined() ? t.data_ptr<bool>() : nullptr;
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  cudaError_t err = cudaSuccess;
  if (staged(dirs, coeffs_in, rest, staged_wanted)) {
    const StagedSources s = staged_sources(coeffs_in, rest);
    // the staged kernel writes every row of both gradients: no zero fill
    auto v0 = at::empty({n, s.c0.size(1), 3}, dirs.options());
    auto v1 = rest.has_value() ? at::empty({n, s.k1(), 3}, dirs.options()) : dirs.new_empty({0});
    err = sh_to_color_backward_staged_cuda_launch(
        d.data_ptr<float>(), s.c0.data_ptr<float>(), s.pitch(s.c0), s.c0.size(1), s.ptr1(), s.pitch(s.c1), s.k1(),
        views, n, int(degree), vis, tr, g.data_ptr<float>(), v_dirs.data_ptr<float>(), v0.data_ptr<float>(),
        rest.has_value() ? v1.data_ptr<float>() : nullptr, stream);
    TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
    return {v_dirs, v0, v1};
  }
  const auto c = joined_coeffs(coeffs_in, rest).contiguous();
  const int64_t k = c.size(1);
  auto v_coeffs = at::zeros({n, k, 3}, dirs.options());  // the plain kernel skips rows it does not walk
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_backward_cuda", [&] {
    using T = scalar_t;
    err = sh_to_color_backward_cuda_launch<T>(d.data_ptr<T>(), c.data_ptr<T>(), views, n, k, int(degree), vis, tr,
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
