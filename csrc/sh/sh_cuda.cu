// CUDA kernels of the spherical-harmonics ops: the same sh_eval_views / sh_eval_vjp_views as the
// CPU kernels, one thread per Gaussian looping its V views (V = 1: one view), in float32 with the
// rows staged through shared memory (the glue's choice, sh_staged_fits), else reading each row
// directly.
#include "common/cuda_helpers.cuh"
#include "common/sh_math.h"
#include "sh_cuda.h"

namespace tiger {
namespace {

// Gaussian i's flags: view 0's entry of visible [V,N] (view v at + v n), null without a mask.
__device__ __forceinline__ const bool* row_flags(const bool* visible, int64_t i) {
  return visible ? visible + i : nullptr;
}

// Whether the backward walks Gaussian i: trainable, and visible in at least one view.
__device__ __forceinline__ bool row_walked(const bool* visible, const bool* trainable, int64_t views, int64_t n,
                                           int64_t i) {
  if (trainable && !trainable[i]) return false;
  if (!visible) return views > 0;
  for (int64_t v = 0; v < views; ++v)
    if (visible[v * n + i]) return true;
  return false;
}

template <typename T>
__global__ void sh_kernel(const T* dirs, const T* coeffs, int64_t views, int64_t n, int64_t k, int degree,
                          const bool* visible, T* colors) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  sh_eval_views<T>(degree, views, n, dirs + 3 * i, coeffs + i * k * 3, row_flags(visible, i), colors + 3 * i);
}

template <typename T>
__global__ void sh_backward_kernel(const T* dirs, const T* coeffs, int64_t views, int64_t n, int64_t k,
                                   int degree, const bool* visible, const bool* trainable, const T* v_colors,
                                   T* v_dirs, T* v_coeffs) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || (trainable && !trainable[i])) return;  // frozen rows: no gradient work
  sh_eval_vjp_views<T>(degree, views, n, dirs + 3 * i, coeffs + i * k * 3, row_flags(visible, i),
                       v_colors + 3 * i, v_coeffs + i * k * 3, v_dirs + 3 * i);
}

constexpr int kThreads = 256;

// Staged variants (float; the default, the ops' _staged=False selects the plain kernels; H100,
// 1M Gaussians, degree 3, forward + backward: 2.15 ms plain, 0.815 ms staged, docs/BENCHMARKS.md).
// A block copies its Gaussians' coefficient rows [rows, k, 3] between global and shared memory with consecutive
// threads on consecutive words, so the 4·3·k-byte rows of neighbouring threads are read and
// written in coalesced transactions instead of one strided row per thread. The shared row is
// padded to an odd length (3k + 1 words): thread t's row starts in bank (t·(3k+1)) mod 32, all
// different within a warp. Every row of the block is written (zeros for invisible Gaussians and
// unused bases), like the zero-initialised output of the plain kernel.
constexpr int kStagedThreads = 64;

// Block-local indices are 32-bit (kStagedThreads rows of 3k words, within 48 KiB): a 64-bit
// division per copied word cost more than the copy (measured on the H100).
__device__ __forceinline__ int staged_rows(int64_t n) {
  return static_cast<int>(min(static_cast<int64_t>(blockDim.x), n - static_cast<int64_t>(blockIdx.x) * blockDim.x));
}

// A coefficient source: rows of `width` words (3 per basis) `pitch` words apart; the staged row
// holds the sources one after the other (the DC block, then the rest: cat without the copy).
struct Rows {
  const float* in;
  float* out;
  int64_t pitch;
  int width;
};

// Shared row words [col0, col0 + width) of the block's rows <- / -> source rows.
// The copy walks word e = threadIdx.x, threadIdx.x + blockDim.x, ... of the rows * width
// block; (row, column) of e advance by a constant step, so one division per thread replaces
// one per copied word.
struct RowWalk {
  int r, c, dr, dc, width;
  __device__ RowWalk(int width_) : width(width_) {
    r = int(threadIdx.x) / width;
    c = int(threadIdx.x) - r * width;
    dr = int(blockDim.x) / width;
    dc = int(blockDim.x) - dr * width;
  }
  __device__ void next() {
    r += dr;
    c += dc;
    if (c >= width) {
      c -= width;
      ++r;
    }
  }
};

__device__ __forceinline__ void stage_in(const Rows& g, float* s, int rows, int row, int col0) {
  const float* src = g.in + static_cast<int64_t>(blockIdx.x) * blockDim.x * g.pitch;
  for (RowWalk w(g.width); w.r < rows; w.next()) s[w.r * row + col0 + w.c] = src[w.r * g.pitch + w.c];
}

__device__ __forceinline__ void stage_out(const float* s, const Rows& g, int rows, int row, int col0) {
  float* dst = g.out + static_cast<int64_t>(blockIdx.x) * blockDim.x * g.pitch;
  for (RowWalk w(g.width); w.r < rows; w.next()) dst[w.r * g.pitch + w.c] = s[w.r * row + col0 + w.c];
}

// Each row is staged once and evaluated for every view (the V-view call's saving over V calls).
__global__ void __launch_bounds__(kStagedThreads) sh_staged_kernel(const float* dirs, Rows a, Rows b, int64_t views,
                                                                   int64_t n, int degree, const bool* visible,
                                                                   float* colors) {
  extern __shared__ float s_coeffs[];  // [blockDim][3k + 1]
  const int row = a.width + b.width + 1, rows = staged_rows(n);
  stage_in(a, s_coeffs, rows, row, 0);
  if (b.width) stage_in(b, s_coeffs, rows, row, a.width);
  __syncthreads();
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (threadIdx.x < rows)
    sh_eval_views<float>(degree, views, n, dirs + 3 * i, s_coeffs + threadIdx.x * row, row_flags(visible, i),
                         colors + 3 * i);
}

