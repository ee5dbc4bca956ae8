#pragma once
// Launcher of the CUDA row LayerNorm (layer_norm_cuda.cu).
#include <cstdint>

namespace tiger {
namespace layer_norm {

// y[r, :] = (u[r, :] - mean_r) * rstd_r * weight + bias for M contiguous rows of C values, with
// u = x + input_bias (in float); bias and input_bias may be null. Statistics of u in float (double
// for T = double), the result rounded once.
template <typename T>
void launch_layer_norm_rows(const T* x, const T* weight, const T* bias, const T* input_bias, T* y, int64_t M,
                            int64_t C, double eps, void* stream);

}  // namespace layer_norm
}  // namespace tiger
