#pragma once
// Launcher of the CUDA channel-bias kernel (channel_bias_cuda.cu).
#include <cstdint>

namespace tiger {
namespace channel_bias {

// y[e] = x[e] + bias[channel(e)] over n elements of a contiguous NCHW (inner = H·W) or NHWC
// (inner = 1) tensor with C channels; computed in float, rounded once to T.
template <typename T>
void launch_channel_bias(const T* x, const T* bias, T* y, int64_t n, int64_t C, int64_t inner, bool nhwc,
                         void* stream);

}  // namespace channel_bias
}  // namespace tiger
