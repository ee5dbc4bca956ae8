// CUDA kernels of tiger::adaptive_conv (raw pointers, no torch headers).
#include <cuda_runtime.h>

#include "jbu/jbu.h"

namespace tiger {
namespace jbu {
namespace {

// One thread per output pixel and channel; x fastest, so a warp reads neighbouring input pixels
// and neighbouring filters (the K*K filter of a pixel is reused by all channels through L1/L2).
template <typename scalar_t>
__global__ void forward_kernel(const scalar_t* __restrict__ in, const scalar_t* __restrict__ f, int64_t B,
                               int64_t C, int64_t H, int64_t W, int64_t K, scalar_t* __restrict__ out) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * H * W) return;
  const int64_t x = t % W, y = (t / W) % H, bc = t / (W * H), b = bc / C;
  const int64_t Hp = H + K - 1, Wp = W + K - 1;
  const scalar_t* plane = in + bc * Hp * Wp;
  const scalar_t* k = f + ((b * H + y) * W + x) * K * K;
  scalar_t s = 0;
  for (int64_t i = 0; i < K; ++i)
    for (int64_t j = 0; j < K; ++j) s += plane[(y + i) * Wp + x + j] * k[i * K + j];
  out[t] = s;
}

template <typename scalar_t>
__global__ void grad_input_kernel(const scalar_t* __restrict__ go, const scalar_t* __restrict__ f, int64_t B,
                                  int64_t C, int64_t H, int64_t W, int64_t K, scalar_t* __restrict__ gi) {
  const int64_t Hp = H + K - 1, Wp = W + K - 1;
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * Hp * Wp) return;
  const int64_t xx = t % Wp, yy = (t / Wp) % Hp, bc = t / (Wp * Hp), b = bc / C;
  scalar_t s = 0;
  for (int64_t i = 0; i < K; ++i) {
    const int64_t y = yy - i;
    if (y < 0 || y >= H) continue;
    for (int64_t j = 0; j < K; ++j) {
      const int64_t x = xx - j;
      if (x < 0 || x >= W) continue;
      s += go[(bc * H + y) * W + x] * f[((b * H + y) * W + x) * K * K + i * K + j];
    }
  }
  gi[t] = s;
}

template <typename scalar_t>
__global__ void grad_filters_kernel(const scalar_t* __restrict__ go, const scalar_t* __restrict__ in,
                                    int64_t B, int64_t C, int64_t H, int64_t W, int64_t K,
                                    scalar_t* __restrict__ gf) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t KK = K * K;
  if (t >= B * H * W * KK) return;
  // Layout [B, H, W, K, K], but threads run x fastest so channel reads coalesce.
  const int64_t x = t % W, rest = t / W, ij = rest % KK, by = rest / KK, y = by % H, b = by / H;
  const int64_t i = ij / K, j = ij % K;
  const int64_t Hp = H + K - 1, Wp = W + K - 1;
  scalar_t s = 0;
  for (int64_t c = 0; c < C; ++c)
    s += go[((b * C + c) * H + y) * W + x] * in[((b * C + c) * Hp + y + i) * Wp + x + j];
  gf[((b * H + y) * W + x) * KK + ij] = s;
}

inline unsigned blocks(int64_t n) { return static_cast<unsigned>((n + 255) / 256); }

}  // namespace

template <typename scalar_t>
void launch_adaptive_conv_forward(const scalar_t* input, const scalar_t* filters, int64_t B, int64_t C,
                                  int64_t H, int64_t W, int64_t K, scalar_t* out, void* stream) {
  const int64_t n = B * C * H * W;
  if (n == 0) return;
  forward_kernel<scalar_t><<<blocks(n), 256, 0, static_cast<cudaStream_t>(stream)>>>(input, filters, B, C, H, W,
                                                                                     K, out);
}

template <typename scalar_t>
void launch_adaptive_conv_grad_input(const scalar_t* grad_out, const scalar_t* filters, int64_t B,
                                     int64_t C, int64_t H, int64_t W, int64_t K, scalar_t* grad_input,
                                     void* stream) {
  const int64_t n = B * C * (H + K - 1) * (W + K - 1);
  if (n == 0) return;
  grad_input_kernel<scalar_t><<<blocks(n), 256, 0, static_cast<cudaStream_t>(stream)>>>(grad_out, filters, B, C,
                                                                                        H, W, K, grad_input);
}

template <typename scalar_t>
void launch_adaptive_conv_grad_filters(const scalar_t* grad_out, const scalar_t* input, int64_t B,
                                       int64_t C, int64_t H, int64_t W, int64_t K,
                                       scalar_t* grad_filters, void* stream) {
  const int64_t n = B * H * W * K * K;
  if (n == 0) return;
  grad_filters_kernel<scalar_t><<<blocks(n), 256, 0, static_cast<cudaStream_t>(stream)>>>(
      grad_out, input, B, C, H, W, K, grad_filters);
}

#define TIGER_INSTANTIATE(T)                                                                                  \
  template void launch_adaptive_conv_forward<T>(const T*, const T*, int64_t, int64_t, int64_t, int64_t,      \
                                                int64_t, T*, void*);                                          \
  template void launch_adaptive_conv_grad_input<T>(const T*, const T*, int64_t, int64_t, int64_t, int64_t,   \
                                                   int64_t, T*, void*);                                       \
  template void launch_adaptive_conv_grad_filters<T>(const T*, const T*, int64_t, int64_t, int64_t, int64_t, \
                                                     int64_t, T*, void*);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace jbu
}  // namespace tiger
