#pragma once
// Launchers of the CUDA fused SSIM kernels (ssim_cuda.cu). Images are contiguous [planes, H, W];
// dmoments holds three such blocks (d/d mu1, d/d e11, d/d e12) one after the other.
#include <cuda_runtime.h>

#include <cstdint>

#include "ssim/ssim_math.h"

namespace tiger {
namespace ssim {

template <typename T>
struct Taps {
  T w[kMaxWindow];
  int radius;
};

template <typename T>
cudaError_t launch_ssim_forward(const T* x, const T* y, int64_t planes, int H, int W, const Taps<T>& taps, T c1,
                                T c2, T* out, T* dmoments, cudaStream_t stream);

template <typename T>
cudaError_t launch_ssim_backward(const T* grad, const T* x, const T* y, const T* dmoments, int64_t planes, int H,
                                 int W, const Taps<T>& taps, T* dx, cudaStream_t stream);

}  // namespace ssim
}  // namespace tiger
