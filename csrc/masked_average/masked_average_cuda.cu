// CUDA kernels of tiger::masked_average (raw pointers, no torch headers).
#include <cuda_runtime.h>

#include "masked_average/masked_average.h"

namespace tiger {
namespace masked_average {
namespace {

constexpr int kChannels = 32;   // threads along channels (one warp: coalesced rows)
constexpr int kRows = 8;        // warps per block, each on its own pixel run
constexpr int kPixPerThread = 64;

// Pixels come in raster order, so a mask's pixels form long runs: each thread accumulates a run
// in a register and issues one atomicAdd per run instead of one per pixel.
template <typename scalar_t>
__global__ void segment_sum_kernel(const scalar_t* __restrict__ values, const int64_t* __restrict__ ids,
                                   int64_t P, int64_t C, scalar_t* __restrict__ sums,
                                   unsigned long long* __restrict__ counts) {
  const int64_t c = static_cast<int64_t>(blockIdx.y) * kChannels + threadIdx.x;
  const int64_t p0 = (static_cast<int64_t>(blockIdx.x) * kRows + threadIdx.y) * kPixPerThread;
  if (p0 >= P) return;
  const int64_t p1 = min(P, p0 + kPixPerThread);
  const bool do_count = counts != nullptr && blockIdx.y == 0 && threadIdx.x == 0;
  int64_t cur = -1;
  scalar_t acc = 0;
  unsigned long long n = 0;
  for (int64_t p = p0; p < p1; ++p) {
    const int64_t m = ids[p];
    if (m != cur) {
      if (cur >= 0) {
        if (c < C) atomicAdd(sums + cur * C + c, acc);
        if (do_count) atomicAdd(counts + cur, n);
      }
      cur = m;
      acc = 0;
      n = 0;
    }
    if (m >= 0) {
      if (c < C) acc += values[p * C + c];
      ++n;
    }
  }
  if (cur >= 0) {
    if (c < C) atomicAdd(sums + cur * C + c, acc);
    if (do_count) atomicAdd(counts + cur, n);
  }
}

template <typename scalar_t>
__global__ void scatter_mean_kernel(const scalar_t* __restrict__ sums, const scalar_t* __restrict__ extra,
                                    const int64_t* __restrict__ counts, const int64_t* __restrict__ ids,
                                    const scalar_t* __restrict__ fallback, int64_t P, int64_t C,
                                    scalar_t* __restrict__ out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= P * C) return;
  const int64_t p = i / C, c = i - p * C;
  const int64_t m = ids[p];
  if (m < 0) {
    out[i] = fallback[i];
    return;
  }
  const int64_t n = counts[m];
  scalar_t s = sums[m * C + c];
  if (extra != nullptr) s += extra[m * C + c];
  out[i] = n > 0 ? s / static_cast<scalar_t>(n) : scalar_t(0);
}

template <typename scalar_t>
__global__ void divide_kernel(const scalar_t* __restrict__ sums, const int64_t* __restrict__ counts,
                              int64_t M, int64_t C, scalar_t* __restrict__ means) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= M * C) return;
  const int64_t n = counts[i / C];
  means[i] = n > 0 ? sums[i] / static_cast<scalar_t>(n) : scalar_t(0);
}

inline unsigned blocks_for(int64_t n, int threads) {
  return static_cast<unsigned>((n + threads - 1) / threads);
}

}  // namespace

template <typename scalar_t>
void launch_segment_sum(const scalar_t* values, const int64_t* ids, int64_t P, int64_t C, int64_t M,
                        scalar_t* sums, int64_t* counts, void* stream) {
  (void)M;
  if (P == 0) return;
  const int64_t per_block = static_cast<int64_t>(kRows) * kPixPerThread;
  dim3 grid(static_cast<unsigned>((P + per_block - 1) / per_block),
            static_cast<unsigned>(C > 0 ? (C + kChannels - 1) / kChannels : 1));
  dim3 block(kChannels, kRows);
  static_assert(sizeof(unsigned long long) == sizeof(int64_t), "counts are 64-bit");
  segment_sum_kernel<scalar_t><<<grid, block, 0, static_cast<cudaStream_t>(stream)>>>(
      values, ids, P, C, sums, reinterpret_cast<unsigned long long*>(counts));
}

template <typename scalar_t>
void launch_scatter_mean(const scalar_t* sums, const scalar_t* extra, const int64_t* counts,
                         const int64_t* ids, const scalar_t* fallback, int64_t P, int64_t C,
                         scalar_t* out, void* stream) {
  if (P * C == 0) return;
  scatter_mean_kernel<scalar_t><<<blocks_for(P * C, 256), 256, 0, static_cast<cudaStream_t>(stream)>>>(
      sums, extra, counts, ids, fallback, P, C, out);
}

template <typename scalar_t>
void launch_divide(const scalar_t* sums, const int64_t* counts, int64_t M, int64_t C, scalar_t* means,
                   void* stream) {
  if (M * C == 0) return;
  divide_kernel<scalar_t><<<blocks_for(M * C, 256), 256, 0, static_cast<cudaStream_t>(stream)>>>(
      sums, counts, M, C, means);
}

#define TIGER_INSTANTIATE(T)                                                                        \
  template void launch_segment_sum<T>(const T*, const int64_t*, int64_t, int64_t, int64_t, T*,     \
                                      int64_t*, void*);                                            \
  template void launch_scatter_mean<T>(const T*, const T*, const int64_t*, const int64_t*, const T*, \
                                       int64_t, int64_t, T*, void*);                               \
  template void launch_divide<T>(const T*, const int64_t*, int64_t, int64_t, T*, void*);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace masked_average
}  // namespace tiger
