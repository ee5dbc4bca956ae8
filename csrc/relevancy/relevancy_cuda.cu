// CUDA kernels of tiger::relevancy on raw pointers (no torch headers: CI compiles this with nvcc alone).
//
// Fast path (rows of D * sizeof(scalar) <= 512 bytes, a multiple of 16, 16-byte aligned):
// a group of G lanes (a power of two <= 32) holds one row, one 16-byte streaming load per lane,
// so a warp reads 512 contiguous bytes per load instruction. Each lane keeps the slice of every
// text vector that matches its 16-byte chunk in registers for the whole kernel, so the hot loop
// touches only the features once: load, convert, |f|^2 and the dot products, group reductions with
// shuffles, then normalise + LERF relevancy and one store per (row, query). At most TMAX text
// vectors (queries + negatives) per pass; more queries run as several passes.
// Generic path (any D): one warp per row, text vectors in shared memory.
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "relevancy/relevancy.h"

namespace tiger {
namespace relevancy {
namespace {

constexpr int kThreads = 256;
constexpr int kTMax = 8;  // most text vectors held in registers per pass (queries + negatives)
constexpr int kRows = 4;  // rows per lane group per iteration (loads issued together)

// 16-byte chunk -> accumulation type. VEC elements per chunk.
template <typename scalar_t>
struct Chunk;
template <>
struct Chunk<__half> {
  static constexpr int VEC = 8;
  __device__ __forceinline__ static void convert(const uint4& v, float* out) {
    const __half2* h = reinterpret_cast<const __half2*>(&v);
#pragma unroll
    for (int i = 0; i < 4; ++i) {
      const float2 f = __half22float2(h[i]);
      out[2 * i] = f.x;
      out[2 * i + 1] = f.y;
    }
  }
  __device__ __forceinline__ static void load(const __half* p, float* out) {
    const uint4 v = __ldcs(reinterpret_cast<const uint4*>(p));
    const __half2* h = reinterpret_cast<const __half2*>(&v);
#pragma unroll
    for (int i = 0; i < 4; ++i) {
      const float2 f = __half22float2(h[i]);
      out[2 * i] = f.x;
      out[2 * i + 1] = f.y;
    }
  }
};
template <>
struct Chunk<float> {
  static constexpr int VEC = 4;
  __device__ __forceinline__ static void convert(const uint4& v, float* out) {
    const float4 f = reinterpret_cast<const float4&>(v);
    out[0] = f.x;
    out[1] = f.y;
    out[2] = f.z;
    out[3] = f.w;
  }
  __device__ __forceinline__ static void load(const float* p, float* out) {
    const float4 v = __ldcs(reinterpret_cast<const float4*>(p));
    out[0] = v.x;
    out[1] = v.y;
    out[2] = v.z;
    out[3] = v.w;
  }
};
template <>
struct Chunk<double> {
  static constexpr int VEC = 2;
  __device__ __forceinline__ static void load(const double* p, double* out) {
    const double2 v = __ldcs(reinterpret_cast<const double2*>(p));
    out[0] = v.x;
    out[1] = v.y;
  }
};

__device__ __forceinline__ float to_acc(__half v) { return __half2float(v); }
__device__ __forceinline__ float to_acc(float v) { return v; }
__device__ __forceinline__ double to_acc(double v) { return v; }
__device__ __forceinline__ float sqrt_t(float v) { return sqrtf(v); }
__device__ __forceinline__ double sqrt_t(double v) { return sqrt(v); }

template <typename acc_t>
__device__ __forceinline__ acc_t group_sum(acc_t v, int group) {
  // Groups are aligned power-of-two lane ranges, so xor partners stay inside the group.
  for (int off = group >> 1; off > 0; off >>= 1) v += __shfl_xor_sync(0xffffffffu, v, off);
  return v;
}

// TMAX (the register capacity for text vectors) is a template parameter so that the common
// small cases (one query, four negatives) do not pay registers, hence occupancy, for eight.
template <typename scalar_t, typename acc_t, int TMAX>
__global__ void __launch_bounds__(kThreads)
    relevancy_vec_kernel(const scalar_t* __restrict__ feat, int64_t n, int d,
                         const acc_t* __restrict__ pos, int qc, const acc_t* __restrict__ neg, int m,
                         int group, acc_t temperature, acc_t eps, acc_t* __restrict__ cos_out,
                         acc_t* __restrict__ rel_out, int64_t ldo) {
  constexpr int VEC = Chunk<scalar_t>::VEC;
  const int chunks = d / VEC;
  const int lane = threadIdx.x & 31;
  const int sub = lane & (group - 1);
  const int gw = lane / group;
  const int groups_per_warp = 32 / group;
  const bool active_chunk = sub < chunks;
  const int nt = qc + m;

  // This lane's slice of every text vector: queries first, then negatives.
  acc_t tx[TMAX][VEC];
#pragma unroll
  for (int t = 0; t < TMAX; ++t) {
    const acc_t* src = t < qc ? pos + int64_t(t) * d : neg + int64_t(t - qc) * d;
#pragma unroll
    for (int e = 0; e < VEC; ++e) tx[t][e] = (t < nt && active_chunk) ? src[sub * VEC + e] : acc_t(0);
  }

  const int64_t warp = (int64_t(blockIdx.x) * blockDim.x + threadIdx.x) >> 5;
  const int64_t n_warps = (int64_t(gridDim.x) * blockDim.x) >> 5;
  const int64_t rows_per_iter = int64_t(groups_per_warp) * kRows;
  for (int64_t base = warp * rows_per_iter; base < n; base += n_warps * rows_per_iter) {
    acc_t x[kRows][VEC];
#pragma unroll
    for (int r = 0; r < kRows; ++r) {
      const int64_t row = base + int64_t(r) * groups_per_warp + gw;
      if (row < n && active_chunk) {
        Chunk<scalar_t>::load(feat + row * d + int64_t(sub) * VEC, x[r]);
      } else {
#pragma unroll
        for (int e = 0; e < VEC; ++e) x[r][e] = acc_t(0);
      }
    }
#pragma unroll
    for (int r = 0; r < kRows; ++r) {
      const int64_t row = base + int64_t(r) * groups_per_warp + gw;
      acc_t n2 = 0;
#pragma unroll
      for (int e = 0; e < VEC; ++e) n2 += x[r][e] * x[r][e];
      n2 = group_sum(n2, group);
      const acc_t inv = acc_t(1) / max(sqrt_t(n2), eps);
      acc_t dots[TMAX];
#pragma unroll
      for (int t = 0; t < TMAX; ++t) {
        acc_t s = 0;
        if (t < nt) {  // nt is uniform across the warp: the shuffles below stay converged
#pragma unroll
          for (int e = 0; e < VEC; ++e) s += x[r][e] * tx[t][e];
          s = group_sum(s, group) * inv;
        }
        dots[t] = s;
      }
      acc_t max_neg = -INFINITY;
#pragma unroll
      for (int t = 0; t < TMAX; ++t)
        if (t >= qc && t < nt) max_neg = max(max_neg, dots[t]);
      if (sub == 0 && row < n) {
#pragma unroll
        for (int t = 0; t < TMAX; ++t) {
          if (t < qc) {
            cos_out[row * ldo + t] = dots[t];
            if (m > 0) rel_out[row * ldo + t] = lerf_relevancy<acc_t>(dots[t], max_neg, temperature);
          }
        }
      }
    }
  }
}


// Row-per-thread path for rows of CH 16-byte chunks (fp16 D=64: CH=8): a block stages a tile
// of kTileRows rows in shared memory with coalesced 16-byte loads (rows padded by one chunk so
// the per-thread reads below are bank-conflict free), then each thread reduces its own row
// against the text vectors (float, shared memory, broadcast reads): no shuffles at all, and
// every output is written once, coalesced across the block.
constexpr int kTileRows = 128;

template <typename scalar_t, int CH>
__global__ void __launch_bounds__(kTileRows)
    relevancy_rowthread_kernel(const scalar_t* __restrict__ feat, int64_t n,
                               const float* __restrict__ pos, int qc, const float* __restrict__ neg,
                               int m, float temperature, float eps, float* __restrict__ cos_out,
                               float* __restrict__ rel_out, int64_t ldo) {
  constexpr int VEC = Chunk<scalar_t>::VEC;
  constexpr int D = CH * VEC;
  __shared__ uint4 tile[kTileRows * (CH + 1)];
  __shared__ __align__(16) float text[kTMax * D];
  const int nt = qc + m;
  for (int i = threadIdx.x; i < nt * D; i += kTileRows) {
    const int t = i / D, k = i - t * D;
    text[i] = t < qc ? pos[int64_t(t) * D + k] : neg[int64_t(t - qc) * D + k];
  }
  const uint4* src = reinterpret_cast<const uint4*>(feat);
  for (int64_t row0 = int64_t(blockIdx.x) * kTileRows; row0 < n; row0 += int64_t(gridDim.x) * kTileRows) {
    const int rows = n - row0 < kTileRows ? int(n - row0) : kTileRows;
    __syncthreads();  // the previous tile is consumed (and, first time, text is written)
#pragma unroll
    for (int k = 0; k < CH; ++k) {
      const int c = threadIdx.x + k * kTileRows;  // chunk index within the tile
      const int r = c / CH, j = c - r * CH;
      if (r < rows) tile[r * (CH + 1) + j] = __ldcs(src + (row0 + r) * CH + j);
    }
    __syncthreads();
    if (threadIdx.x >= rows) continue;
    float n2 = 0.f, dots[kTMax];
#pragma unroll
    for (int t = 0; t < kTMax; ++t) dots[t] = 0.f;
#pragma unroll
    for (int j = 0; j < CH; ++j) {
      const uint4 v = tile[threadIdx.x * (CH + 1) + j];
      float x[VEC];
      Chunk<scalar_t>::convert(v, x);
#pragma unroll
      for (int e = 0; e < VEC; ++e) n2 += x[e] * x[e];
#pragma unroll
      for (int t = 0; t < kTMax; ++t) {
        if (t < nt) {
          const float4* tv = reinterpret_cast<const float4*>(text + t * D + j * VEC);
#pragma unroll
          for (int e4 = 0; e4 < VEC / 4; ++e4) {
            const float4 w = tv[e4];
            dots[t] += x[4 * e4] * w.x + x[4 * e4 + 1] * w.y + x[4 * e4 + 2] * w.z + x[4 * e4 + 3] * w.w;
          }
        }
      }
    }
    const float inv = 1.f / fmaxf(sqrtf(n2), eps);
    float max_neg = -INFINITY;
#pragma unroll
    for (int t = 0; t < kTMax; ++t)
      if (t >= qc && t < nt) max_neg = fmaxf(max_neg, dots[t] * inv);
    const int64_t row = row0 + threadIdx.x;
#pragma unroll
    for (int t = 0; t < kTMax; ++t) {
      if (t < qc) {
        const float c = dots[t] * inv;
        __stcs(cos_out + row * ldo + t, c);
        if (m > 0) __stcs(rel_out + row * ldo + t, lerf_relevancy<float>(c, max_neg, temperature));
      }
    }
  }
}

// Any D: one warp per row; the nt text vectors live in shared memory.
template <typename scalar_t, typename acc_t>
__global__ void __launch_bounds__(kThreads)
    relevancy_generic_kernel(const scalar_t* __restrict__ feat, int64_t n, int d,
                             const acc_t* __restrict__ pos, int qc, const acc_t* __restrict__ neg,
                             int m, acc_t temperature, acc_t eps, acc_t* __restrict__ cos_out,
                             acc_t* __restrict__ rel_out, int64_t ldo) {
  extern __shared__ __align__(16) unsigned char smem_raw[];
  acc_t* tv = reinterpret_cast<acc_t*>(smem_raw);
  const int nt = qc + m;
  for (int i = threadIdx.x; i < nt * d; i += blockDim.x) {
    const int t = i / d, k = i - t * d;
    tv[i] = t < qc ? pos[int64_t(t) * d + k] : neg[int64_t(t - qc) * d + k];
  }
  __syncthreads();
  const int lane = threadIdx.x & 31;
  const int64_t warp = (int64_t(blockIdx.x) * blockDim.x + threadIdx.x) >> 5;
  const int64_t n_warps = (int64_t(gridDim.x) * blockDim.x) >> 5;
  for (int64_t row = warp; row < n; row += n_warps) {
    const scalar_t* f = feat + row * d;
    acc_t n2 = 0;
    for (int k = lane; k < d; k += 32) {
      const acc_t v = to_acc(f[k]);
      n2 += v * v;
    }
    n2 = group_sum(n2, 32);
    const acc_t inv = acc_t(1) / max(sqrt_t(n2), eps);
    acc_t max_neg = -INFINITY;
    for (int j = 0; j < m; ++j) {
      acc_t s = 0;
      for (int k = lane; k < d; k += 32) s += to_acc(f[k]) * tv[(qc + j) * d + k];
      max_neg = max(max_neg, group_sum(s, 32) * inv);
    }
    for (int t = 0; t < qc; ++t) {
      acc_t s = 0;
      for (int k = lane; k < d; k += 32) s += to_acc(f[k]) * tv[t * d + k];
      const acc_t c = group_sum(s, 32) * inv;
      if (lane == 0) {
        cos_out[row * ldo + t] = c;
        if (m > 0) rel_out[row * ldo + t] = lerf_relevancy<acc_t>(c, max_neg, temperature);
      }
    }
  }
}

template <typename K>
int grid_for(K kernel, int64_t warps_needed, size_t smem) {
  int dev = 0, sms = 1, per_sm = 1;
  cudaGetDevice(&dev);
  cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
  cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, kernel, kThreads, smem);
  const int64_t blocks_needed = (warps_needed + (kThreads / 32) - 1) / (kThreads / 32);
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(blocks_needed, int64_t(sms) * std::max(per_sm, 1))));
}

