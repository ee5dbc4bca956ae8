#pragma once
// Per-pixel SSIM (Wang et al. 2004, as in 3DGS's training loss) from the five local Gaussian
// moments, and its partial derivatives with respect to the moments of the first image, shared by
// the CPU and CUDA kernels. With mu = g*x, e11 = g*(x x), e12 = g*(x y) (g the window, mu2/e22
// fixed), d ssim / d x(p) = sum_q g(q - p) [dmu1(q) + 2 x(p) de11(q) + y(p) de12(q)]: the backward
// needs only these three derivative maps and the window again.
#include "common/macros.h"

namespace tiger {
namespace ssim {

constexpr int kMaxWindow = 11;  // the fused kernels' window (3DGS's 11 taps, sigma 1.5)

template <typename T>
struct SsimPixel {
  T value;  // SSIM at the pixel
  T dmu1;   // d value / d mu1 (through mu1 and through the variances that contain it)
  T de11;   // d value / d e11 (e11 = local mean of x*x)
  T de12;   // d value / d e12 (e12 = local mean of x*y)
};

template <typename T>
TIGER_HD SsimPixel<T> ssim_pixel(T mu1, T mu2, T e11, T e22, T e12, T c1, T c2) {
  const T mu1_sq = mu1 * mu1, mu2_sq = mu2 * mu2, mu12 = mu1 * mu2;
  const T s1 = e11 - mu1_sq, s2 = e22 - mu2_sq, s12 = e12 - mu12;
  const T a = T(2) * mu12 + c1, b = T(2) * s12 + c2;  // numerator factors
  const T c = mu1_sq + mu2_sq + c1, d = s1 + s2 + c2;  // denominator factors
  const T inv_cd = T(1) / (c * d);
  SsimPixel<T> out;
  out.value = a * b * inv_cd;
  const T d_a = b * inv_cd, d_b = a * inv_cd;            // d value / d a, d value / d b
  const T d_c = -out.value / c, d_d = -out.value / d;    // d value / d c, d value / d d
  // a, b, c, d depend on mu1 as 2 mu2, -2 mu2, 2 mu1, -2 mu1; on e11 only through d; on e12 through b.
  out.dmu1 = T(2) * mu2 * (d_a - d_b) + T(2) * mu1 * (d_c - d_d);
  out.de11 = d_d;
  out.de12 = T(2) * d_b;
  return out;
}

}  // namespace ssim
}  // namespace tiger
