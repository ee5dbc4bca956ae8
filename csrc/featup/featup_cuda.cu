// CUDA kernels of tiger::jittered_window_attention (raw pointers, no torch headers).
//
// One block per cell (jitter j, window row i, window column l) computes the window's bilinear
// taps, its softmax, and the cell's source tile: the attention pushed through the bilinear
// weights onto the (at most (K+3)^2) source pixels that the window reads. The output is then a
// dot product of the tile with the features (channels last, so the threads of a block read
// neighbouring channels). The features' gradient is gathered per source pixel from the tiles of
// the cells that cover it (no atomics); the logit map's gradient uses atomics (K*K*4 per cell, or
// one per touched tile pixel after a shared-memory sum). Variants: featup.h.
#include <cuda_bf16.h>
#include <cuda_runtime.h>
#include <limits.h>
#include <math.h>

#include <type_traits>

#include "common/cuda_helpers.cuh"
#include "featup/featup.h"
#include "featup/featup_math.h"

namespace tiger {
namespace featup {
namespace {

constexpr int kMaxTile = kMaxKernel + 3;  // a window of K rows reads at most K + 2 source rows
constexpr int kMaxThreads = 256;
constexpr int kPixelsPerBlock = 16;       // grad_features: source pixels of one row per block
constexpr int kDotCols = 32;              // tile_dots: source pixels of one row per block (at most)
constexpr int kDotList = 1024;            // tile_dots: candidate cells tested per round
constexpr int kGatherList = 256;          // grad_features_staged: candidate cells tested per round
// forward_grouped: neighbouring cells per block (shared memory: CellShared plus G tiles, < 48 KB)
template <typename T>
constexpr int kForwardGroup = sizeof(T) == 4 ? 4 : 2;

// A feature read as the accumulation type (bfloat16 widened to float).
__device__ __forceinline__ float widen(float v) { return v; }
__device__ __forceinline__ double widen(double v) { return v; }
__device__ __forceinline__ float widen(__nv_bfloat16 v) { return __bfloat162float(v); }

template <typename T>
struct CellShared {
  Tap<T> ty[kMaxKernel], tx[kMaxKernel];
  T attn[kMaxKernel * kMaxKernel];
  T buf[kMaxKernel * kMaxKernel];
  T tile[kMaxTile * kMaxTile];
  T red[kMaxThreads / 32];
  int r0, c0, tr, tc;
  bool overflow;
};

template <typename T>
__device__ __forceinline__ T warp_max(T v) {
  for (int o = 16; o > 0; o >>= 1) {
    const T other = __shfl_xor_sync(cuda::kFullMask, v, o);
    v = other > v ? other : v;
  }
  return v;
}

// Block-wide sum or max (blockDim.x a multiple of 32); every thread gets the result.
template <typename T, bool kMax>
__device__ T block_reduce(T v, T* red) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  v = kMax ? warp_max(v) : cuda::warp_sum(v);
  if (lane == 0) red[warp] = v;
  __syncthreads();
  if (warp == 0) {
    T r = lane < warps ? red[lane] : (kMax ? T(-INFINITY) : T(0));
    r = kMax ? warp_max(r) : cuda::warp_sum(r);
    if (lane == 0) red[0] = r;
  }
  __syncthreads();
  const T out = red[0];
  __syncthreads();
  return out;
}

// The window's taps and its source tile's origin and extent (all threads; ends synchronised).
template <typename T>
__device__ void load_cell(const T* cy, const T* cx, const WindowDims& d, int64_t cell, CellShared<T>& s) {
  const int64_t j = cell / (d.FH * d.FW), i = (cell / d.FW) % d.FH, l = cell % d.FW;
  for (int t = threadIdx.x; t < d.K; t += blockDim.x) {
    s.ty[t] = axis_tap(cy[j * d.Ho + i * d.SH + t], d.H);
    s.tx[t] = axis_tap(cx[j * d.Wo + l * d.SW + t], d.W);
  }
  __syncthreads();
  if (threadIdx.x == 0) {
    int rlo = s.ty[0].index, rhi = rlo, clo = s.tx[0].index, chi = clo;
    for (int t = 0; t < d.K; ++t) {
      rlo = min(rlo, s.ty[t].index);
      rhi = max(rhi, s.ty[t].index + (s.ty[t].second ? 1 : 0));
      clo = min(clo, s.tx[t].index);
      chi = max(chi, s.tx[t].index + (s.tx[t].second ? 1 : 0));
    }
    const int side = static_cast<int>(d.K) + 3;
    s.r0 = rlo;
    s.c0 = clo;
    s.tr = rhi - rlo + 1;
    s.tc = chi - clo + 1;
    s.overflow = s.tr > side || s.tc > side;
  }
  __syncthreads();
}

// s.attn = softmax of the window's masked, scaled logits (ends synchronised).
template <typename T>
__device__ void cell_softmax(const T* logit_map, const T* w, const T* b, T m, const WindowDims& d, CellShared<T>& s) {
  const int KK = static_cast<int>(d.K * d.K), K = static_cast<int>(d.K);
  T zmax = T(-INFINITY);
  for (int p = threadIdx.x; p < KK; p += blockDim.x) {
    const T z = bilinear(logit_map, d.W, s.ty[p / K], s.tx[p % K]) * m * w[p] + b[p];
    s.attn[p] = z;
    zmax = z > zmax ? z : zmax;
  }
  zmax = block_reduce<T, true>(zmax, s.red);
  T sum = 0;
  for (int p = threadIdx.x; p < KK; p += blockDim.x) {
    const T e = exp(s.attn[p] - zmax);
    s.attn[p] = e;
    sum += e;
  }
  sum = block_reduce<T, false>(sum, s.red);
  const T inv = T(1) / sum;
  for (int p = threadIdx.x; p < KK; p += blockDim.x) s.attn[p] *= inv;
  __syncthreads();
}

// Calls f(tile index, bilinear weight) for the taps of window pixel (py, px).
template <typename T, typename F>
__device__ __forceinline__ void for_tile_taps(const CellShared<T>& s, int py, int px, int side, F&& f) {
  const Tap<T>& ty = s.ty[py];
  const Tap<T>& tx = s.tx[px];
  const int base = (ty.index - s.r0) * side + (tx.index - s.c0);
  const T wy0 = T(1) - ty.frac, wx0 = T(1) - tx.frac;
  f(base, wy0 * wx0);
  if (tx.second) f(base + 1, wy0 * tx.frac);
  if (ty.second) {
    f(base + side, ty.frac * wx0);
    if (tx.second) f(base + side + 1, ty.frac * tx.frac);
  }
}

// s.tile = the attention pushed through the bilinear weights (ends synchronised).
template <typename T>
__device__ void build_tile(const WindowDims& d, CellShared<T>& s) {
  const int K = static_cast<int>(d.K), side = K + 3;
  for (int t = threadIdx.x; t < side * side; t += blockDim.x) s.tile[t] = T(0);
  __syncthreads();
  if (!s.overflow)
    for (int p = threadIdx.x; p < K * K; p += blockDim.x) {
      const T a = s.attn[p];
      for_tile_taps(s, p / K, p % K, side, [&](int t, T wt) { atomicAdd(&s.tile[t], a * wt); });
    }
  __syncthreads();
}

template <typename T, typename TF>
__global__ void __launch_bounds__(kMaxThreads) forward_kernel(const TF* __restrict__ F, const T* __restrict__ logit_map,
                                                              const T* __restrict__ cy, const T* __restrict__ cx,
                                                              const T* __restrict__ w, const T* __restrict__ b,
                                                              const T* __restrict__ mask, WindowDims d,
                                                              T* __restrict__ out, T* __restrict__ attn) {
  __shared__ CellShared<T> s;
  const int64_t cell = blockIdx.x;
  const int KK = static_cast<int>(d.K * d.K), side = static_cast<int>(d.K) + 3;
  load_cell(cy, cx, d, cell, s);
  cell_softmax(logit_map, w, b, mask[cell], d, s);
  for (int p = threadIdx.x; p < KK; p += blockDim.x) attn[cell * KK + p] = s.attn[p];
  build_tile(d, s);
  for (int64_t c = threadIdx.x; c < d.C; c += blockDim.x) {
    T acc = 0;
    if (s.overflow) {
      acc = T(NAN);
    } else {
      for (int r = 0; r < s.tr; ++r) {
        const TF* row = F + ((s.r0 + r) * d.W + s.c0) * d.C + c;
        const T* trow = s.tile + r * side;
        for (int q = 0; q < s.tc; ++q) acc += trow[q] * static_cast<T>(widen(row[q * d.C]));
      }
    }
    out[cell * d.C + c] = acc;
  }
}

// forward_kernel for G neighbouring cells (j, i, l0 .. l0 + G - 1) of a window row per block: they
// share their tile rows (the row taps depend on (j, i) only) and their tiles overlap by about half,
// so the block reads the union of their tiles' columns once per row instead of each tile apart.
// Each cell's softmax and tile are computed in turn (as forward_kernel does) and its tile kept in
// shared memory; the sums run over the same pixels in the same order as forward_kernel's.
template <typename T, typename TF, int G>
__global__ void __launch_bounds__(kMaxThreads) forward_grouped_kernel(
    const TF* __restrict__ F, const T* __restrict__ logit_map, const T* __restrict__ cy, const T* __restrict__ cx,
    const T* __restrict__ w, const T* __restrict__ b, const T* __restrict__ mask, WindowDims d, T* __restrict__ out,
    T* __restrict__ attn) {
  __shared__ CellShared<T> s;
  __shared__ T group_tile[G][kMaxTile * kMaxTile];
  __shared__ int group_c0[G], group_tc[G];  // tc = 0: no such cell, or its footprint overflows
  const int groups_per_row = static_cast<int>((d.FW + G - 1) / G);
  const int64_t window_row = blockIdx.x / groups_per_row;  // j * FH + i
  const int l0 = static_cast<int>(blockIdx.x % groups_per_row) * G;
  const int n = min(G, static_cast<int>(d.FW) - l0);
  const int KK = static_cast<int>(d.K * d.K), side = static_cast<int>(d.K) + 3;
  for (int k = 0; k < G; ++k) {
    if (k >= n) {
      if (threadIdx.x == 0) group_c0[k] = group_tc[k] = 0;
      continue;
    }
    const int64_t cell = window_row * d.FW + l0 + k;
    load_cell(cy, cx, d, cell, s);
    cell_softmax(logit_map, w, b, mask[cell], d, s);
    for (int p = threadIdx.x; p < KK; p += blockDim.x) attn[cell * KK + p] = s.attn[p];
    build_tile(d, s);
    for (int t = threadIdx.x; t < side * side; t += blockDim.x) group_tile[k][t] = s.tile[t];
    if (threadIdx.x == 0) {
      group_c0[k] = s.overflow ? 0 : s.c0;
      group_tc[k] = s.overflow ? 0 : s.tc;
    }
    __syncthreads();  // the next cell's load_cell rewrites s
  }
  __syncthreads();  // (group_c0, group_tc of the missing cells past the row's end)
  // every cell of the group has the same tile rows (s: the last cell's); the columns' union
  const int r0 = s.r0, tr = s.tr;
  int c0[G], tc[G], vlo = INT_MAX, vhi = -1;
#pragma unroll
  for (int k = 0; k < G; ++k) {
    c0[k] = group_c0[k];
    tc[k] = group_tc[k];
    if (tc[k] > 0) {
      vlo = min(vlo, c0[k]);
      vhi = max(vhi, c0[k] + tc[k] - 1);
    }
  }
  for (int64_t c = threadIdx.x; c < d.C; c += blockDim.x) {
    T acc[G];
#pragma unroll
    for (int k = 0; k < G; ++k) acc[k] = T(0);
    for (int r = 0; r < tr && vlo <= vhi; ++r) {
      const TF* row = F + static_cast<int64_t>(r0 + r) * d.W * d.C + c;
      for (int v = vlo; v <= vhi; ++v) {
        const T f = static_cast<T>(widen(row[v * d.C]));
#pragma unroll
        for (int k = 0; k < G; ++k) {
          const int q = v - c0[k];
          if (q >= 0 && q < tc[k]) acc[k] += group_tile[k][r * side + q] * f;
        }
      }
    }
#pragma unroll
    for (int k = 0; k < G; ++k)
      if (k < n) out[(window_row * d.FW + l0 + k) * d.C + c] = tc[k] > 0 ? acc[k] : T(NAN);
  }
}

// kSharedScatter: the cell's logit-map gradient is summed in the shared tile, then added to
// grad_logit with one atomic per nonzero tile pixel (else K*K*4 global atomics).
// kDotsGiven: D (g dotted with the features of each tile pixel) is read from `dots` (tile_dots_kernel)
// instead of being computed here from F.
template <typename T, bool kSharedScatter, bool kDotsGiven>
__global__ void __launch_bounds__(kMaxThreads) backward_cells_kernel(
    const T* __restrict__ g, const T* __restrict__ F, const T* __restrict__ logit_map, const T* __restrict__ cy,
    const T* __restrict__ cx, const T* __restrict__ w, const T* __restrict__ mask, const T* __restrict__ attn,
    const T* __restrict__ dots, WindowDims d, T* __restrict__ gz_out, T* __restrict__ gzl_out,
    T* __restrict__ grad_logit, T* __restrict__ tiles, int32_t* __restrict__ origins) {
  __shared__ CellShared<T> s;
  const int64_t cell = blockIdx.x;
  const int K = static_cast<int>(d.K), KK = K * K, side = K + 3;
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  load_cell(cy, cx, d, cell, s);
  for (int p = threadIdx.x; p < KK; p += blockDim.x) s.attn[p] = attn[cell * KK + p];
  // s.tile = D: the output gradient dotted with the features at every tile pixel
  if (!s.overflow) {
    if (kDotsGiven) {
      const T* dc = dots + cell * side * side;
      for (int t = threadIdx.x; t < s.tr * s.tc; t += blockDim.x) {
        const int r = t / s.tc, q = t % s.tc;
        s.tile[r * side + q] = dc[r * side + q];
      }
    } else {  // a warp per pixel
      const T* gc = g + cell * d.C;
      for (int t = warp; t < s.tr * s.tc; t += warps) {
        const int r = t / s.tc, q = t % s.tc;
        const T* f = F + ((s.r0 + r) * d.W + s.c0 + q) * d.C;
        T acc = 0;
        for (int64_t c = lane; c < d.C; c += 32) acc += gc[c] * f[c];
        acc = cuda::warp_sum(acc);
        if (lane == 0) s.tile[r * side + q] = acc;
      }
    }
  }
  __syncthreads();
  // ga[p] = sum over taps of weight * D; the softmax backward
  T dot = 0;
  for (int p = threadIdx.x; p < KK; p += blockDim.x) {
    T ga = 0;
    if (s.overflow)
      ga = T(NAN);
    else
      for_tile_taps(s, p / K, p % K, side, [&](int t, T wt) { ga += wt * s.tile[t]; });
    s.buf[p] = ga;
    dot += s.attn[p] * ga;
  }
  dot = block_reduce<T, false>(dot, s.red);  // ends synchronised: D is no longer read
  // an overflowing cell's taps leave the tile: it scatters to global memory directly (NaN)
  const bool shared_scatter = kSharedScatter && !s.overflow;
  if (shared_scatter) {
    for (int t = threadIdx.x; t < side * side; t += blockDim.x) s.tile[t] = T(0);
    __syncthreads();
  }
  const T m = mask[cell];
  for (int p = threadIdx.x; p < KK; p += blockDim.x) {
    const int py = p / K, px = p % K;
    const T gz = s.attn[p] * (s.buf[p] - dot);
    gz_out[cell * KK + p] = gz;
    gzl_out[cell * KK + p] = gz * m * bilinear(logit_map, d.W, s.ty[py], s.tx[px]);
    const T coef = gz * m * w[p];
    if (shared_scatter) {
      for_tile_taps(s, py, px, side, [&](int t, T wt) { atomicAdd(&s.tile[t], coef * wt); });
      continue;
    }
    const Tap<T>& ty = s.ty[py];
    const Tap<T>& tx = s.tx[px];
    T* base = grad_logit + static_cast<int64_t>(ty.index) * d.W + tx.index;
    const T wy0 = T(1) - ty.frac, wx0 = T(1) - tx.frac;
    atomicAdd(base, coef * wy0 * wx0);
    if (tx.second) atomicAdd(base + 1, coef * wy0 * tx.frac);
    if (ty.second) {
      atomicAdd(base + d.W, coef * ty.frac * wx0);
      if (tx.second) atomicAdd(base + d.W + 1, coef * ty.frac * tx.frac);
    }
  }
  __syncthreads();
  if (shared_scatter) {
    for (int t = threadIdx.x; t < s.tr * s.tc; t += blockDim.x) {
      const int r = t / s.tc, q = t % s.tc;
      const T v = s.tile[r * side + q];
      if (v != T(0)) atomicAdd(grad_logit + static_cast<int64_t>(s.r0 + r) * d.W + s.c0 + q, v);
    }
    __syncthreads();
  }
  // the cell's source tile, for the features' gradient
  build_tile(d, s);
  for (int t = threadIdx.x; t < side * side; t += blockDim.x) tiles[cell * side * side + t] = s.tile[t];
  if (threadIdx.x == 0) {
    origins[cell * 2] = s.r0;
    origins[cell * 2 + 1] = s.c0;
  }
}

// Each cell's tile extent (r0, c0, tr, tc) as load_cell computes it; (0, 0, 0, 0) for a cell whose
// footprint overflows the tile (its outputs are NaN, and no pixel lists it).
template <typename T>
__global__ void cell_extents_kernel(const T* __restrict__ cy, const T* __restrict__ cx, WindowDims d,
                                    int4* __restrict__ extents) {
  const int64_t cell = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (cell >= d.J * d.FH * d.FW) return;
  const int64_t j = cell / (d.FH * d.FW), i = (cell / d.FW) % d.FH, l = cell % d.FW;
  int rlo = 0, rhi = 0, clo = 0, chi = 0;
  for (int t = 0; t < d.K; ++t) {
    const Tap<T> ty = axis_tap(cy[j * d.Ho + i * d.SH + t], d.H);
    const Tap<T> tx = axis_tap(cx[j * d.Wo + l * d.SW + t], d.W);
    const int rh = ty.index + (ty.second ? 1 : 0), ch = tx.index + (tx.second ? 1 : 0);
    rlo = t ? min(rlo, ty.index) : ty.index;
    rhi = t ? max(rhi, rh) : rh;
    clo = t ? min(clo, tx.index) : tx.index;
    chi = t ? max(chi, ch) : ch;
  }
  const int side = static_cast<int>(d.K) + 3, tr = rhi - rlo + 1, tc = chi - clo + 1;
  extents[cell] = tr > side || tc > side ? make_int4(0, 0, 0, 0) : make_int4(rlo, clo, tr, tc);
}

// dots[cell, r, q] = g[cell, :] . F[r0 + r, c0 + q, :] for every tile pixel (r < tr, q < tc) of every
// cell: pixel-major, so that each feature is read once. A block: source row u, `cols` columns from
// v0, staged in shared memory ([cols][fstride], fstride odd for float: conflict-free); then the
// cells whose tiles cover any of them are listed (kDotList candidates per round), and each thread
// dots one (cell, pixel) pair: the pairs are numbered over each cell's overlap with the block's
// columns (prefix sums), so consecutive threads mostly share a cell (g read through L1 as a
// broadcast) and none idles on a column off the cell's tile.
// kRoundBf16 (float): the features rounded to bfloat16 as they are staged (the values the bf16
// forward reads from its copy; each feature is read once here, so no copy is made).
template <typename T, bool kRoundBf16>
__global__ void __launch_bounds__(kMaxThreads) tile_dots_kernel(const T* __restrict__ g, const T* __restrict__ F,
                                                                const int4* __restrict__ extents, WindowDims d,
                                                                int cols, int fstride, T* __restrict__ dots) {
  extern __shared__ __align__(16) unsigned char dot_smem[];
  T* Fs = reinterpret_cast<T*>(dot_smem);
  __shared__ int list[kDotList];
  __shared__ int start[kDotList + 1];  // the listed cells' first pair; start[n] = the pairs
  __shared__ int count;
  const int u = blockIdx.y, v0 = blockIdx.x * cols;
  const int ncols = min(cols, static_cast<int>(d.W) - v0);
  const int C = static_cast<int>(d.C), side = static_cast<int>(d.K) + 3, area = side * side;
  const T* src = F + (static_cast<int64_t>(u) * d.W + v0) * C;  // ncols * C contiguous values
  for (int t = threadIdx.x; t < ncols * C; t += blockDim.x) {
    T f = src[t];
    if constexpr (kRoundBf16) f = __bfloat162float(__float2bfloat16(f));  // as the bfloat16 copy holds it
    Fs[(t / C) * fstride + t % C] = f;
  }
  const int64_t cells = d.J * d.FH * d.FW;
  for (int64_t round = 0; round < cells; round += kDotList) {
    if (threadIdx.x == 0) count = 0;
    __syncthreads();  // (the first round: also the staged features)
    for (int k = threadIdx.x; k < kDotList && round + k < cells; k += blockDim.x) {
      const int4 e = extents[round + k];
      if (u >= e.x && u < e.x + e.z && e.y < v0 + ncols && e.y + e.w > v0)
        list[atomicAdd(&count, 1)] = static_cast<int>(round + k);
    }
    __syncthreads();
    const int n = count;
    // pairs = (listed cell, one of its tile columns among the block's): an exclusive scan of the
    // overlaps' widths by the first warp, so that no thread idles on a column off the tile
    if (threadIdx.x < 32) {
      int carry = 0;
      for (int base = 0; base < n; base += 32) {
        const int e = base + static_cast<int>(threadIdx.x);
        int width = 0;
        if (e < n) {
          const int4 x = extents[list[e]];
          width = min(v0 + ncols, x.y + x.w) - max(v0, x.y);
        }
        int incl = width;
        for (int o = 1; o < 32; o <<= 1) {
          const int up = __shfl_up_sync(cuda::kFullMask, incl, o);
          if (static_cast<int>(threadIdx.x) >= o) incl += up;
        }
        if (e < n) start[e] = carry + incl - width;
        carry += __shfl_sync(cuda::kFullMask, incl, 31);
      }
      if (threadIdx.x == 0) start[n] = carry;
    }
    __syncthreads();
    const int pairs = start[n];
    for (int pair = threadIdx.x; pair < pairs; pair += blockDim.x) {
      int lo = 0, hi = n;  // start[lo] <= pair < start[hi]
      while (hi - lo > 1) {
        const int mid = (lo + hi) >> 1;
        if (start[mid] <= pair) lo = mid; else hi = mid;
      }
      const int cell = list[lo];
      const int4 e = extents[cell];
      const int q = max(v0, e.y) - v0 + (pair - start[lo]);  // the block's column
      const int dc = v0 + q - e.y;                            // the tile's column
      const T* gc = g + static_cast<int64_t>(cell) * C;
      const T* f = Fs + q * fstride;
      T a0 = 0, a1 = 0, a2 = 0, a3 = 0;  // four chains: the loads overlap
      int c = 0;
      for (; c + 4 <= C; c += 4) {
        a0 += gc[c] * f[c];
        a1 += gc[c + 1] * f[c + 1];
        a2 += gc[c + 2] * f[c + 2];
        a3 += gc[c + 3] * f[c + 3];
      }
      for (; c < C; ++c) a0 += gc[c] * f[c];
      dots[static_cast<int64_t>(cell) * area + (u - e.x) * side + dc] = (a0 + a1) + (a2 + a3);
    }
    __syncthreads();  // the list is rewritten next round
  }
}

// grad_features as grad_features_kernel computes it, with fewer instructions per multiply-add: the
// covering cells are listed kGatherList at a time over all jitters, and their tiles' values at the
// block's kPixelsPerBlock pixels (0 off the tile) are staged in shared memory first, so that the
// per-channel loop reads them as a broadcast without bounds tests.
template <typename T>
__global__ void __launch_bounds__(kMaxThreads) grad_features_staged_kernel(const T* __restrict__ g,
                                                                           const T* __restrict__ tiles,
                                                                           const int32_t* __restrict__ origins,
                                                                           WindowDims d, T* __restrict__ gF) {
  __shared__ int list[kGatherList];
  __shared__ __align__(16) T stage[kGatherList * kPixelsPerBlock];
  __shared__ int count;
  const int u = blockIdx.y, v0 = blockIdx.x * kPixelsPerBlock;
  const int side = static_cast<int>(d.K) + 3, area = side * side;
  const int64_t cells = d.J * d.FH * d.FW;
  for (int64_t cbase = 0; cbase < d.C; cbase += blockDim.x) {
    const int64_t c = cbase + threadIdx.x;
    T acc[kPixelsPerBlock];
#pragma unroll
    for (int q = 0; q < kPixelsPerBlock; ++q) acc[q] = T(0);
    for (int64_t round = 0; round < cells; round += kGatherList) {
      if (threadIdx.x == 0) count = 0;
      __syncthreads();
      for (int k = threadIdx.x; k < kGatherList && round + k < cells; k += blockDim.x) {
        const int64_t cell = round + k;
        const int r0 = origins[cell * 2], c0 = origins[cell * 2 + 1];
        if (u >= r0 && u < r0 + side && c0 < v0 + kPixelsPerBlock && c0 + side > v0)
          list[atomicAdd(&count, 1)] = static_cast<int>(cell);
      }
      __syncthreads();
      const int n = count;
      for (int t = threadIdx.x; t < n * kPixelsPerBlock; t += blockDim.x) {
        const int64_t cell = list[t / kPixelsPerBlock];
        const int r0 = origins[cell * 2], c0 = origins[cell * 2 + 1];
        const int dv = v0 + t % kPixelsPerBlock - c0;
        stage[t] = dv >= 0 && dv < side ? tiles[cell * area + (u - r0) * side + dv] : T(0);
      }
      __syncthreads();
      if (c < d.C)
        for (int e = 0; e < n; ++e) {
          const T gval = g[static_cast<int64_t>(list[e]) * d.C + c];
          const T* sv = stage + e * kPixelsPerBlock;
#pragma unroll
          for (int q = 0; q < kPixelsPerBlock; ++q) acc[q] += sv[q] * gval;
        }
      __syncthreads();  // list and stage are rewritten next round
    }
    if (c < d.C)
#pragma unroll
      for (int q = 0; q < kPixelsPerBlock; ++q)
        if (v0 + q < d.W) gF[(static_cast<int64_t>(u) * d.W + v0 + q) * d.C + c] = acc[q];
  }
}

// grad_features[u, v0 + q, c] = sum over cells whose tile covers the pixel of tile value * g[cell, c].
// A block: one source row u, kPixelsPerBlock columns, threads over channels; the covering cells
// of each jitter are listed in shared memory first (rows and columns tested from the origins).
template <typename T>
__global__ void __launch_bounds__(kMaxThreads) grad_features_kernel(const T* __restrict__ g,
                                                                    const T* __restrict__ tiles,
                                                                    const int32_t* __restrict__ origins,
                                                                    WindowDims d, T* __restrict__ gF) {
  __shared__ int list[kMaxThreads];
  __shared__ int count;
  const int u = blockIdx.y, v0 = blockIdx.x * kPixelsPerBlock;
  const int side = static_cast<int>(d.K) + 3, area = side * side;
  const int64_t cells_per_jitter = d.FH * d.FW;
  for (int64_t cbase = 0; cbase < d.C; cbase += blockDim.x) {
    const int64_t c = cbase + threadIdx.x;
    T acc[kPixelsPerBlock];
#pragma unroll
    for (int q = 0; q < kPixelsPerBlock; ++q) acc[q] = T(0);
    for (int64_t j = 0; j < d.J; ++j)
      for (int64_t chunk = 0; chunk < cells_per_jitter; chunk += blockDim.x) {
        if (threadIdx.x == 0) count = 0;
        __syncthreads();
        const int64_t local = chunk + threadIdx.x;
        if (local < cells_per_jitter) {
          const int64_t cell = j * cells_per_jitter + local;
          const int r0 = origins[cell * 2], c0 = origins[cell * 2 + 1];
          if (u >= r0 && u < r0 + side && c0 < v0 + kPixelsPerBlock && c0 + side > v0)
            list[atomicAdd(&count, 1)] = static_cast<int>(cell);
        }
        __syncthreads();
        const int n = count;
        if (c < d.C)
          for (int e = 0; e < n; ++e) {
            const int64_t cell = list[e];
            const int r0 = origins[cell * 2], c0 = origins[cell * 2 + 1];
            const T gval = g[cell * d.C + c];
            const T* trow = tiles + cell * area + (u - r0) * side;
#pragma unroll
            for (int q = 0; q < kPixelsPerBlock; ++q) {
              const int dv = v0 + q - c0;
              if (dv >= 0 && dv < side) acc[q] += trow[dv] * gval;
            }
          }
        __syncthreads();
      }
    if (c < d.C)
#pragma unroll
      for (int q = 0; q < kPixelsPerBlock; ++q)
        if (v0 + q < d.W) gF[(static_cast<int64_t>(u) * d.W + v0 + q) * d.C + c] = acc[q];
  }
}

// Threads per block: the channels rounded up to warps, 64 to 256.
inline int threads_for(int64_t C) {
  const int64_t t = (C + 31) / 32 * 32;
  return static_cast<int>(t < 64 ? 64 : (t > kMaxThreads ? kMaxThreads : t));
}

}  // namespace

// Staged columns per tile_dots block and the padded row stride of the staged features (elements).
inline void dot_staging(int64_t C, size_t elem, int* cols, int* fstride) {
  *fstride = static_cast<int>(elem == 4 ? (C | 1) : C);
  const int64_t fit = kDotStageBytes / (static_cast<int64_t>(*fstride) * static_cast<int64_t>(elem));
  *cols = static_cast<int>(fit < kDotCols ? fit : kDotCols);
}

template <typename scalar_t>
void launch_window_forward(const scalar_t* features, const scalar_t* logit_map, const scalar_t* coord_y,
                           const scalar_t* coord_x, const scalar_t* w, const scalar_t* b, const scalar_t* mask,
                           WindowDims d, int variant, const void* features_bf16, scalar_t* out, scalar_t* attn,
                           void* stream) {
  const int64_t cells = d.J * d.FH * d.FW;
  if (cells == 0) return;
  const auto st = static_cast<cudaStream_t>(stream);
  const int threads = threads_for(d.C);
  if (!uses_grouped_forward(variant)) {
    forward_kernel<scalar_t, scalar_t><<<static_cast<unsigned>(cells), threads, 0, st>>>(
        features, logit_map, coord_y, coord_x, w, b, mask, d, out, attn);
    return;
  }
  constexpr int G = kForwardGroup<scalar_t>;
  const unsigned blocks = static_cast<unsigned>(d.J * d.FH * ((d.FW + G - 1) / G));
  if constexpr (std::is_same<scalar_t, float>::value) {
    if (uses_bf16_features(variant)) {
      forward_grouped_kernel<float, __nv_bfloat16, G><<<blocks, threads, 0, st>>>(
          static_cast<const __nv_bfloat16*>(features_bf16), logit_map, coord_y, coord_x, w, b, mask, d, out, attn);
      return;
    }
  }
  forward_grouped_kernel<scalar_t, scalar_t, G><<<blocks, threads, 0, st>>>(features, logit_map, coord_y, coord_x, w,
                                                                           b, mask, d, out, attn);
}

template <typename scalar_t>
void launch_window_backward_cells(const scalar_t* grad_out, const scalar_t* features, const scalar_t* logit_map,
                                  const scalar_t* coord_y, const scalar_t* coord_x, const scalar_t* w,
                                  const scalar_t* mask, const scalar_t* attn, WindowDims d, int variant,
                                  int32_t* extents, scalar_t* dots, scalar_t* gz,
                                  scalar_t* gz_logit, scalar_t* grad_logit_map, scalar_t* tiles,
                                  int32_t* origins, void* stream) {
  const int64_t cells = d.J * d.FH * d.FW;
  if (cells == 0) return;
  const auto st = static_cast<cudaStream_t>(stream);
  const unsigned blocks = static_cast<unsigned>(cells);
  if (variant == kBaseline) {
    backward_cells_kernel<scalar_t, false, false><<<blocks, kMaxThreads, 0, st>>>(
        grad_out, features, logit_map, coord_y, coord_x, w, mask, attn, nullptr, d, gz, gz_logit, grad_logit_map,
        tiles, origins);
    return;
  }
  if (variant == kSharedScatter) {
    backward_cells_kernel<scalar_t, true, false><<<blocks, kMaxThreads, 0, st>>>(
        grad_out, features, logit_map, coord_y, coord_x, w, mask, attn, nullptr, d, gz, gz_logit, grad_logit_map,
        tiles, origins);
    return;
  }
  // pixel_dots and after: extents, the dots pixel-major, then the cells from the dots
  int4* ext = reinterpret_cast<int4*>(extents);
  cell_extents_kernel<scalar_t><<<static_cast<unsigned>((cells + 255) / 256), 256, 0, st>>>(coord_y, coord_x, d, ext);
  int cols = 0, fstride = 0;
  dot_staging(d.C, sizeof(scalar_t), &cols, &fstride);
  const dim3 grid(static_cast<unsigned>((d.W + cols - 1) / cols), static_cast<unsigned>(d.H));
  const size_t smem = static_cast<size_t>(cols) * fstride * sizeof(scalar_t);
  if (uses_bf16_features(variant) && std::is_same<scalar_t, float>::value)
    tile_dots_kernel<scalar_t, true><<<grid, kMaxThreads, smem, st>>>(grad_out, features, ext, d, cols, fstride, dots);
  else
    tile_dots_kernel<scalar_t, false><<<grid, kMaxThreads, smem, st>>>(grad_out, features, ext, d, cols, fstride,
                                                                      dots);
  backward_cells_kernel<scalar_t, true, true><<<blocks, kMaxThreads, 0, st>>>(
      grad_out, features, logit_map, coord_y, coord_x, w, mask, attn, dots, d, gz, gz_logit, grad_logit_map, tiles,
      origins);
}

template <typename scalar_t>
void launch_window_grad_features(const scalar_t* grad_out, const scalar_t* tiles, const int32_t* origins,
                                 WindowDims d, int variant, scalar_t* grad_features, void* stream) {
  if (d.H * d.W * d.C == 0) return;
  const dim3 grid(static_cast<unsigned>((d.W + kPixelsPerBlock - 1) / kPixelsPerBlock), static_cast<unsigned>(d.H));
  const auto st = static_cast<cudaStream_t>(stream);
  if (variant >= kStagedTiles)
    grad_features_staged_kernel<scalar_t><<<grid, threads_for(d.C), 0, st>>>(grad_out, tiles, origins, d,
                                                                             grad_features);
  else
    grad_features_kernel<scalar_t><<<grid, threads_for(d.C), 0, st>>>(grad_out, tiles, origins, d, grad_features);
}

#define TIGER_INSTANTIATE(T)                                                                                    \
  template void launch_window_forward<T>(const T*, const T*, const T*, const T*, const T*, const T*, const T*,  \
                                         WindowDims, int, const void*, T*, T*, void*);                          \
  template void launch_window_backward_cells<T>(const T*, const T*, const T*, const T*, const T*, const T*,     \
                                                const T*, const T*, WindowDims, int, int32_t*, T*, T*, T*, T*,   \
                                                T*, int32_t*, void*);                                            \
  template void launch_window_grad_features<T>(const T*, const T*, const int32_t*, WindowDims, int, T*, void*);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace featup
}  // namespace tiger
