// CUDA kernels of tiger::group_norm (raw pointers, no torch headers).
//
// Both layouts are walked the same way: a "slice" is an image row block that shares one set of
// per-column channels (NHWC: slice = n, rows = pixels, columns = the C / V channel vectors;
// NCHW: slice = (n, c), rows = H·W / V pixel vectors, one column whose V lanes all belong to
// channel c). Block (slice s = blockIdx.x, chunk k = blockIdx.y, column pass blockIdx.z) covers
// rows [k·chunk, (k+1)·chunk) of the pass's (at most kMaxCols) columns; thread (tx, ty) owns
// column tx of the pass and rows ty, ty + R, ... so a warp reads contiguous 16-byte vectors.
// Column passes are blocks of their own, not a loop of one block: a wide map with few pixels
// (the UNets' 1920- and 2560-channel maps at 8²-16², 4-5 passes) otherwise ran on N x 2 blocks.
// Per-(slice, chunk, lane) partials (Welford moments relative to a per-channel shift; sums of dz
// and dz·x̂ for the backward) are combined per (n, g) by a second kernel in a fixed order:
// deterministic, and no host synchronisation anywhere.
#include <cuda_runtime.h>

#include <algorithm>

#include "common/cuda_helpers.cuh"
#include "group_norm/group_norm.h"
#include "group_norm/group_norm_device.cuh"