template <typename scalar_t, typename acc_t>
int launch(const scalar_t* feat, int64_t n, int d, const acc_t* texts, int q, int m, double temperature,
           double eps, acc_t* cos_out, acc_t* rel_out, size_t max_smem, cudaStream_t stream) {
  if (n == 0 || q == 0) return 0;
  constexpr int VEC = Chunk<scalar_t>::VEC;
  const acc_t* neg = texts + int64_t(q) * d;
  const int row_bytes = d * int(sizeof(scalar_t));
  const bool vec_ok = row_bytes % 16 == 0 && row_bytes <= 512 &&
                      reinterpret_cast<uintptr_t>(feat) % 16 == 0 && m < kTMax;
  if constexpr (!std::is_same<scalar_t, double>::value) {
    const int ch = row_bytes / 16;
    if (vec_ok && (ch == 8 || ch == 16)) {
      const int q_per_pass = kTMax - m;
      for (int q0 = 0; q0 < q; q0 += q_per_pass) {
        const int qc = std::min(q_per_pass, q - q0);
        auto kernel = ch == 8 ? relevancy_rowthread_kernel<scalar_t, 8>
                              : relevancy_rowthread_kernel<scalar_t, 16>;
        int dev = 0, sms = 1, per_sm = 1;
        cudaGetDevice(&dev);
        cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
        cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, kernel, kTileRows, 0);
        const int64_t tiles = (n + kTileRows - 1) / kTileRows;
        const int grid = int(std::max<int64_t>(1, std::min<int64_t>(tiles, int64_t(sms) * std::max(per_sm, 1))));
        kernel<<<grid, kTileRows, 0, stream>>>(feat, n, texts + int64_t(q0) * d, qc, neg, m,
                                               float(temperature), float(eps), cos_out + q0,
                                               m > 0 ? rel_out + q0 : nullptr, q);
      }
      return static_cast<int>(cudaGetLastError());
    }
  }
  if (vec_ok) {
    int group = 1;
    while (group < d / VEC) group <<= 1;
    const int64_t rows_per_warp = int64_t(32 / group) * kRows;
    const int64_t warps_needed = (n + rows_per_warp - 1) / rows_per_warp;
    const int q_per_pass = kTMax - m;
    for (int q0 = 0; q0 < q; q0 += q_per_pass) {
      const int qc = std::min(q_per_pass, q - q0);
      auto kernel = qc + m <= 2   ? relevancy_vec_kernel<scalar_t, acc_t, 2>
                    : qc + m <= 5 ? relevancy_vec_kernel<scalar_t, acc_t, 5>
                                  : relevancy_vec_kernel<scalar_t, acc_t, kTMax>;
      const int grid = grid_for(kernel, warps_needed, 0);
      kernel<<<grid, kThreads, 0, stream>>>(feat, n, d, texts + int64_t(q0) * d, qc, neg, m, group,
                                            acc_t(temperature), acc_t(eps), cos_out + q0,
                                            m > 0 ? rel_out + q0 : nullptr, q);
    }
  } else {
    // Shared memory holds the negatives and as many queries as fit.
    const size_t row_sz = size_t(d) * sizeof(acc_t);
    if (size_t(m + 1) * row_sz > max_smem) return -1;  // caller reports: too large for shared memory
    const int q_per_pass = static_cast<int>(std::min<size_t>(q, max_smem / row_sz - m));
    for (int q0 = 0; q0 < q; q0 += q_per_pass) {
      const int qc = std::min(q_per_pass, q - q0);
      const size_t smem = size_t(qc + m) * row_sz;
      if (smem > 48 * 1024)
        cudaFuncSetAttribute(relevancy_generic_kernel<scalar_t, acc_t>,
                             cudaFuncAttributeMaxDynamicSharedMemorySize, int(smem));
      const int grid = grid_for(relevancy_generic_kernel<scalar_t, acc_t>, n, smem);
      relevancy_generic_kernel<scalar_t, acc_t><<<grid, kThreads, smem, stream>>>(
          feat, n, d, texts + int64_t(q0) * d, qc, neg, m, acc_t(temperature), acc_t(eps),
          cos_out + q0, m > 0 ? rel_out + q0 : nullptr, q);
    }
  }
  return static_cast<int>(cudaGetLastError());
}

}  // namespace

// Return codes: 0 ok, -1 the text vectors do not fit in shared memory, else the cudaError_t of the launch.
int relevancy_cuda_f16(const void* feat, int64_t n, int d, const float* texts, int q, int m,
                       double temperature, double eps, float* cos_out, float* rel_out,
                       size_t max_smem, cudaStream_t stream) {
  return launch<__half, float>(static_cast<const __half*>(feat), n, d, texts, q, m, temperature, eps,
                               cos_out, rel_out, max_smem, stream);
}
int relevancy_cuda_f32(const float* feat, int64_t n, int d, const float* texts, int q, int m,
                       double temperature, double eps, float* cos_out, float* rel_out,
                       size_t max_smem, cudaStream_t stream) {
  return launch<float, float>(feat, n, d, texts, q, m, temperature, eps, cos_out, rel_out, max_smem,
                              stream);
}
int relevancy_cuda_f64(const double* feat, int64_t n, int d, const double* texts, int q, int m,
                       double temperature, double eps, double* cos_out, double* rel_out,
                       size_t max_smem, cudaStream_t stream) {
  return launch<double, double>(feat, n, d, texts, q, m, temperature, eps, cos_out, rel_out, max_smem,
                                stream);
}

}  // namespace relevancy
}  // namespace tiger
