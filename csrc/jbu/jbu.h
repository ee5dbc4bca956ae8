#pragma once
// tiger::adaptive_conv — the per-pixel ("adaptive") convolution of FeatUp's joint bilateral
// upsampler (JBU): every output pixel has its own K x K kernel, shared by all channels.
//
//   input   [B, C, H + K - 1, W + K - 1]   (already padded by the caller, FeatUp pads reflectively)
//   filters [B, H, W, K, K]
//   out[b, c, y, x] = sum_{i, j < K} input[b, c, y + i, x + j] * filters[b, y, x, i, j]
//
// Backward (adaptive_conv_backward):
//   grad_input[b, c, y + i, x + j] += grad_out[b, c, y, x] * filters[b, y, x, i, j]  (gathered)
//   grad_filters[b, y, x, i, j]     = sum_c grad_out[b, c, y, x] * input[b, c, y + i, x + j]
#include <cstdint>

namespace tiger {
namespace jbu {

template <typename scalar_t>
void launch_adaptive_conv_forward(const scalar_t* input, const scalar_t* filters, int64_t B, int64_t C,
                                  int64_t H, int64_t W, int64_t K, scalar_t* out, void* stream);

template <typename scalar_t>
void launch_adaptive_conv_grad_input(const scalar_t* grad_out, const scalar_t* filters, int64_t B,
                                     int64_t C, int64_t H, int64_t W, int64_t K, scalar_t* grad_input,
                                     void* stream);

template <typename scalar_t>
void launch_adaptive_conv_grad_filters(const scalar_t* grad_out, const scalar_t* input, int64_t B,
                                       int64_t C, int64_t H, int64_t W, int64_t K,
                                       scalar_t* grad_filters, void* stream);

}  // namespace jbu
}  // namespace tiger
