// CPU kernels of tiger::relu_scale_layer_norm (formula in relu_norm.h): pixels in parallel for
// the forward; the backward's sums over pixels through fixed blocks of pixels, summed in block
// order, so the result does not depend on the number of threads.
#include <ATen/Parallel.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <optional>
#include <tuple>
#include <vector>

#include "common/optional_tensor.h"
#include "featup/relu_norm.h"
#include "featup/relu_norm_glue.h"
#include "featup/stored_types.h"

namespace tiger {
namespace featup {
namespace {

constexpr int64_t kPixelBlock = 512;  // pixels per partial row of the backward

// z [D] of pixel p: max(x, 0) * scale.
template <typename X, typename T>
void relu_scaled(const X* x, const T* s, int64_t D, T* z) {
  for (int64_t c = 0; c < D; ++c) {
    const T v = static_cast<T>(x[c]);
    z[c] = (v > T(0) ? v : T(0)) * (s ? s[c] : T(1));
  }
}

template <typename X, typename T>
void forward_cpu(const X* x, const T* scale, const T* w, const T* b, const NormDims& d, T eps, X* out, T* mean,
                 T* rstd) {
  const int64_t D = d.D;
  at::parallel_for(0, d.B * d.N, 64, [&](int64_t p0, int64_t p1) {
    std::vector<T> z(D);
    for (int64_t p = p0; p < p1; ++p) {
      relu_scaled(x + p * D, scale ? scale + (p / d.N) * D : nullptr, D, z.data());
      T sum = 0;
      for (int64_t c = 0; c < D; ++c) sum += z[c];
      const T m = sum / T(D);
      T var = 0;
      for (int64_t c = 0; c < D; ++c) var += (z[c] - m) * (z[c] - m);
      const T r = T(1) / std::sqrt(var / T(D) + eps);
      mean[p] = m;
      rstd[p] = r;
      for (int64_t c = 0; c < D; ++c) out[p * D + c] = static_cast<X>((z[c] - m) * r * w[c] + b[c]);
    }
  });
}

template <typename X, typename T>
void backward_cpu(const X* grad, const X* x, const T* scale, const T* w, const T* mean, const T* rstd,
                  const NormDims& d, X* grad_x, T* partials, T* grad_w, T* grad_b) {
  const int64_t D = d.D, P = d.B * d.N, blocks = (P + kPixelBlock - 1) / kPixelBlock;
  at::parallel_for(0, blocks, 1, [&](int64_t k0, int64_t k1) {
    std::vector<T> z(D), g(D);
    for (int64_t k = k0; k < k1; ++k) {
      T* gw = partials + k * 2 * D;
      T* gb = gw + D;
      std::fill(gw, gw + 2 * D, T(0));
      for (int64_t p = k * kPixelBlock; p < std::min(P, (k + 1) * kPixelBlock); ++p) {
        const T* s = scale ? scale + (p / d.N) * D : nullptr;
        relu_scaled(x + p * D, s, D, z.data());
        const T m = mean[p], r = rstd[p];
        T sum_gw = 0, sum_gwzh = 0;
        for (int64_t c = 0; c < D; ++c) {
          z[c] = (z[c] - m) * r;  // now zh
          g[c] = static_cast<T>(grad[p * D + c]);
          gw[c] += g[c] * z[c];
          gb[c] += g[c];
          sum_gw += g[c] * w[c];
          sum_gwzh += g[c] * w[c] * z[c];
        }
        const T mg = sum_gw / T(D), mgzh = sum_gwzh / T(D);
        for (int64_t c = 0; c < D; ++c) {
          const T dz = r * (g[c] * w[c] - mg - z[c] * mgzh);
          grad_x[p * D + c] = static_cast<X>(static_cast<T>(x[p * D + c]) > T(0) ? dz * (s ? s[c] : T(1)) : T(0));
        }
      }
    }
  });
  for (int64_t j = 0; j < 2 * D; ++j) {
    T total = 0;
    for (int64_t k = 0; k < blocks; ++k) total += partials[k * 2 * D + j];
    (j < D ? grad_w[j] : grad_b[j - D]) = total;
  }
}


std::tuple<at::Tensor, at::Tensor, at::Tensor> relu_norm_cpu(const at::Tensor& x, const std::optional<at::Tensor>& scale,
                                                             const at::Tensor& weight, const at::Tensor& bias,
                                                             double eps) {
  const NormDims d = check_relu_norm(x, scale, weight, bias);
  TORCH_CHECK(x.device().is_cpu(), kReluNormOp, "x must be on the CPU here, got ", x.device());
  const auto xc = x.contiguous(), w = weight.contiguous(), b = bias.contiguous();
  const auto s = contiguous(scale);
  auto out = at::empty_like(xc);
  auto mean = at::empty({d.B, d.N}, w.options()), rstd = at::empty({d.B, d.N}, w.options());
  dispatch_stored_types(xc.scalar_type(), kReluNormOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    forward_cpu<X, T>(reinterpret_cast<const X*>(xc.data_ptr()), optional_ptr<T>(s), w.data_ptr<T>(),
                      b.data_ptr<T>(), d, static_cast<T>(eps), reinterpret_cast<X*>(out.data_ptr()),
                      mean.data_ptr<T>(), rstd.data_ptr<T>());
  });
  return {out, mean, rstd};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> relu_norm_backward_cpu(const at::Tensor& grad_out, const at::Tensor& x,
                                                                      const std::optional<at::Tensor>& scale,
                                                                      const at::Tensor& weight, const at::Tensor& mean,
                                                                      const at::Tensor& rstd) {
  const NormDims d = check_relu_norm(x, scale, weight, weight);
  check_relu_norm_backward(grad_out, x, mean, rstd, d);
  TORCH_CHECK(x.device().is_cpu(), "tiger.relu_scale_layer_norm_backward: x must be on the CPU here");
  const auto g = grad_out.contiguous(), xc = x.contiguous(), w = weight.contiguous(), mu = mean.contiguous(),
             rs = rstd.contiguous();
  const auto s = contiguous(scale);
  const int64_t blocks = (d.B * d.N + kPixelBlock - 1) / kPixelBlock;
  auto grad_x = at::empty_like(xc);
  auto partials = at::empty({blocks, 2 * d.D}, w.options());
  auto grad_w = at::empty({d.D}, w.options()), grad_b = at::empty({d.D}, w.options());
  dispatch_stored_types(xc.scalar_type(), kReluNormOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    backward_cpu<X, T>(reinterpret_cast<const X*>(g.data_ptr()), reinterpret_cast<const X*>(xc.data_ptr()),
                       optional_ptr<T>(s), w.data_ptr<T>(), mu.data_ptr<T>(), rs.data_ptr<T>(), d,
                       reinterpret_cast<X*>(grad_x.data_ptr()), partials.data_ptr<T>(), grad_w.data_ptr<T>(),
                       grad_b.data_ptr<T>());
  });
  return {grad_x, grad_w, grad_b};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("relu_scale_layer_norm", &relu_norm_cpu);
  m.impl("relu_scale_layer_norm_backward", &relu_norm_backward_cpu);
}

}  // namespace featup
}  // namespace tiger
