#pragma once
// tiger::magnitude_blur — the fast FeatUp fit's map before its attention downsampler, channels
// last: each pixel's feature magnitude, and a separable Gaussian blur with reflect padding of
// (magnitude, features), with no channels-first copy.
//
//   x     [H, W, C]      the implicit network's output (float32/float64; bfloat16/float16 too)
//   radius, sigma        taps g[t] = exp(-t^2 / (2 sigma^2)) / sum, t in [-radius, radius]
//                        (tiger.utils.filters.gaussian_taps with size 2 radius + 1), radius < H, W
//
//   m[y, x]          = sqrt(sum_c x[y, x, c]^2)
//   u[y, x, 0]       = m[y, x];   u[y, x, 1 + c] = x[y, x, c]
//   blurred[y, x, k] = sum_a g[a] sum_b g[b] u[r_H(y + a), r_W(x + b), k]
//                      (r_n: F.pad's "reflect" about 0 and n - 1; the inner sum runs along W,
//                      as gaussian_blur's depthwise convolutions do)
// Outputs: blurred [H, W, C + 1] and magnitude m [H, W], float32 (float64 for float64 x).
//
// Backward (magnitude_blur_backward), gb = grad of blurred, gm = grad of magnitude (optional):
//   gu = B^T gb   (B's transpose: the reflected taps scattered back, gathered per pixel)
//   s[y, x] = (gu[y, x, 0] + gm[y, x]) / m[y, x]   (0 where m = 0, as torch.norm's backward)
//   grad_x[y, x, c] = gu[y, x, 1 + c] + s[y, x] x[y, x, c]     (x's dtype)
// Every output element is a gather of its own taps: no atomics, the same result on every run.
#include <cstdint>

namespace tiger {
namespace featup {

constexpr int kMaxBlurRadius = 8;

struct BlurDims {
  int64_t H, W, C;
  int radius;
};

// The normalised taps g[0 .. 2 radius] in T (computed in double, then rounded once).
template <typename T>
struct BlurTaps {
  T g[2 * kMaxBlurRadius + 1];
};

// X: the features' storage type; T: float (double for double X), the outputs' type.
template <typename X, typename T>
void launch_magnitude_blur_forward(const X* x, BlurDims d, BlurTaps<T> taps, T* blurred, T* magnitude,
                                   void* stream);

// grad_magnitude may be null; scale [H, W] is scratch (s above).
template <typename X, typename T>
void launch_magnitude_blur_backward(const T* grad_blurred, const T* grad_magnitude, const X* x, const T* magnitude,
                                    BlurDims d, BlurTaps<T> taps, T* scale, X* grad_x, void* stream);

}  // namespace featup
}  // namespace tiger
