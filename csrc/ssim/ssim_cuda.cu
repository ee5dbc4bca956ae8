// CUDA fused SSIM. One block per 32 x TH output tile of one image plane: the tile and its halo
// (the window radius, at most 5) go to shared memory once, the window is applied along rows into
// shared row sums, then along columns, and every output pixel is finished in registers. The
// forward reads two images and writes the SSIM map and its three derivative maps; the backward
// reads those and the images and writes d loss / d img1: two kernels for what the unfused loss
// spends ~40 elementwise and convolution kernels on (a torch.cat, four depthwise convolutions,
// the moment arithmetic and its autograd).
#include <type_traits>

#include "ssim/ssim_cuda.h"

namespace tiger {
namespace ssim {
namespace {

constexpr int kTileW = 32;         // output columns per block (one warp wide)
constexpr int kRowsPerPass = 8;    // blockDim.y
constexpr int kHalo = kMaxWindow / 2;
constexpr int kInW = kTileW + 2 * kHalo;

// Rows of output per block: 16 in float, 8 in double (shared memory stays under 48 KiB).
template <typename T>
struct TileRows {
  static constexpr int value = sizeof(T) == 4 ? 16 : 8;
};

// Loads K maps of the tile with its halo (zero outside the plane) into s[K][TH + 2 halo][kInW];
// value(k, i) gives map k at plane offset i.
template <typename T, int K, int TH, typename Value>
__device__ void load_halo(T (*s)[TH + 2 * kHalo][kInW], int H, int W, int x0, int y0, int r, Value&& value) {
  const int rows = TH + 2 * r, cols = kTileW + 2 * r;
  const int tid = threadIdx.y * kTileW + threadIdx.x, nthreads = kTileW * kRowsPerPass;
  for (int e = tid; e < rows * cols; e += nthreads) {
    const int row = e / cols, col = e - row * cols;
    const int gy = y0 - r + row, gx = x0 - r + col;
    const bool in = gy >= 0 && gy < H && gx >= 0 && gx < W;
    const int64_t i = in ? int64_t(gy) * W + gx : 0;
#pragma unroll
    for (int k = 0; k < K; ++k) s[k][row][col] = in ? value(k, i) : T(0);
  }
}

// The column pass of K row-filtered maps at output row j of the tile:
// sums[k] = sum_t taps[t] s_row[k][j + t][column of this thread].
template <typename T, int K, int TH, int R>
__device__ __forceinline__ void column_pass(const T (*s_row)[TH + 2 * kHalo][kTileW], const Taps<T>& taps, int j,
                                            T (&sums)[K]) {
#pragma unroll
  for (int k = 0; k < K; ++k) sums[k] = T(0);
#pragma unroll
  for (int t = 0; t <= 2 * R; ++t) {
    const T g = taps.w[t];
#pragma unroll
    for (int k = 0; k < K; ++k) sums[k] += g * s_row[k][j + t][threadIdx.x];
  }
}

// f(j, offset) for the output rows j of this thread's column of the tile (offset: the pixel's
// index in its plane), skipping pixels outside the plane.
template <int TH, typename F>
__device__ __forceinline__ void for_outputs(int H, int W, int x0, int y0, F&& f) {
  const int gx = x0 + threadIdx.x;
  if (gx >= W) return;
  for (int j = threadIdx.y; j < TH; j += kRowsPerPass) {
    const int gy = y0 + j;
    if (gy >= H) break;
    f(j, int64_t(gy) * W + gx);
  }
}

// R: the window radius, a template constant so that the tap loops unroll and the taps stay in
// the kernel's parameter space (a runtime index would copy them to local memory).
template <typename T, int TH, int R>
__global__ void __launch_bounds__(kTileW * kRowsPerPass)
    ssim_forward_kernel(const T* __restrict__ x, const T* __restrict__ y, int H, int W, Taps<T> taps, T c1, T c2,
                        T* __restrict__ out, T* __restrict__ dm, int64_t total) {
  __shared__ T s_in[2][TH + 2 * kHalo][kInW];
  __shared__ T s_row[5][TH + 2 * kHalo][kTileW];
  constexpr int r = R;
  const int x0 = blockIdx.x * kTileW, y0 = blockIdx.y * TH;
  const int64_t base = int64_t(blockIdx.z) * H * W;
  const T* xp = x + base;
  const T* yp = y + base;
  load_halo<T, 2, TH>(s_in, H, W, x0, y0, r, [&](int k, int64_t i) { return k == 0 ? xp[i] : yp[i]; });
  __syncthreads();
  const int rows = TH + 2 * r;
  for (int row = threadIdx.y; row < rows; row += kRowsPerPass) {
    T m[5] = {};
#pragma unroll
    for (int t = 0; t <= 2 * r; ++t) {
      const T g = taps.w[t], a = s_in[0][row][threadIdx.x + t], b = s_in[1][row][threadIdx.x + t];
      m[0] += g * a;
      m[1] += g * b;
      m[2] += g * a * a;
      m[3] += g * b * b;
      m[4] += g * a * b;
    }
#pragma unroll
    for (int k = 0; k < 5; ++k) s_row[k][row][threadIdx.x] = m[k];
  }
  __syncthreads();
  for_outputs<TH>(H, W, x0, y0, [&](int j, int64_t offset) {
    T m[5];
    column_pass<T, 5, TH, R>(s_row, taps, j, m);
    const SsimPixel<T> p = ssim_pixel<T>(m[0], m[1], m[2], m[3], m[4], c1, c2);
    const int64_t i = base + offset;
    out[i] = p.value;
    dm[i] = p.dmu1;
    dm[total + i] = p.de11;
    dm[2 * total + i] = p.de12;
  });
}

template <typename T, int TH, int R>
__global__ void __launch_bounds__(kTileW * kRowsPerPass)
    ssim_backward_kernel(const T* __restrict__ grad, const T* __restrict__ x, const T* __restrict__ y,
                         const T* __restrict__ dm, int H, int W, Taps<T> taps, T* __restrict__ dx, int64_t total) {
  __shared__ T s_in[3][TH + 2 * kHalo][kInW];
  __shared__ T s_row[3][TH + 2 * kHalo][kTileW];
  constexpr int r = R;
  const int x0 = blockIdx.x * kTileW, y0 = blockIdx.y * TH;
  const int64_t base = int64_t(blockIdx.z) * H * W;
  const T* gp = grad + base;
  const T* dp = dm + base;
  // the three derivative maps times the incoming gradient
  load_halo<T, 3, TH>(s_in, H, W, x0, y0, r, [&](int k, int64_t i) { return gp[i] * dp[k * total + i]; });
  __syncthreads();
  const int rows = TH + 2 * r;
  for (int row = threadIdx.y; row < rows; row += kRowsPerPass) {
    T m[3] = {};
#pragma unroll
    for (int t = 0; t <= 2 * r; ++t) {
      const T g = taps.w[t];
#pragma unroll
      for (int k = 0; k < 3; ++k) m[k] += g * s_in[k][row][threadIdx.x + t];
    }
#pragma unroll
    for (int k = 0; k < 3; ++k) s_row[k][row][threadIdx.x] = m[k];
  }
  __syncthreads();
  for_outputs<TH>(H, W, x0, y0, [&](int j, int64_t offset) {
    T b[3];
    column_pass<T, 3, TH, R>(s_row, taps, j, b);
    const int64_t i = base + offset;
    dx[i] = b[0] + T(2) * x[i] * b[1] + y[i] * b[2];
  });
}

template <typename T>
dim3 grid_of(int64_t planes, int H, int W) {
  constexpr int TH = TileRows<T>::value;
  return dim3(unsigned((W + kTileW - 1) / kTileW), unsigned((H + TH - 1) / TH), unsigned(planes));
}

// f(std::integral_constant<int, radius>) for radius 0..kHalo (the glue checked the range).
template <typename F>
void with_radius(int radius, F&& f) {
  switch (radius) {
    case 0: f(std::integral_constant<int, 0>()); break;
    case 1: f(std::integral_constant<int, 1>()); break;
    case 2: f(std::integral_constant<int, 2>()); break;
    case 3: f(std::integral_constant<int, 3>()); break;
    case 4: f(std::integral_constant<int, 4>()); break;
    default: f(std::integral_constant<int, kHalo>()); break;
  }
}

}  // namespace

template <typename T>
cudaError_t launch_ssim_forward(const T* x, const T* y, int64_t planes, int H, int W, const Taps<T>& taps, T c1,
                                T c2, T* out, T* dmoments, cudaStream_t stream) {
  if (planes == 0 || H == 0 || W == 0) return cudaSuccess;
  constexpr int TH = TileRows<T>::value;
  const dim3 grid = grid_of<T>(planes, H, W), block(kTileW, kRowsPerPass);
  const int64_t total = planes * H * W;
  with_radius(taps.radius, [&](auto r) {
    ssim_forward_kernel<T, TH, decltype(r)::value><<<grid, block, 0, stream>>>(x, y, H, W, taps, c1, c2, out,
                                                                               dmoments, total);
  });
  return cudaGetLastError();
}

template <typename T>
cudaError_t launch_ssim_backward(const T* grad, const T* x, const T* y, const T* dmoments, int64_t planes, int H,
                                 int W, const Taps<T>& taps, T* dx, cudaStream_t stream) {
  if (planes == 0 || H == 0 || W == 0) return cudaSuccess;
  constexpr int TH = TileRows<T>::value;
  const dim3 grid = grid_of<T>(planes, H, W), block(kTileW, kRowsPerPass);
  const int64_t total = planes * H * W;
  with_radius(taps.radius, [&](auto r) {
    ssim_backward_kernel<T, TH, decltype(r)::value><<<grid, block, 0, stream>>>(grad, x, y, dmoments, H, W, taps,
                                                                                dx, total);
  });
  return cudaGetLastError();
}

#define TIGER_INSTANTIATE(T)                                                                                 \
  template cudaError_t launch_ssim_forward<T>(const T*, const T*, int64_t, int, int, const Taps<T>&, T, T, T*, \
                                              T*, cudaStream_t);                                             \
  template cudaError_t launch_ssim_backward<T>(const T*, const T*, const T*, const T*, int64_t, int, int,     \
                                               const Taps<T>&, T*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace ssim
}  // namespace tiger
