#pragma once
// tiger::masked_logit — the attention downsampler's per-pixel logit in the fast FeatUp fit: a
// linear map of each pixel's channels after the input dropout, read channels last, with the
// dropout mask as torch draws it for the channels-first map (no transposed copy of either).
//
//   x           [H, W, U]  the blurred map, channels last (float32/float64)
//   keep        [U, H, W]  optional bool mask per channel and pixel (the dropout's kept
//                          elements, drawn channels first: 1 byte per element, not 4)
//   keep_scale             the kept elements' multiplier (1 / keep rate)
//   weight      [U], bias [1]
//
//   m[k, y, x]  = keep[k, y, x] ? keep_scale : 0                       (1 when keep is absent)
//   logit[y, x] = bias + sum_k weight[k] (x[y, x, k] m[k, y, x])
//
// Backward (masked_logit_backward), g = grad of logit [H, W]:
//   grad_x[y, x, k] = g[y, x] weight[k] m[k, y, x]
//   grad_weight[k]  = sum_pixels g (x[., k] m[k, .]);  grad_bias = sum_pixels g
// The sums over pixels go through fixed blocks of pixels, summed in block order (deterministic).
#include <cstdint>

#include "common/macros.h"

namespace tiger {
namespace featup {

struct LogitDims {
  int64_t P, U;  // pixels (H W), channels
};

// m above for element i = k P + p of the channels-first mask.
template <typename T>
TIGER_HD T keep_multiplier(const bool* keep, T keep_scale, int64_t i) {
  return keep ? (keep[i] ? keep_scale : T(0)) : T(1);
}

int masked_logit_blocks(int64_t pixels);

template <typename T>
void launch_masked_logit_forward(const T* x, const bool* keep, T keep_scale, const T* weight, const T* bias,
                                 LogitDims d, T* logit, void* stream);

// partials [blocks, U + 1] scratch; grad_x may be null (not needed).
template <typename T>
void launch_masked_logit_backward(const T* grad, const T* x, const bool* keep, T keep_scale, const T* weight,
                                  LogitDims d, T* grad_x, T* partials, int blocks, T* grad_weight, T* grad_bias,
                                  void* stream);

}  // namespace featup
}  // namespace tiger