// a.out / b.out: contiguous gradient rows (pitch = width), every row written: the sum over the
// views, accumulated in the shared row. A block none of whose rows is walked (row_walked: culled
// in every view, or frozen) writes zeros without staging: an edit's frozen Gaussians cost a write
// of their rows, not the walk.
__global__ void __launch_bounds__(kStagedThreads) sh_backward_staged_kernel(const float* dirs, Rows a, Rows b,
                                                                            int64_t views, int64_t n, int degree,
                                                                            const bool* visible,
                                                                            const bool* trainable,
                                                                            const float* v_colors, float* v_dirs) {
  extern __shared__ float s_mem[];  // coefficients, then their gradients: [blockDim][3k + 1] each
  const int row = a.width + b.width + 1, rows = staged_rows(n);
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const bool walked = threadIdx.x < rows && row_walked(visible, trainable, views, n, i);
  if (!__syncthreads_or(walked)) {  // no row of the block is walked (culled or frozen): zeros
    for (RowWalk w(a.width); w.r < rows; w.next()) a.out[(int64_t(blockIdx.x) * blockDim.x + w.r) * a.width + w.c] = 0.f;
    if (b.width)  // (RowWalk divides by its width: not built for an absent source)
      for (RowWalk w(b.width); w.r < rows; w.next())
        b.out[(int64_t(blockIdx.x) * blockDim.x + w.r) * b.width + w.c] = 0.f;
    return;
  }
  float* s_coeffs = s_mem;
  float* s_grad = s_mem + blockDim.x * row;
  stage_in(a, s_coeffs, rows, row, 0);
  if (b.width) stage_in(b, s_coeffs, rows, row, a.width);
  for (int e = threadIdx.x; e < static_cast<int>(blockDim.x) * row; e += blockDim.x) s_grad[e] = 0.f;
  __syncthreads();
  if (walked)
    sh_eval_vjp_views<float>(degree, views, n, dirs + 3 * i, s_coeffs + threadIdx.x * row, row_flags(visible, i),
                             v_colors + 3 * i, s_grad + threadIdx.x * row, v_dirs + 3 * i);
  __syncthreads();
  const Rows ga{nullptr, a.out, a.width, a.width}, gb{nullptr, b.out, b.width, b.width};
  stage_out(s_grad, ga, rows, row, 0);
  if (b.width) stage_out(s_grad, gb, rows, row, a.width);
}

size_t staged_bytes(int64_t k, int buffers) {
  return static_cast<size_t>(buffers) * kStagedThreads * (3 * k + 1) * sizeof(float);
}

}  // namespace

bool sh_staged_fits(int64_t k) { return staged_bytes(k, 2) <= 48 * 1024; }

template <typename T>
cudaError_t sh_to_color_cuda_launch(const T* dirs, const T* coeffs, int64_t views, int64_t n, int64_t k,
                                    int degree, const bool* visible, T* colors, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  sh_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(dirs, coeffs, views, n, k, degree, visible,
                                                                      colors);
  return cudaGetLastError();
}

template <typename T>
cudaError_t sh_to_color_backward_cuda_launch(const T* dirs, const T* coeffs, int64_t views, int64_t n,
                                             int64_t k, int degree, const bool* visible,
                                             const bool* trainable, const T* v_colors, T* v_dirs,
                                             T* v_coeffs, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  sh_backward_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      dirs, coeffs, views, n, k, degree, visible, trainable, v_colors, v_dirs, v_coeffs);
  return cudaGetLastError();
}

cudaError_t sh_to_color_staged_cuda_launch(const float* dirs, const float* c0, int64_t pitch0, int64_t k0,
                                          const float* c1, int64_t pitch1, int64_t k1, int64_t views, int64_t n,
                                          int degree, const bool* visible, float* colors, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  const Rows a{c0, nullptr, pitch0, static_cast<int>(3 * k0)}, b{c1, nullptr, pitch1, static_cast<int>(3 * k1)};
  sh_staged_kernel<<<cuda::ceil_div(n, kStagedThreads), kStagedThreads, staged_bytes(k0 + k1, 1), stream>>>(
      dirs, a, b, views, n, degree, visible, colors);
  return cudaGetLastError();
}

cudaError_t sh_to_color_backward_staged_cuda_launch(const float* dirs, const float* c0, int64_t pitch0, int64_t k0,
                                                   const float* c1, int64_t pitch1, int64_t k1, int64_t views,
                                                   int64_t n, int degree, const bool* visible,
                                                   const bool* trainable, const float* v_colors, float* v_dirs,
                                                   float* v0, float* v1, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  const Rows a{c0, v0, pitch0, static_cast<int>(3 * k0)}, b{c1, v1, pitch1, static_cast<int>(3 * k1)};
  sh_backward_staged_kernel<<<cuda::ceil_div(n, kStagedThreads), kStagedThreads, staged_bytes(k0 + k1, 2),
                              stream>>>(dirs, a, b, views, n, degree, visible, trainable, v_colors, v_dirs);
  return cudaGetLastError();
}

#define TIGER_INSTANTIATE(T)                                                                             \
  template cudaError_t sh_to_color_cuda_launch<T>(const T*, const T*, int64_t, int64_t, int64_t, int,    \
                                                  const bool*, T*, cudaStream_t);                        \
  template cudaError_t sh_to_color_backward_cuda_launch<T>(const T*, const T*, int64_t, int64_t, int64_t, \
                                                           int, const bool*, const bool*, const T*, T*,  \
                                                           T*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger
