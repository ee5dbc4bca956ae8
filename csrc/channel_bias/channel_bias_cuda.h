#pragma once
// Launcher of the CUDA channel-bias kernel (channel_bias_cuda.cu).
#include <cstdint>

namespace tiger {
namespace channel_bias {

// y[e] = x[e] + bias[(n,) channel(e)] (+ residual[e]) over n elements of a contiguous NCHW
// (inner = H·W) or NHWC (inner = 1) tensor with C channels and `plane` = C·H·W elements per
// sample; bias is [C], or [N, C] when per_sample, or null (y = x (+ residual)); residual (same
// layout as x) may be null. NHWC: y's rows (pixels) are out_row >= C elements apart (C: y has x's
// layout); NCHW: out_row is not read and y has x's layout. Computed in float, rounded once to T.
template <typename T>
void launch_channel_bias(const T* x, const T* bias, const T* residual, T* y, int64_t n, int64_t C, int64_t inner,
                         int64_t plane, int64_t out_row, bool per_sample, bool nhwc, void* stream);

// The sub-pixel upsampling's interleave: y's row (n, 2i+a, 2j+b) (C values; rows out_row >= C
// elements apart, NHWC) = z[n, i+a, j+b, (2a+b)·C : (2a+b+1)·C] (+ bias) for z NHWC [N, H+1, W+1, 4C];
// bias [C] or null (a copy). Summed in float, rounded once.
template <typename T>
void launch_subpixel_interleave(const T* z, const T* bias, T* y, int64_t N, int64_t C, int64_t H, int64_t W,
                                int64_t out_row, void* stream);

}  // namespace channel_bias
}  // namespace tiger