namespace tiger {
namespace group_norm {
namespace {

using tiger::cuda::load_as;
using tiger::cuda::store_as;
using tiger::cuda::Vec;

constexpr int kFinalThreads = 128;

// The walk of one block: geometry shared by the four walking kernels.
struct Walk {
  int64_t rows, cols, C, chunk;  // rows and columns (vectors) per slice, channels, rows per chunk
  int cvt;                       // threads along columns
  bool nhwc;
};

struct Tile {
  int64_t slice, n, r0, r1;
  int tx, ty, R;
};

__device__ __forceinline__ Tile tile_of(const Walk& w) {
  Tile t;
  t.slice = blockIdx.x;
  t.n = w.nhwc ? t.slice : t.slice / w.C;
  t.r0 = static_cast<int64_t>(blockIdx.y) * w.chunk;
  t.r1 = min(w.rows, t.r0 + w.chunk);
  t.tx = threadIdx.x % w.cvt;
  t.ty = threadIdx.x / w.cvt;
  t.R = blockDim.x / w.cvt;
  return t;
}

// Channel of lane j of column v.
template <int V>
__device__ __forceinline__ int64_t channel_of(const Walk& w, const Tile& t, int64_t v, int j) {
  return w.nhwc ? v * V + j : t.slice % w.C;
}

template <int V>
__device__ __forceinline__ int64_t offset_of(const Walk& w, const Tile& t, int64_t r, int64_t v) {
  return (t.slice * w.rows + r) * w.cols * V + v * V;
}

// Moments are accumulated relative to a per-(n, c) shift, the channel's first element in the
// slice, so large-mean inputs lose no variance to cancellation: every chunk and thread of a
// channel shares it, and the per-(n, g) combine moves each channel into its group's frame.
// c: the channel (NHWC); NCHW slices hold one channel and start with its first element.
template <typename T, int V>
__device__ __forceinline__ float shift_at(const T* x, const Walk& w, int64_t slice, int64_t c) {
  return load_as<float>(x[w.nhwc ? slice * w.rows * w.C + c : slice * w.rows * V]);
}

// Chan's merge of (count, mean, M2) b into a.
__device__ __forceinline__ void merge(float& n, float& mean, float& m2, float nb, float meanb, float m2b) {
  if (nb == 0.f) return;
  const float tot = n + nb;
  const float f = nb / tot;
  const float delta = meanb - mean;
  mean += delta * f;
  m2 += m2b + delta * delta * n * f;
  n = tot;
}

// Tree over the R thread rows of a block (slot = ty·cvt + tx), fixed order; after it slot tx
// (ty = 0) holds the column's result. P is the power of two >= R.
__device__ __forceinline__ int pow2_at_least(int r) {
  int p = 1;
  while (p < r) p <<= 1;
  return p;
}

// Rows r0, r0 + step, ... < r1 in order, loading B rows before using them: the loads of a batch
// are in flight together (one 16-byte load per thread at a time left the walks latency bound at
// 50-70 % of the H100's bandwidth). The use order is the plain loop's: same results. B = 4 for
// the one-tensor walks, 2 for the two-tensor ones (x and dy: 4 loads in flight either way; 4 rows
// of both took ~160 registers a thread, one block per SM).
template <int B, typename Load, typename Use>
__device__ __forceinline__ void walk_rows(int64_t r0, int64_t r1, int64_t step, Load load, Use use) {
  int64_t r = r0;
  for (; r + (B - 1) * step < r1; r += B * step) {
    decltype(load(r)) v[B];
#pragma unroll
    for (int u = 0; u < B; ++u) v[u] = load(r + u * step);
#pragma unroll
    for (int u = 0; u < B; ++u) use(r + u * step, v[u]);
  }
  for (; r < r1; r += step) use(r, load(r));
}

template <typename T, int V>
struct VecPair {
  Vec<T, V> x, g;
};

// ---- statistics: per-(slice, chunk, lane) Welford moments --------------------------------
template <typename T, int V>
__global__ void __launch_bounds__(kThreads) stats_kernel(const T* __restrict__ x, Walk w, float* __restrict__ pmean,
                                                         float* __restrict__ pm2) {
  __shared__ float s_mean[kThreads * V], s_m2[kThreads * V], s_n[kThreads];
  const Tile t = tile_of(w);
  const int slot = threadIdx.x;
  const int P = pow2_at_least(t.R);
  for (int64_t v0 = int64_t(blockIdx.z) * w.cvt; v0 < w.cols; v0 += int64_t(gridDim.z) * w.cvt) {
    const int64_t v = v0 + t.tx;
    const bool active = t.ty < t.R && v < w.cols;
    float n = 0.f, mean[V], m2[V], shift[V];
#pragma unroll
    for (int j = 0; j < V; ++j) mean[j] = m2[j] = shift[j] = 0.f;
    if (active) {
#pragma unroll
      for (int j = 0; j < V; ++j) shift[j] = shift_at<T, V>(x, w, t.slice, v * V + j);
      walk_rows<4>(
          t.r0 + t.ty, t.r1, t.R,
          [&](int64_t r) { return *reinterpret_cast<const Vec<T, V>*>(x + offset_of<V>(w, t, r, v)); },
          [&](int64_t, const Vec<T, V>& val) {
            n += 1.f;
            const float inv = 1.f / n;
#pragma unroll
            for (int j = 0; j < V; ++j) {
              const float xv = load_as<float>(val.v[j]) - shift[j];
              const float d = xv - mean[j];
              mean[j] += d * inv;
              m2[j] += d * (xv - mean[j]);
            }
          });
    }
#pragma unroll
    for (int j = 0; j < V; ++j) {
      s_mean[slot * V + j] = mean[j];
      s_m2[slot * V + j] = m2[j];
    }
    s_n[slot] = n;
    __syncthreads();
    for (int s = P / 2; s >= 1; s >>= 1) {
      if (active && t.ty < s && t.ty + s < t.R) {
        const int other = slot + s * w.cvt;
        const float nb = s_n[other];
#pragma unroll
        for (int j = 0; j < V; ++j) {
          float n_j = n;  // the lanes share the count: each merge starts from it
          merge(n_j, mean[j], m2[j], nb, s_mean[other * V + j], s_m2[other * V + j]);
          s_mean[slot * V + j] = mean[j];
          s_m2[slot * V + j] = m2[j];
        }
        n += nb;
        s_n[slot] = n;
      }
      __syncthreads();
    }
    if (active && t.ty == 0) {
      const int64_t base = (t.slice * gridDim.y + blockIdx.y) * w.cols * V + v * V;
#pragma unroll
      for (int j = 0; j < V; ++j) {
        pmean[base + j] = mean[j];
        pm2[base + j] = m2[j];
      }
    }
    __syncthreads();
  }
}

// Number of partial entries of group (n, g) and the address/count of entry e: NHWC partials are
// [N, K, C], NCHW partials [N·C, K, V] (V lanes of one channel).
struct Partials {
  int64_t N, C, G, K, rows, chunk;
  int V;
  bool nhwc;
  __device__ __forceinline__ int64_t entries() const { return (C / G) * K * (nhwc ? 1 : V); }
  __device__ __forceinline__ void at(int64_t n, int64_t g, int64_t e, int64_t& index, float& count) const {
    const int64_t D = C / G;
    int64_t k, c;
    if (nhwc) {
      k = e / D;
      c = g * D + e % D;
      index = (n * K + k) * C + c;
    } else {
      const int64_t j = e % V, kc = e / V;
      k = kc % K;
      c = g * D + kc / K;
      index = ((n * C + c) * K + k) * V + j;
    }
    count = static_cast<float>(max(int64_t(0), min(chunk, rows - k * chunk)));
  }
  // Element of x whose value is channel c's shift (shift_at).
  __device__ __forceinline__ int64_t shift_index(int64_t n, int64_t c) const {
    return nhwc ? n * rows * C + c : (n * C + c) * rows * V;
  }
  __device__ __forceinline__ int64_t channel_of_entry(int64_t g, int64_t e) const {
    const int64_t D = C / G;
    return nhwc ? g * D + e % D : g * D + e / (V * K);
  }
};

// The input bias (input_bias_at) is added to every element of the channel, shifts included, so the
// per-channel moments (relative to the shift) need no change.

template <typename T>
__global__ void __launch_bounds__(kFinalThreads) finalize_stats_kernel(Partials pt, const T* __restrict__ x,
                                                                       const float* __restrict__ ib,
                                                                       int64_t ib_stride,
                                                                       const float* __restrict__ pmean,
                                                                       const float* __restrict__ pm2, float eps,
                                                                       float* __restrict__ mean_out,
                                                                       float* __restrict__ rstd_out) {
  __shared__ float s_n[kFinalThreads], s_mean[kFinalThreads], s_m2[kFinalThreads];
  const int64_t ng = blockIdx.x, n = ng / pt.G, g = ng % pt.G;
  // The group's frame: the shift of its first channel; each entry's mean moves into it.
  const int64_t c_first = g * (pt.C / pt.G);
  const float s0 = load_as<float>(x[pt.shift_index(n, c_first)]) + input_bias_at(ib, ib_stride, n, c_first);
  float cnt = 0.f, mean = 0.f, m2 = 0.f;
  const int64_t E = pt.entries();
  for (int64_t e = threadIdx.x; e < E; e += blockDim.x) {
    int64_t idx;
    float c;
    pt.at(n, g, e, idx, c);
    const int64_t ch = pt.channel_of_entry(g, e);
    const float to_group = load_as<float>(x[pt.shift_index(n, ch)]) + input_bias_at(ib, ib_stride, n, ch) - s0;
    merge(cnt, mean, m2, c, to_group + pmean[idx], pm2[idx]);
  }
  s_n[threadIdx.x] = cnt;
  s_mean[threadIdx.x] = mean;
  s_m2[threadIdx.x] = m2;
  __syncthreads();
  for (int s = blockDim.x / 2; s >= 1; s >>= 1) {
    if (threadIdx.x < s) {
      const int o = threadIdx.x + s;
      merge(cnt, mean, m2, s_n[o], s_mean[o], s_m2[o]);
      s_n[threadIdx.x] = cnt;
      s_mean[threadIdx.x] = mean;
      s_m2[threadIdx.x] = m2;
    }
    __syncthreads();
  }
  if (threadIdx.x == 0) {
    mean_out[ng] = s0 + mean;
    rstd_out[ng] = rsqrtf(fmaxf(cnt > 0.f ? m2 / cnt : 0.f, 0.f) + eps);
  }
}

// Per-lane constants of one column: mean, rstd, w, b of its V channels.
template <typename T, int V>
struct ColumnConsts {
  float mean[V], rstd[V], w[V], b[V], ib[V];
  __device__ __forceinline__ void load(const Walk& wk, const Tile& t, int64_t v, const Params& p, int64_t G,
                                       const float* mean_g, const float* rstd_g) {
    const int64_t D = wk.C / G;
#pragma unroll
    for (int j = 0; j < V; ++j) {
      const int64_t c = channel_of<V>(wk, t, v, j);
      const int64_t ng = t.n * G + c / D;
      ib[j] = input_bias_at(p.input_bias, p.input_bias_stride, t.n, c);
      mean[j] = mean_g[ng];
      rstd[j] = rstd_g[ng];
      w[j] = param_at<T>(p, p.weight, c, 1.f);
      b[j] = param_at<T>(p, p.bias, c, 0.f);
    }
  }
};

// Three constants per lane for the passes that apply the norm or its backward: with m = mean − ib
// (the input bias moved into the mean: x − m keeps the subtraction of nearly equal values exact;
// x·a + shift would not), a = rstd·w and b, z = (x − m)·a + b. Fewer registers than ColumnConsts'
// five plus products, and fewer operations per element.
template <typename T, int V>
struct FoldedConsts {
  float m[V], a[V], b[V];
  __device__ __forceinline__ void load(const Walk& wk, const Tile& t, int64_t v, const Params& p, int64_t G,
                                       const float* mean_g, const float* rstd_g) {
    ColumnConsts<T, V> k;
    k.load(wk, t, v, p, G, mean_g, rstd_g);
#pragma unroll
    for (int j = 0; j < V; ++j) {
      m[j] = k.mean[j] - k.ib[j];
      a[j] = k.rstd[j] * k.w[j];
      b[j] = k.b[j];
    }
  }
};

// ---- forward apply: y = act((x − mean)·rstd·w + b) ---------------------------------------
// Four blocks per SM (64 registers; 32 bytes of the bf16 instances spill): the 80 registers of
// three blocks left the 512² maps at 70 % of DRAM bandwidth; the apply kernels of one
// InstructPix2Pix step 2.56 -> 2.36 ms (H100, guidance_floor_gn_apply_registers_h100.txt).
template <typename T, int V, bool SILU>
__global__ void __launch_bounds__(kThreads, 4) apply_kernel(const T* __restrict__ x, Walk w, Params p, int64_t G,
                                                         const float* __restrict__ mean_g,
                                                         const float* __restrict__ rstd_g, T* __restrict__ y) {
  const Tile t = tile_of(w);
  if (t.ty >= t.R) return;
  for (int64_t v = int64_t(blockIdx.z) * w.cvt + t.tx; v < w.cols; v += int64_t(gridDim.z) * w.cvt) {
    FoldedConsts<T, V> k;  // fewer registers: more blocks per SM for this bandwidth-bound pass
    k.load(w, t, v, p, G, mean_g, rstd_g);
    walk_rows<4>(
        t.r0 + t.ty, t.r1, t.R,
        [&](int64_t r) { return *reinterpret_cast<const Vec<T, V>*>(x + offset_of<V>(w, t, r, v)); },
        [&](int64_t r, const Vec<T, V>& in) {
          Vec<T, V> out;
#pragma unroll
          for (int j = 0; j < V; ++j) {
            float z = (load_as<float>(in.v[j]) - k.m[j]) * k.a[j] + k.b[j];
            if (SILU) z *= sigmoid(z);
            out.v[j] = store_as<T>(z);
          }
          *reinterpret_cast<Vec<T, V>*>(y + offset_of<V>(w, t, r, v)) = out;
        });
  }
}

// The backward with FoldedConsts (m = mean − ib, a = rstd·w, b):
//   d = x − m,   z = d·a + b  (a = rstd·w),   dz = dy·σ(z)(1 + z(1 − σ(z)))  (dz = dy without SiLU),
//   Σ dz·x̂ = rstd·Σ dz·d,   dx = a·dz − rstd·c1 − d·rstd²·c2.
// The reduction keeps m, a, b (3 a lane, rstd applied once at its end), the input gradient m, a,
// b, k1 = rstd·c1, k2 = rstd²·c2 (5), instead of mean, rstd, w, b, ib (and c1, c2), with fewer
// operations per element. The VAE's backward norms ran 7-11 % faster at the same two blocks per SM
// (group_norm_backward_occupancy_variants_h100.txt); capped at 80 registers (three blocks per
// SM, which the folded constants allow) they were slower (group_norm.h).

// ---- backward reductions: per-(slice, chunk, lane) Σ dz and Σ dz·x̂ -----------------------
// kBackwardBlocksPerSm blocks per SM (group_norm.h).
template <typename T, int V, bool SILU>
__global__ void __launch_bounds__(kThreads, kBackwardBlocksPerSm) backward_reduce_kernel(const T* __restrict__ dy, const T* __restrict__ x,
                                                                      Walk w, Params p, int64_t G,
                                                                      const float* __restrict__ mean_g,
                                                                      const float* __restrict__ rstd_g,
                                                                      float* __restrict__ pdz, float* __restrict__ pdzx) {
  __shared__ float s_a[kThreads * V], s_b[kThreads * V];
  const Tile t = tile_of(w);
  const int slot = threadIdx.x;
  const int P = pow2_at_least(t.R);
  const int64_t D = w.C / G;
  for (int64_t v0 = int64_t(blockIdx.z) * w.cvt; v0 < w.cols; v0 += int64_t(gridDim.z) * w.cvt) {
    const int64_t v = v0 + t.tx;
    const bool active = t.ty < t.R && v < w.cols;
    float sa[V], sb[V];  // Σ dz, Σ dz·d
#pragma unroll
    for (int j = 0; j < V; ++j) sa[j] = sb[j] = 0.f;
    if (active) {
      FoldedConsts<T, V> k;
      k.load(w, t, v, p, G, mean_g, rstd_g);
      walk_rows<2>(
          t.r0 + t.ty, t.r1, t.R,
          [&](int64_t r) {
            const int64_t off = offset_of<V>(w, t, r, v);
            return VecPair<T, V>{*reinterpret_cast<const Vec<T, V>*>(x + off),
                                 *reinterpret_cast<const Vec<T, V>*>(dy + off)};
          },
          [&](int64_t, const VecPair<T, V>& in) {
#pragma unroll
            for (int j = 0; j < V; ++j) {
              const float d = load_as<float>(in.x.v[j]) - k.m[j];
              const float dz = dz_of<SILU>(d, load_as<float>(in.g.v[j]), k.a[j], k.b[j]);
              sa[j] += dz;
              sb[j] += dz * d;
            }
          });
#pragma unroll
      for (int j = 0; j < V; ++j) sb[j] *= rstd_g[t.n * G + channel_of<V>(w, t, v, j) / D];  // Σ dz·x̂
    }
#pragma unroll
    for (int j = 0; j < V; ++j) {
      s_a[slot * V + j] = sa[j];
      s_b[slot * V + j] = sb[j];
    }
    __syncthreads();
    for (int s = P / 2; s >= 1; s >>= 1) {
      if (active && t.ty < s && t.ty + s < t.R) {
        const int other = slot + s * w.cvt;
#pragma unroll
        for (int j = 0; j < V; ++j) {
          sa[j] += s_a[other * V + j];
          sb[j] += s_b[other * V + j];
          s_a[slot * V + j] = sa[j];
          s_b[slot * V + j] = sb[j];
        }
      }
      __syncthreads();
    }
    if (active && t.ty == 0) {
      const int64_t base = (t.slice * gridDim.y + blockIdx.y) * w.cols * V + v * V;
#pragma unroll
      for (int j = 0; j < V; ++j) {
        pdz[base + j] = sa[j];
        pdzx[base + j] = sb[j];
      }
    }
    __syncthreads();
  }
}

// Per (n, g): per-channel totals (for dw, db) and c1, c2 = Σ w·dz / M, Σ w·dz·x̂ / M.
// One warp per channel (channels of the group strided over the block's warps), its lanes over
// the channel's partial entries, a fixed shuffle tree: a group has few channels (4-16 in the
// SD VAE) but each has a partial per chunk (~100), so lanes, not channels, carry the width.
template <typename T>
__global__ void __launch_bounds__(kFinalThreads) finalize_backward_kernel(Partials pt, Params p,
                                                                          const float* __restrict__ pdz,
                                                                          const float* __restrict__ pdzx,
                                                                          float* __restrict__ sum_dz,
                                                                          float* __restrict__ sum_dzx,
                                                                          float* __restrict__ c1,
                                                                          float* __restrict__ c2) {
  constexpr int kWarps = kFinalThreads / 32;
  __shared__ float s_a[kWarps], s_b[kWarps];
  const int64_t ng = blockIdx.x, n = ng / pt.G, g = ng % pt.G, D = pt.C / pt.G;
  const int64_t per_channel = pt.K * (pt.nhwc ? 1 : pt.V);  // entries of one channel
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  float wa = 0.f, wb = 0.f;  // lane 0: this warp's share of Σ w·a, Σ w·b
  for (int64_t j = warp; j < D; j += kWarps) {
    float a = 0.f, b = 0.f;
    for (int64_t q = lane; q < per_channel; q += 32) {
      // Entry order of Partials::at: NHWC e = k·D + j, NCHW e = (j·K + k)·V + lane.
      const int64_t e = pt.nhwc ? q * D + j : j * per_channel + q;
      int64_t idx;
      float unused;
      pt.at(n, g, e, idx, unused);
      a += pdz[idx];
      b += pdzx[idx];
    }
#pragma unroll
    for (int o = 16; o >= 1; o >>= 1) {
      a += __shfl_down_sync(0xffffffffu, a, o);
      b += __shfl_down_sync(0xffffffffu, b, o);
    }
    if (lane == 0) {
      const int64_t c = g * D + j;
      sum_dz[n * pt.C + c] = a;
      sum_dzx[n * pt.C + c] = b;
      const float wc = param_at<T>(p, p.weight, c, 1.f);
      wa += wc * a;
      wb += wc * b;
    }
  }
  if (lane == 0) {
    s_a[warp] = wa;
    s_b[warp] = wb;
  }
  __syncthreads();
  if (threadIdx.x == 0) {
    float ta = 0.f, tb = 0.f;
    for (int w = 0; w < kWarps; ++w) {
      ta += s_a[w];
      tb += s_b[w];
    }
    const float m = static_cast<float>(D) * static_cast<float>(pt.rows) * (pt.nhwc ? 1.f : pt.V);
    c1[ng] = ta / m;
    c2[ng] = tb / m;
  }
}

template <typename T, int V>
struct VecTriple {
  Vec<T, V> x, g, r;
};

// ---- backward apply: dx = a·dz − k1 − d·k2 (+ residual) (FoldedConsts) ----------
// RES: a residual gradient (like x) is read with x and dy and added before the rounding.
// kBackwardBlocksPerSm blocks per SM (group_norm.h).
template <typename T, int V, bool SILU, bool RES>
__global__ void __launch_bounds__(kThreads, kBackwardBlocksPerSm) dx_kernel(const T* __restrict__ dy, const T* __restrict__ x, Walk w,
                                                      Params p, int64_t G, const float* __restrict__ mean_g,
                                                      const float* __restrict__ rstd_g, const float* __restrict__ c1,
                                                      const float* __restrict__ c2, const T* __restrict__ residual,
                                                      T* __restrict__ dx) {
  const Tile t = tile_of(w);
  if (t.ty >= t.R) return;
  const int64_t D = w.C / G;
  for (int64_t v = int64_t(blockIdx.z) * w.cvt + t.tx; v < w.cols; v += int64_t(gridDim.z) * w.cvt) {
    FoldedConsts<T, V> k;
    k.load(w, t, v, p, G, mean_g, rstd_g);
    float k1[V], k2[V];
#pragma unroll
    for (int j = 0; j < V; ++j) {
      const int64_t ng = t.n * G + channel_of<V>(w, t, v, j) / D;
      const float rstd = rstd_g[ng];
      k1[j] = rstd * c1[ng];
      k2[j] = rstd * rstd * c2[ng];
    }
    walk_rows<2>(
        t.r0 + t.ty, t.r1, t.R,
        [&](int64_t r) {
          const int64_t off = offset_of<V>(w, t, r, v);
          VecTriple<T, V> in;
          in.x = *reinterpret_cast<const Vec<T, V>*>(x + off);
          in.g = *reinterpret_cast<const Vec<T, V>*>(dy + off);
          if constexpr (RES) in.r = *reinterpret_cast<const Vec<T, V>*>(residual + off);
          return in;
        },
        [&](int64_t r, const VecTriple<T, V>& in) {
          Vec<T, V> out;
#pragma unroll
          for (int j = 0; j < V; ++j) {
            const float d = load_as<float>(in.x.v[j]) - k.m[j];
            const float dz = dz_of<SILU>(d, load_as<float>(in.g.v[j]), k.a[j], k.b[j]);
            float g = k.a[j] * dz - k1[j] - d * k2[j];
            if constexpr (RES) g += load_as<float>(in.r.v[j]);
            out.v[j] = store_as<T>(g);
          }
          *reinterpret_cast<Vec<T, V>*>(dx + offset_of<V>(w, t, r, v)) = out;
        });
  }
}

// Geometry of the walk for vector width V.
Walk make_walk(const Dims& d, int V, int64_t chunks) {
  Walk w;
  w.nhwc = d.nhwc;
  w.C = d.C;
  w.rows = d.nhwc ? d.HW : d.HW / V;
  w.cols = d.nhwc ? d.C / V : 1;
  const int64_t passes = (w.cols + kMaxCols - 1) / kMaxCols;
  w.cvt = static_cast<int>((w.cols + passes - 1) / passes);
  w.chunk = (w.rows + chunks - 1) / chunks;
  return w;
}

Partials make_partials(const Dims& d, const Walk& w, int V, int64_t chunks) {
  return Partials{d.N, d.C, d.G, chunks, w.rows, w.chunk, V, d.nhwc};
}

// Column passes of kMaxCols vectors.
int64_t column_passes(const Walk& w) { return (w.cols + w.cvt - 1) / w.cvt; }

dim3 walk_grid(const Dims& d, const Walk& w, int64_t chunks) {
  return dim3(static_cast<unsigned>(d.nhwc ? d.N : d.N * d.C), static_cast<unsigned>(chunks),
              static_cast<unsigned>(column_passes(w)));
}

template <typename T, int V>
void forward_impl(const T* x, Params p, const Dims& d, float eps, bool silu, int64_t chunks, float* pmean, float* pm2,
                  float* mean, float* rstd, T* y, cudaStream_t st) {
  const Walk w = make_walk(d, V, chunks);
  const dim3 grid = walk_grid(d, w, chunks);
  stats_kernel<T, V><<<grid, kThreads, 0, st>>>(x, w, pmean, pm2);
  finalize_stats_kernel<T><<<static_cast<unsigned>(d.N * d.G), kFinalThreads, 0, st>>>(
      make_partials(d, w, V, chunks), x, p.input_bias, p.input_bias_stride, pmean, pm2, eps, mean, rstd);
  if (silu)
    apply_kernel<T, V, true><<<grid, kThreads, 0, st>>>(x, w, p, d.G, mean, rstd, y);
  else
    apply_kernel<T, V, false><<<grid, kThreads, 0, st>>>(x, w, p, d.G, mean, rstd, y);
}

template <typename T, int V, bool SILU>
void backward_impl(const T* dy, const T* x, Params p, const Dims& d, const float* mean, const float* rstd,
                   int64_t chunks, float* pdz, float* pdzx, float* sum_dz, float* sum_dzx, float* c1, float* c2,
                   const T* residual, T* dx, cudaStream_t st) {
  const Walk w = make_walk(d, V, chunks);
  const dim3 grid = walk_grid(d, w, chunks);
  backward_reduce_kernel<T, V, SILU><<<grid, kThreads, 0, st>>>(dy, x, w, p, d.G, mean, rstd, pdz, pdzx);
  finalize_backward_kernel<T><<<static_cast<unsigned>(d.N * d.G), kFinalThreads, 0, st>>>(
      make_partials(d, w, V, chunks), p, pdz, pdzx, sum_dz, sum_dzx, c1, c2);
  if (residual != nullptr)
    dx_kernel<T, V, SILU, true><<<grid, kThreads, 0, st>>>(dy, x, w, p, d.G, mean, rstd, c1, c2, residual, dx);
  else
    dx_kernel<T, V, SILU, false><<<grid, kThreads, 0, st>>>(dy, x, w, p, d.G, mean, rstd, c1, c2, nullptr, dx);
}

}  // namespace

int64_t plan_chunks(const Dims& d, int vector_width, int blocks_per_sm) {
  int dev = 0, sm_count = 0;
  if (cudaGetDevice(&dev) != cudaSuccess || cudaDeviceGetAttribute(&sm_count, cudaDevAttrMultiProcessorCount, dev) != cudaSuccess)
    sm_count = 132;
  const Walk w = make_walk(d, vector_width, 1);
  // blocks per chunk of rows: one per slice and column pass
  const int64_t slices = (d.nhwc ? d.N : d.N * d.C) * column_passes(w);
  const int64_t R = kThreads / w.cvt;
  const int64_t target = static_cast<int64_t>(blocks_per_sm) * sm_count;
  int64_t chunks = slices > 0 ? (target + slices - 1) / slices : 1;
  const int64_t min_rows = 8 * R;  // at least 8 rows per thread row
  chunks = std::max<int64_t>(1, std::min<int64_t>(chunks, (w.rows + min_rows - 1) / min_rows));
  chunks = std::min<int64_t>(chunks, 65535);
  const int64_t chunk = (w.rows + chunks - 1) / chunks;  // drop empty trailing chunks
  return std::max<int64_t>(1, (w.rows + chunk - 1) / std::max<int64_t>(chunk, 1));
}

template <typename T>
void launch_forward(const T* x, Params p, const Dims& d, float eps, bool silu, int64_t chunks, float* partial_mean,
                    float* partial_m2, float* mean, float* rstd, T* y, int vector_width, void* stream) {
  const auto st = static_cast<cudaStream_t>(stream);
  if (vector_width > 1)
    forward_impl<T, 16 / sizeof(T)>(x, p, d, eps, silu, chunks, partial_mean, partial_m2, mean, rstd, y, st);
  else
    forward_impl<T, 1>(x, p, d, eps, silu, chunks, partial_mean, partial_m2, mean, rstd, y, st);
}

template <typename T>
void launch_backward(const T* dy, const T* x, Params p, const Dims& d, const float* mean, const float* rstd, bool silu,
                     int64_t chunks, float* partial_dz, float* partial_dzx, float* sum_dz, float* sum_dzx, float* c1,
                     float* c2, const T* residual, T* dx, int vector_width, void* stream) {
  const auto st = static_cast<cudaStream_t>(stream);
  constexpr int VV = 16 / sizeof(T);
#define TIGER_GN_BWD(V, S) \
  backward_impl<T, V, S>(dy, x, p, d, mean, rstd, chunks, partial_dz, partial_dzx, sum_dz, sum_dzx, c1, c2, residual, \
                         dx, st)
  if (vector_width > 1) {
    if (silu) TIGER_GN_BWD(VV, true); else TIGER_GN_BWD(VV, false);
  } else {
    if (silu) TIGER_GN_BWD(1, true); else TIGER_GN_BWD(1, false);
  }
#undef TIGER_GN_BWD
}

#define TIGER_INSTANTIATE(T)                                                                                     \
  template void launch_forward<T>(const T*, Params, const Dims&, float, bool, int64_t, float*, float*, float*, \
                                  float*, T*, int, void*);                                                     \
  template void launch_backward<T>(const T*, const T*, Params, const Dims&, const float*, const float*, bool,  \
                                   int64_t, float*, float*, float*, float*, float*, float*, const T*, T*, int, void*);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(__half)
TIGER_INSTANTIATE(__nv_bfloat16)
#undef TIGER_INSTANTIATE

}  // namespace group_norm
}  // namespace tiger
