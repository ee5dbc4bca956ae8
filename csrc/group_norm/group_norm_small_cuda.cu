// tiger::group_norm's forward for small channels-last maps in one launch, and its input gradient
// for the VAE encoders' mid-sized maps in one launch (small_backward_kernel).
//
// The general forward (group_norm_cuda.cu) runs three kernels: per-chunk moments, their combine
// per (n, g), the apply. On the diffusion UNets' smallest maps each of those launches is
// latency-bound and walks long column passes with few blocks (8x1280x4², 8 blocks): 22-28 us per
// norm for 0.3-8 MB. Here one block owns one (sample n, channel block) — cb = lcm(V, D) channels,
// i.e. whole groups in whole 16-byte vectors — and holds its elements in registers: every thread
// keeps up to E vectors of one fixed column (so its lanes' channels, groups and affine constants
// are fixed), the groups' sums go warp -> block in a fixed order (deterministic), first of the
// values (a first mean), then of the deviations from it and their squares (the exact mean and the
// variance: large-mean inputs keep their variance), then each thread writes its elements
// normalised. One read and one write of the map, one launch, no partial buffers.
//
// Clusters of K blocks per (n, channel block), sharing their sums through distributed shared
// memory, were measured and dropped: on the H100 clusters of 4-8 made the 32²-128² maps slower
// than the general forward (8x320x32² 17.5 -> 26.6 us, 4x256x128² 56.4 -> 97.7), while single
// blocks made the small ones 1.5-3.4x faster (8x1280x8² 26.6 -> 8.0 us, 12x1280x16² 28.1 -> 19.4;
// benchmarks/gpu/results/group_norm_small_maps_ab_h100.txt; the cluster version is in git
// history). Maps whose (n, channel block) does not fit one block's registers take the general
// forward.
#include <cuda_runtime.h>

#include <numeric>

#include "common/cuda_helpers.cuh"
#include "group_norm/group_norm.h"
#include "group_norm/group_norm_device.cuh"

