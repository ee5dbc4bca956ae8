// CPU kernels of tiger::magnitude_blur (formula in magnitude_blur.h): rows of pixels in parallel,
// every output element a gather of its own taps (the result does not depend on the threads).
#include <ATen/Parallel.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>
#include <torch/library.h>

#include <cmath>
#include <optional>
#include <tuple>
#include <vector>

#include "common/optional_tensor.h"
#include "featup/blur_math.h"
#include "featup/magnitude_blur.h"
#include "featup/magnitude_blur_glue.h"
#include "featup/stored_types.h"

namespace tiger {
namespace featup {
namespace {

template <typename X, typename T>
void forward_cpu(const X* x, const BlurDims& d, const BlurTaps<T>& taps, T* blurred, T* magnitude) {
  const int64_t H = d.H, W = d.W, C = d.C, U = C + 1, R = d.radius;
  at::parallel_for(0, H * W, 256, [&](int64_t p0, int64_t p1) {
    for (int64_t p = p0; p < p1; ++p) {
      T sum = 0;
      for (int64_t c = 0; c < C; ++c) {
        const T v = static_cast<T>(x[p * C + c]);
        sum += v * v;
      }
      magnitude[p] = std::sqrt(sum);
    }
  });
  at::parallel_for(0, H, 1, [&](int64_t y0, int64_t y1) {
    std::vector<T> acc(U), row(U);
    for (int64_t y = y0; y < y1; ++y) {
      for (int64_t xo = 0; xo < W; ++xo) {
        std::fill(acc.begin(), acc.end(), T(0));
        for (int64_t a = -R; a <= R; ++a) {
          const int64_t sy = reflect_index(y + a, H);
          std::fill(row.begin(), row.end(), T(0));
          for (int64_t b = -R; b <= R; ++b) {
            const int64_t q = sy * W + reflect_index(xo + b, W);
            const T gb = taps.g[b + R];
            const X* src = x + q * C;
            row[0] += gb * magnitude[q];  // channel 0: the magnitude; then the features
            for (int64_t c = 0; c < C; ++c) row[1 + c] += gb * static_cast<T>(src[c]);
          }
          const T ga = taps.g[a + R];
          for (int64_t k = 0; k < U; ++k) acc[k] += ga * row[k];
        }
        std::copy(acc.begin(), acc.end(), blurred + (y * W + xo) * U);
      }
    }
  });
}

template <typename X, typename T>
void backward_cpu(const T* grad_blurred, const T* grad_magnitude, const X* x, const T* magnitude, const BlurDims& d,
                  const BlurTaps<T>& taps, X* grad_x) {
  const int64_t H = d.H, W = d.W, C = d.C, U = C + 1;
  at::parallel_for(0, H, 1, [&](int64_t y0, int64_t y1) {
    std::vector<T> acc(U), row(U);
    AdjointTaps<T> ty, tx;
    for (int64_t y = y0; y < y1; ++y) {
      adjoint_taps(y, H, taps.g, d.radius, ty);
      for (int64_t xo = 0; xo < W; ++xo) {
        adjoint_taps(xo, W, taps.g, d.radius, tx);
        std::fill(acc.begin(), acc.end(), T(0));
        for (int a = 0; a < ty.count; ++a) {
          std::fill(row.begin(), row.end(), T(0));
          for (int b = 0; b < tx.count; ++b) {
            const T* src = grad_blurred + (ty.index[a] * W + tx.index[b]) * U;
            for (int64_t k = 0; k < U; ++k) row[k] += tx.weight[b] * src[k];
          }
          for (int64_t k = 0; k < U; ++k) acc[k] += ty.weight[a] * row[k];
        }
        const int64_t p = y * W + xo;
        const T m = magnitude[p];
        const T gm = acc[0] + (grad_magnitude ? grad_magnitude[p] : T(0));
        const T s = m > T(0) ? gm / m : T(0);
        for (int64_t c = 0; c < C; ++c)
          grad_x[p * C + c] = static_cast<X>(acc[1 + c] + s * static_cast<T>(x[p * C + c]));
      }
    }
  });
}


std::tuple<at::Tensor, at::Tensor> magnitude_blur_cpu(const at::Tensor& x, int64_t radius, double sigma) {
  const BlurDims d = check_magnitude_blur(x, radius, sigma);
  TORCH_CHECK(x.device().is_cpu(), kMagnitudeBlurOp, "x must be on the CPU here, got ", x.device());
  const auto xc = x.contiguous();
  const auto opts = xc.options().dtype(blur_out_dtype(xc.scalar_type()));
  auto blurred = at::empty({d.H, d.W, d.C + 1}, opts), magnitude = at::empty({d.H, d.W}, opts);
  dispatch_stored_types(xc.scalar_type(), kMagnitudeBlurOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    forward_cpu<X, T>(reinterpret_cast<const X*>(xc.data_ptr()), d, blur_taps<T>(d.radius, sigma),
                      blurred.data_ptr<T>(), magnitude.data_ptr<T>());
  });
  return {blurred, magnitude};
}

at::Tensor magnitude_blur_backward_cpu(const at::Tensor& grad_blurred, const std::optional<at::Tensor>& grad_magnitude,
                                       const at::Tensor& x, const at::Tensor& magnitude, int64_t radius, double sigma) {
  const BlurDims d = check_magnitude_blur(x, radius, sigma);
  check_magnitude_blur_backward(grad_blurred, grad_magnitude, x, magnitude, d);
  TORCH_CHECK(x.device().is_cpu(), "tiger.magnitude_blur_backward: x must be on the CPU here, got ", x.device());
  const auto g = grad_blurred.contiguous(), xc = x.contiguous(), m = magnitude.contiguous();
  const auto gm = contiguous(grad_magnitude);
  auto grad_x = at::empty_like(xc);
  dispatch_stored_types(xc.scalar_type(), kMagnitudeBlurOp, [&](auto xt, auto t) {
    using X = decltype(xt);
    using T = decltype(t);
    backward_cpu<X, T>(g.data_ptr<T>(), optional_ptr<T>(gm),
                       reinterpret_cast<const X*>(xc.data_ptr()), m.data_ptr<T>(), d, blur_taps<T>(d.radius, sigma),
                       reinterpret_cast<X*>(grad_x.data_ptr()));
  });
  return grad_x;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("magnitude_blur", &magnitude_blur_cpu);
  m.impl("magnitude_blur_backward", &magnitude_blur_backward_cpu);
}

}  // namespace featup
}  // namespace tiger
