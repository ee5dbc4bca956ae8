#pragma once
// tiger::masked_logit — the attention downsampler's per-pixel logit in the fast FeatUp fit: a
// linear map of each pixel's channels after the input dropout, read channels last, with the
// dropout mask as torch draws it for the channels-first map (no transposed copy of either).
//
//   x       [H, W, U]   the blurred map, channels last (float32/float64)
//   keep    [U, H, W]   optional multiplier per channel and pixel (the dropout mask divided by the
//                       keep rate, drawn channels first), x's dtype; not differentiable
//   weight  [U], bias [1]
//
//   logit[y, x] = bias + sum_k weight[k] x[y, x, k] keep[k, y, x]        (keep = 1 when absent)
//
// Backward (masked_logit_backward), g = grad of logit [H, W]:
//   grad_x[y, x, k] = g[y, x] weight[k] keep[k, y, x]
//   grad_weight[k]  = sum_pixels g x[., k] keep[k, .];  grad_bias = sum_pixels g
// The sums over pixels go through fixed blocks of pixels, summed in block order (deterministic).
#include <cstdint>

namespace tiger {
namespace featup {

struct LogitDims {
  int64_t P, U;  // pixels (H W), channels
};

int masked_logit_blocks(int64_t pixels);

template <typename T>
void launch_masked_logit_forward(const T* x, const T* keep, const T* weight, const T* bias, LogitDims d, T* logit,
                                 void* stream);

// partials [blocks, U + 1] scratch; grad_x may be null (not needed).
template <typename T>
void launch_masked_logit_backward(const T* grad, const T* x, const T* keep, const T* weight, LogitDims d, T* grad_x,
                                  T* partials, int blocks, T* grad_weight, T* grad_bias, void* stream);

}  // namespace featup
}  // namespace tiger