namespace tiger {
namespace group_norm {
namespace {

using tiger::cuda::load_as;
using tiger::cuda::store_as;
using tiger::cuda::Vec;

constexpr int kBlockThreads = 256;  // the most threads a block has
// 16-byte vectors a thread holds: 8 of 2-byte types (32 registers; 12 spilled at two blocks per
// SM), 12 of float32.
template <typename T>
constexpr int kMaxVectors = sizeof(T) == 2 ? 8 : 12;
constexpr int kMaxWarps = kBlockThreads / 32;
// The one-launch input gradient's blocks: one per SM (a block per (sample, channel block), about
// one wave), so twice the forward's threads to keep twice the loads in flight.
constexpr int kBackwardThreads = 512;

struct SmallGeom {
  int64_t C, HW, G, cb;  // channels, pixels, groups, channels per block (whole groups and vectors)
  int cbv, threads, E;  // vectors per pixel row of a block, threads of a block that hold pixels
                        // (a multiple of cbv), vectors per thread
};

// Block-wide sums of s[0..GB) in a fixed order (warps, then warp 0..n); every thread gets the totals.
template <int GB>
__device__ __forceinline__ void block_sums(float (&s)[GB], float (*s_warp)[GB], float* s_total) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = (blockDim.x + 31) >> 5;
#pragma unroll
  for (int g = 0; g < GB; ++g) {
#pragma unroll
    for (int o = 16; o >= 1; o >>= 1) s[g] += __shfl_xor_sync(0xffffffffu, s[g], o);
  }
  if (lane == 0) {
#pragma unroll
    for (int g = 0; g < GB; ++g) s_warp[warp][g] = s[g];
  }
  __syncthreads();
  if (threadIdx.x < GB) {
    float t = 0.f;
    for (int w = 0; w < warps; ++w) t += s_warp[w][threadIdx.x];
    s_total[threadIdx.x] = t;
  }
  __syncthreads();
#pragma unroll
  for (int g = 0; g < GB; ++g) s[g] = s_total[g];
}

// Sums over the lanes of each lane's group: out[g] = Σ_{l: group(l) = g} acc[l].
template <int V, int GB>
__device__ __forceinline__ void lanes_to_groups(const float (&acc)[V], uint32_t groups, float (&out)[GB]) {
#pragma unroll
  for (int g = 0; g < GB; ++g) {
    out[g] = 0.f;
#pragma unroll
    for (int l = 0; l < V; ++l) out[g] += ((groups >> (4 * l)) & 15u) == uint32_t(g) ? acc[l] : 0.f;
  }
}

// Two per-lane sums to per-group sums: out[0..GB) from first, out[GB..2GB) from second.
template <int V, int GB>
__device__ __forceinline__ void pair_to_groups(const float (&first)[V], const float (&second)[V], uint32_t groups,
                                               float (&out)[2 * GB]) {
  float p1[GB], p2[GB];
  lanes_to_groups<V, GB>(first, groups, p1);
  lanes_to_groups<V, GB>(second, groups, p2);
#pragma unroll
  for (int g = 0; g < GB; ++g) {
    out[g] = p1[g];
    out[GB + g] = p2[g];
  }
}

// The value of lane l's group in per-group values.
template <int GB>
__device__ __forceinline__ float group_value(const float (&vals)[GB], uint32_t groups, int l) {
  float r = 0.f;
#pragma unroll
  for (int g = 0; g < GB; ++g) r = ((groups >> (4 * l)) & 15u) == uint32_t(g) ? vals[g] : r;
  return r;
}

template <typename T, int V, bool SILU, int GB>
__global__ void __launch_bounds__(kBlockThreads, 2)
    small_forward_kernel(const T* __restrict__ x, Params p, SmallGeom s, float eps, float* __restrict__ mean_out,
                         float* __restrict__ rstd_out, T* __restrict__ y) {
  __shared__ float s_warp[kMaxWarps][2 * GB];
  __shared__ float s_total[2 * GB];
  const int64_t item = blockIdx.x, blocks_per_n = s.C / s.cb;
  const int64_t n = item / blocks_per_n, c0 = item % blocks_per_n * s.cb;
  const int64_t D = s.C / s.G, g0 = c0 / D;
  const int i = static_cast<int>(threadIdx.x);
  const int cv = i % s.cbv;  // the thread's column: its lanes' channels and groups are fixed
  // threads past s.threads (blockDim is a whole number of warps, for the shuffles) hold no pixel
  const int64_t pix0 = i < s.threads ? i / s.cbv : s.HW;
  const int64_t pix_step = s.threads / s.cbv;
  const int64_t base = n * s.HW * s.C + c0 + cv * V;
  const float inv_m = 1.f / static_cast<float>(D * s.HW);

  uint32_t groups = 0;  // 4 bits a lane: its group relative to g0 (< 8)
  float ib[V];
#pragma unroll
  for (int l = 0; l < V; ++l) {
    groups |= static_cast<uint32_t>((cv * V + l) / D) << (4 * l);
    ib[l] = input_bias_at(p.input_bias, p.input_bias_stride, n, c0 + cv * V + l);
  }
  Vec<T, V> v[kMaxVectors<T>];
  float acc[V], acc2[V];
#pragma unroll
  for (int l = 0; l < V; ++l) acc[l] = 0.f;
#pragma unroll
  for (int k = 0; k < kMaxVectors<T>; ++k) {
    const int64_t pix = pix0 + k * pix_step;
    if (k < s.E && pix < s.HW) {
      v[k] = *reinterpret_cast<const Vec<T, V>*>(x + base + pix * s.C);
#pragma unroll
      for (int l = 0; l < V; ++l) acc[l] += load_as<float>(v[k].v[l]) + ib[l];
    }
  }
  // pass 1: a first mean, the shift of pass 2 (large-mean inputs keep their variance there)
  float sums[2 * GB];
  {
    float part[GB];
    lanes_to_groups<V, GB>(acc, groups, part);
#pragma unroll
    for (int g = 0; g < GB; ++g) sums[g] = part[g];
  }
  block_sums<GB>(reinterpret_cast<float(&)[GB]>(sums), reinterpret_cast<float(*)[GB]>(s_warp), s_total);
  float shift[GB];
#pragma unroll
  for (int g = 0; g < GB; ++g) shift[g] = sums[g] * inv_m;
  // pass 2: Σ d and Σ d² about the shift: the exact mean and the variance
#pragma unroll
  for (int l = 0; l < V; ++l) acc[l] = acc2[l] = 0.f;
#pragma unroll
  for (int k = 0; k < kMaxVectors<T>; ++k) {
    const int64_t pix = pix0 + k * pix_step;
    if (k < s.E && pix < s.HW) {
#pragma unroll
      for (int l = 0; l < V; ++l) {
        const float d = load_as<float>(v[k].v[l]) + ib[l] - group_value<GB>(shift, groups, l);
        acc[l] += d;
        acc2[l] += d * d;
      }
    }
  }
  pair_to_groups<V, GB>(acc, acc2, groups, sums);
  __syncthreads();  // every thread has read s_total: it is reused
  block_sums<2 * GB>(sums, s_warp, s_total);
  float mean[GB], rstd[GB];
#pragma unroll
  for (int g = 0; g < GB; ++g) {
    const float dm = sums[g] * inv_m;
    mean[g] = shift[g] + dm;
    rstd[g] = rsqrtf(fmaxf(sums[GB + g] * inv_m - dm * dm, 0.f) + eps);
  }
  if (i == 0) {
    for (int g = 0; g < static_cast<int>(s.cb / D); ++g) {
#pragma unroll
      for (int h = 0; h < GB; ++h)
        if (h == g) {
          mean_out[n * s.G + g0 + g] = mean[h];
          rstd_out[n * s.G + g0 + g] = rstd[h];
        }
    }
  }
  float m[V], a[V], b[V];
#pragma unroll
  for (int l = 0; l < V; ++l) {
    const int64_t c = c0 + cv * V + l;
    const float w = param_at<T>(p, p.weight, c, 1.f);
    b[l] = param_at<T>(p, p.bias, c, 0.f);
    m[l] = group_value<GB>(mean, groups, l) - ib[l];  // x − (mean − ib), as the general apply
    a[l] = group_value<GB>(rstd, groups, l) * w;
  }
#pragma unroll
  for (int k = 0; k < kMaxVectors<T>; ++k) {
    const int64_t pix = pix0 + k * pix_step;
    if (k < s.E && pix < s.HW) {
      Vec<T, V> out;
#pragma unroll
      for (int l = 0; l < V; ++l) {
        float z = (load_as<float>(v[k].v[l]) - m[l]) * a[l] + b[l];
        if (SILU) z *= sigmoid(z);
        out.v[l] = store_as<T>(z);
      }
      *reinterpret_cast<Vec<T, V>*>(y + base + pix * s.C) = out;
    }
  }
}

// ---- the input gradient in one launch (no parameter gradients) ---------------------------
// One block per (sample n, channel block) as the forward, walking its slice twice instead of
// holding it: pass 1 sums w·dz and w·dz·(x − m) per lane over the block's pixels (x and dy read
// from DRAM), the block combines them into c1, c2 of its groups (fixed order), pass 2 reads x and
// dy again (from L2: plan_small_backward admits maps whose x and dy fit it) and writes
// dx = a·dz − rstd·c1 − (x − m)·rstd²·c2 (+ residual), the three-kernel backward's formula
// (group_norm_cuda.cu, FoldedConsts) with m = mean − ib, a = rstd·w. The three-kernel backward
// gives these maps (the VAE encoders' 32²-128² norms) two walks of ~30 us each plus a combine,
// latency-bound at 31-53 % of DRAM bandwidth (group_norm_vae_ncu_h100.txt). H100, bf16, SiLU
// (group_norm_one_launch_input_grad_h100.txt): 4x512x32² 21.7 -> 10.0 us, 4x512x64² 60.9 -> 38.2
// (67.2 -> 47.3 with a residual); 256-thread blocks took 50.4 at 64², and admitting 4x256x128²
// (x and dy 64 MiB, pass 2 partly from DRAM) made it slower than the walk (89.9 -> 100.1 us).
template <typename T, int V, bool SILU, bool RES, int GB>
__global__ void __launch_bounds__(kBackwardThreads, 1)
    small_backward_kernel(const T* __restrict__ dy, const T* __restrict__ x, Params p, SmallGeom s,
                          const float* __restrict__ mean_g, const float* __restrict__ rstd_g,
                          const T* __restrict__ residual, T* __restrict__ dx) {
  __shared__ float s_warp[kBackwardThreads / 32][2 * GB];
  __shared__ float s_total[2 * GB];
  const int64_t item = blockIdx.x, blocks_per_n = s.C / s.cb;
  const int64_t n = item / blocks_per_n, c0 = item % blocks_per_n * s.cb;
  const int64_t D = s.C / s.G, g0 = c0 / D;
  const int i = static_cast<int>(threadIdx.x);
  const int cv = i % s.cbv;
  const int64_t pix0 = i < s.threads ? i / s.cbv : s.HW;  // threads past s.threads hold no pixel
  const int64_t pix_step = s.threads / s.cbv;
  const int64_t base = n * s.HW * s.C + c0 + cv * V;
  const float inv_m = 1.f / static_cast<float>(D * s.HW);

  uint32_t groups = 0;
  float m[V], a[V], b[V], w[V], r[V];
#pragma unroll
  for (int l = 0; l < V; ++l) {
    const int gl = (cv * V + l) / static_cast<int>(D);
    groups |= static_cast<uint32_t>(gl) << (4 * l);
    const int64_t c = c0 + cv * V + l, ng = n * s.G + g0 + gl;
    const float ib = input_bias_at(p.input_bias, p.input_bias_stride, n, c);
    w[l] = param_at<T>(p, p.weight, c, 1.f);
    b[l] = param_at<T>(p, p.bias, c, 0.f);
    r[l] = rstd_g[ng];
    m[l] = mean_g[ng] - ib;
    a[l] = r[l] * w[l];
  }
  // pass 1: Σ dz and Σ dz·(x − m) per lane
  float sa[V], sb[V];
#pragma unroll
  for (int l = 0; l < V; ++l) sa[l] = sb[l] = 0.f;
#pragma unroll 4
  for (int64_t pix = pix0; pix < s.HW; pix += pix_step) {
    const Vec<T, V> xv = *reinterpret_cast<const Vec<T, V>*>(x + base + pix * s.C);
    const Vec<T, V> gv = *reinterpret_cast<const Vec<T, V>*>(dy + base + pix * s.C);
#pragma unroll
    for (int l = 0; l < V; ++l) {
      const float d = load_as<float>(xv.v[l]) - m[l];
      const float dz = dz_of<SILU>(d, load_as<float>(gv.v[l]), a[l], b[l]);
      sa[l] += dz;
      sb[l] += dz * d;
    }
  }
  // c1 = Σ w·dz / M, c2 = Σ w·dz·x̂ / M per group (x̂ = (x − m)·rstd)
  float sums[2 * GB];
  {
    float wa[V], wb[V];
#pragma unroll
    for (int l = 0; l < V; ++l) {
      wa[l] = w[l] * sa[l];
      wb[l] = w[l] * r[l] * sb[l];
    }
    pair_to_groups<V, GB>(wa, wb, groups, sums);
  }
  block_sums<2 * GB>(sums, s_warp, s_total);
  float k1[V], k2[V];
  {
    float c1[GB], c2[GB];
#pragma unroll
    for (int g = 0; g < GB; ++g) {
      c1[g] = sums[g] * inv_m;
      c2[g] = sums[GB + g] * inv_m;
    }
#pragma unroll
    for (int l = 0; l < V; ++l) {
      k1[l] = r[l] * group_value<GB>(c1, groups, l);
      k2[l] = r[l] * r[l] * group_value<GB>(c2, groups, l);
    }
  }
  // pass 2: dx
#pragma unroll 4
  for (int64_t pix = pix0; pix < s.HW; pix += pix_step) {
    const int64_t off = base + pix * s.C;
    const Vec<T, V> xv = *reinterpret_cast<const Vec<T, V>*>(x + off);
    const Vec<T, V> gv = *reinterpret_cast<const Vec<T, V>*>(dy + off);
    Vec<T, V> rv;
    if constexpr (RES) rv = *reinterpret_cast<const Vec<T, V>*>(residual + off);
    Vec<T, V> out;
#pragma unroll
    for (int l = 0; l < V; ++l) {
      const float d = load_as<float>(xv.v[l]) - m[l];
      const float dz = dz_of<SILU>(d, load_as<float>(gv.v[l]), a[l], b[l]);
      float g = a[l] * dz - k1[l] - d * k2[l];
      if constexpr (RES) g += load_as<float>(rv.v[l]);
      out.v[l] = store_as<T>(g);
    }
    *reinterpret_cast<Vec<T, V>*>(dx + off) = out;
  }
}

// The geometry for this map, or false when the one-launch forward does not apply (not
// channels-last, scalar path, pre-Hopper device (only measured on the H100), more than 4 groups
// or 8 vectors per block row, or too many pixels for one block's registers).
bool plan_small(const Dims& d, int V, int max_vectors, SmallGeom& s, int block_threads = kBlockThreads) {
  if (!d.nhwc || V == 1 || d.G <= 0 || d.C % d.G != 0 || d.HW <= 0) return false;
  int dev = 0, major = 0;
  if (cudaGetDevice(&dev) != cudaSuccess ||
      cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, dev) != cudaSuccess || major < 9)
    return false;
  const int64_t D = d.C / d.G, cb = std::lcm<int64_t>(V, D);
  // at most 4 groups and 8 vectors a block row: what was measured (the up blocks' 1920- and
  // 2560-channel maps, 10-15 vectors a row, were not and take the general forward)
  if (d.C % cb != 0 || cb / D > 4 || cb / V > kBlockThreads / 32) return false;
  s.C = d.C;
  s.HW = d.HW;
  s.G = d.G;
  s.cb = cb;
  s.cbv = static_cast<int>(cb / V);
  s.threads = block_threads / s.cbv * s.cbv;
  const int64_t per_pass = s.threads / s.cbv;  // pixels a block covers per vector a thread holds
  const int64_t E = (d.HW + per_pass - 1) / per_pass;
  if (E > max_vectors) return false;
  s.E = static_cast<int>(E);
  return true;
}

template <typename T, int V, bool SILU, int GB>
void launch_small(const T* x, Params p, const SmallGeom& s, int64_t N, float eps, float* mean, float* rstd, T* y,
                  cudaStream_t st) {
  const unsigned blocks = static_cast<unsigned>(N * (s.C / s.cb));
  const unsigned threads = static_cast<unsigned>((s.threads + 31) / 32 * 32);  // whole warps (full-mask shuffles)
  small_forward_kernel<T, V, SILU, GB><<<blocks, threads, 0, st>>>(x, p, s, eps, mean, rstd, y);
}

template <typename T, int V, bool SILU>
void launch_small_groups(const T* x, Params p, const SmallGeom& s, int64_t N, float eps, float* mean, float* rstd,
                         T* y, cudaStream_t st) {
  switch (s.cb / (s.C / s.G)) {
    case 1: return launch_small<T, V, SILU, 1>(x, p, s, N, eps, mean, rstd, y, st);
    case 2: return launch_small<T, V, SILU, 2>(x, p, s, N, eps, mean, rstd, y, st);
    default: return launch_small<T, V, SILU, 4>(x, p, s, N, eps, mean, rstd, y, st);  // 3 or 4 (plan_small)
  }
}

// The one-launch input gradient applies where the forward's block geometry does (without its
// register limit on the pixels: the backward walks them) and the map is large enough to give most
// SMs a block, yet small enough that pass 2 finds x and dy in L2.
constexpr int64_t kSmallBackwardMaxBytes = int64_t(36) << 20;  // x + dy; the H100's L2 is 50 MB

bool plan_small_backward(const Dims& d, int V, int64_t elem_bytes, SmallGeom& s) {
  if (!plan_small(d, V, 1 << 30, s, kBackwardThreads)) return false;
  int dev = 0, sms = 0;
  if (cudaGetDevice(&dev) != cudaSuccess ||
      cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev) != cudaSuccess)
    return false;
  const int64_t blocks = d.N * (d.C / s.cb);
  return 4 * blocks >= 3 * int64_t(sms) && 2 * d.N * d.C * d.HW * elem_bytes <= kSmallBackwardMaxBytes;
}

template <typename T, int V, bool SILU, bool RES>
void launch_small_backward(const T* dy, const T* x, Params p, const SmallGeom& s, int64_t N, const float* mean,
                           const float* rstd, const T* residual, T* dx, cudaStream_t st) {
  const unsigned blocks = static_cast<unsigned>(N * (s.C / s.cb));
  const unsigned threads = static_cast<unsigned>((s.threads + 31) / 32 * 32);
  switch (s.cb / (s.C / s.G)) {
    case 1:
      return small_backward_kernel<T, V, SILU, RES, 1><<<blocks, threads, 0, st>>>(dy, x, p, s, mean, rstd, residual,
                                                                                   dx);
    case 2:
      return small_backward_kernel<T, V, SILU, RES, 2><<<blocks, threads, 0, st>>>(dy, x, p, s, mean, rstd, residual,
                                                                                   dx);
    default:
      return small_backward_kernel<T, V, SILU, RES, 4><<<blocks, threads, 0, st>>>(dy, x, p, s, mean, rstd, residual,
                                                                                   dx);
  }
}

}  // namespace

template <typename T>
bool launch_forward_small(const T* x, Params p, const Dims& d, float eps, bool silu, float* mean, float* rstd, T* y,
                          int vector_width, void* stream) {
  constexpr int V = 16 / sizeof(T);
  SmallGeom s;
  if (vector_width != V || !plan_small(d, V, kMaxVectors<T>, s)) return false;
  const auto st = static_cast<cudaStream_t>(stream);
  if (silu)
    launch_small_groups<T, V, true>(x, p, s, d.N, eps, mean, rstd, y, st);
  else
    launch_small_groups<T, V, false>(x, p, s, d.N, eps, mean, rstd, y, st);
  return true;
}

template bool launch_forward_small<float>(const float*, Params, const Dims&, float, bool, float*, float*, float*, int,
                                          void*);
template bool launch_forward_small<__half>(const __half*, Params, const Dims&, float, bool, float*, float*, __half*,
                                           int, void*);
template bool launch_forward_small<__nv_bfloat16>(const __nv_bfloat16*, Params, const Dims&, float, bool, float*,
                                                  float*, __nv_bfloat16*, int, void*);

template <typename T>
bool launch_backward_small(const T* dy, const T* x, Params p, const Dims& d, const float* mean, const float* rstd,
                           bool silu, const T* residual, T* dx, int vector_width, void* stream) {
  constexpr int V = 16 / sizeof(T);
  SmallGeom s;
  if (vector_width != V || !plan_small_backward(d, V, sizeof(T), s)) return false;
  const auto st = static_cast<cudaStream_t>(stream);
  if (silu) {
    if (residual != nullptr) launch_small_backward<T, V, true, true>(dy, x, p, s, d.N, mean, rstd, residual, dx, st);
    else launch_small_backward<T, V, true, false>(dy, x, p, s, d.N, mean, rstd, residual, dx, st);
  } else {
    if (residual != nullptr) launch_small_backward<T, V, false, true>(dy, x, p, s, d.N, mean, rstd, residual, dx, st);
    else launch_small_backward<T, V, false, false>(dy, x, p, s, d.N, mean, rstd, residual, dx, st);
  }
  return true;
}

#define TIGER_GN_SMALL_BACKWARD(T)                                                                                \
  template bool launch_backward_small<T>(const T*, const T*, Params, const Dims&, const float*, const float*, bool, \
                                         const T*, T*, int, void*);
TIGER_GN_SMALL_BACKWARD(float)
TIGER_GN_SMALL_BACKWARD(__half)
TIGER_GN_SMALL_BACKWARD(__nv_bfloat16)
#undef TIGER_GN_SMALL_BACKWARD

}  // namespace group_norm
}  // namespace tiger
