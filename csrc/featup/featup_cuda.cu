// CUDA kernels of tiger::jittered_window_attention (raw pointers, no torch headers).
//
// One block per cell (jitter j, window row i, window column l) computes the window's bilinear
// taps, its softmax, and the cell's source tile: the attention pushed through the bilinear
// weights onto the (at most (K+3)^2) source pixels that the window reads (built separably in a
// fixed order). The output is then a dot product of the tile with the features (channels last,
// so the threads of a block read neighbouring channels).
//
// Backward: the cells' tiles and origins first (no features read); then, per source pixel,
// D = grad_out[cell] . features[pixel] for every cell whose tile covers the pixel (each pixel's
// features read once, not once per covering cell); then per cell the softmax backward from D.
// The features' gradient is gathered per source pixel from the tiles of the cells that cover it
// (the covering cells found per window row and column, summed in index order), and so is the
// logit map's, from per-cell tiles of its coefficients: no atomics, the same result on every run.
#include <cuda_runtime.h>
#include <math.h>

#include "common/cuda_helpers.cuh"
#include "featup/featup.h"
#include "featup/featup_math.h"

namespace tiger {
namespace featup {
namespace {

constexpr int kMaxTile = kMaxKernel + 3;  // a window of K rows reads at most K + 2 source rows
constexpr int kMaxThreads = 256;
constexpr int kPixelsPerBlock = 16;       // grad_features: source pixels of one row per block
constexpr int kDotPixels = 32;            // pixel_dots: source pixels of one row per block (about
                                          // 2 x 3 covering cells per jitter: ~200 dot products)

template <typename T>
struct CellShared {
  Tap<T> ty[kMaxKernel], tx[kMaxKernel];
  T attn[kMaxKernel * kMaxKernel];
  T buf[kMaxKernel * kMaxKernel];
  T tile[kMaxTile * kMaxTile];
  T cols[kMaxKernel * kMaxTile];  // build_tile's first stage: [window row][tile column]
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

// s.tile = values [K*K] per window pixel (the attention, or the logit gradient's coefficients)
// pushed through the bilinear weights (ends synchronised; values may live in shared memory,
// written before the call by any thread), separably and
// in a fixed order: first along columns (one thread per window row walks its pixels in order),
// then along rows (one thread per tile column walks the window rows in order). No two threads
// add to one entry: the same tile on every run (shared-memory atomics would add in any order).
template <typename T>
__device__ void build_tile(const WindowDims& d, CellShared<T>& s, const T* values) {
  const int K = static_cast<int>(d.K), side = K + 3;
  for (int t = threadIdx.x; t < side * side; t += blockDim.x) s.tile[t] = T(0);
  for (int t = threadIdx.x; t < K * side; t += blockDim.x) s.cols[t] = T(0);
  __syncthreads();
  if (!s.overflow) {  // the same in every thread
    for (int py = threadIdx.x; py < K; py += blockDim.x) {
      T* row = s.cols + py * side;
      for (int px = 0; px < K; ++px) {
        const Tap<T>& tx = s.tx[px];
        const T a = values[py * K + px];
        const int q = tx.index - s.c0;
        row[q] += (T(1) - tx.frac) * a;
        if (tx.second) row[q + 1] += tx.frac * a;
      }
    }
    __syncthreads();
    for (int q = threadIdx.x; q < side; q += blockDim.x)
      for (int py = 0; py < K; ++py) {
        const Tap<T>& ty = s.ty[py];
        const T v = s.cols[py * side + q];
        const int r = ty.index - s.r0;
        s.tile[r * side + q] += (T(1) - ty.frac) * v;
        if (ty.second) s.tile[(r + 1) * side + q] += ty.frac * v;
      }
  }
  __syncthreads();
}

template <typename T>
__global__ void __launch_bounds__(kMaxThreads) forward_kernel(const T* __restrict__ F, const T* __restrict__ logit_map,
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
  build_tile(d, s, s.attn);
  for (int64_t c = threadIdx.x; c < d.C; c += blockDim.x) {
    T acc = 0;
    if (s.overflow) {
      acc = T(NAN);
    } else {
      for (int r = 0; r < s.tr; ++r) {
        const T* row = F + ((s.r0 + r) * d.W + s.c0) * d.C + c;
        const T* trow = s.tile + r * side;
        for (int q = 0; q < s.tc; ++q) acc += trow[q] * row[q * d.C];
      }
    }
    out[cell * d.C + c] = acc;
  }
}

// The cell's source tile (the attention pushed through the bilinear weights, for the features'
// gradient) and its origin (for every kernel below). Reads no features.
template <typename T>
__global__ void __launch_bounds__(kMaxThreads) cell_tiles_kernel(const T* __restrict__ cy, const T* __restrict__ cx,
                                                                 const T* __restrict__ attn, WindowDims d,
                                                                 T* __restrict__ tiles, int32_t* __restrict__ origins) {
  __shared__ CellShared<T> s;
  const int64_t cell = blockIdx.x;
  const int KK = static_cast<int>(d.K * d.K), side = static_cast<int>(d.K) + 3;
  load_cell(cy, cx, d, cell, s);
  for (int p = threadIdx.x; p < KK; p += blockDim.x) s.attn[p] = attn[cell * KK + p];
  build_tile(d, s, s.attn);  // (synchronises before reading s.attn)
  for (int t = threadIdx.x; t < side * side; t += blockDim.x) tiles[cell * side * side + t] = s.tile[t];
  if (threadIdx.x == 0) {
    origins[cell * 2] = s.r0;
    origins[cell * 2 + 1] = s.c0;
  }
}

template <typename T>
__global__ void __launch_bounds__(kMaxThreads) backward_cells_kernel(
    const T* __restrict__ dots, const T* __restrict__ logit_map, const T* __restrict__ cy, const T* __restrict__ cx,
    const T* __restrict__ w, const T* __restrict__ mask, const T* __restrict__ attn, WindowDims d,
    T* __restrict__ gz_out, T* __restrict__ gzl_out, T* __restrict__ logit_tiles) {
  __shared__ CellShared<T> s;
  const int64_t cell = blockIdx.x;
  const int K = static_cast<int>(d.K), KK = K * K, side = K + 3;
  load_cell(cy, cx, d, cell, s);
  for (int p = threadIdx.x; p < KK; p += blockDim.x) s.attn[p] = attn[cell * KK + p];
  // s.tile = D: the output gradient dotted with the features at every tile pixel (pixel_dots_kernel)
  if (!s.overflow)
    for (int t = threadIdx.x; t < s.tr * s.tc; t += blockDim.x) {
      const int r = t / s.tc, q = t - r * s.tc;
      s.tile[r * side + q] = dots[cell * side * side + r * side + q];
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
  dot = block_reduce<T, false>(dot, s.red);
  const T m = mask[cell];
  for (int p = threadIdx.x; p < KK; p += blockDim.x) {
    const T gz = s.attn[p] * (s.buf[p] - dot);
    gz_out[cell * KK + p] = gz;
    gzl_out[cell * KK + p] = gz * m * bilinear(logit_map, d.W, s.ty[p / K], s.tx[p % K]);
    s.buf[p] = gz * m * w[p];  // the logit map's gradient at window pixel p (this thread's entry)
  }
  // pushed through the bilinear weights onto the cell's tile, gathered per source pixel later
  build_tile(d, s, s.buf);
  for (int t = threadIdx.x; t < side * side; t += blockDim.x) logit_tiles[cell * side * side + t] = s.tile[t];
}

// Appends, in thread order, the values of the threads whose pred is true to list[count ...];
// returns the new count (all threads call it; blockDim.x a multiple of 32; ends synchronised).
// A ballot and the warps' counts give each entry its place: the order does not depend on timing.
__device__ int ordered_append(bool pred, int value, int* list, int count, int* warp_counts) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  const unsigned ballot = __ballot_sync(cuda::kFullMask, pred);
  if (lane == 0) warp_counts[warp] = __popc(ballot);
  __syncthreads();
  int offset = count, total = count;
  for (int k = 0; k < warps; ++k) {
    if (k < warp) offset += warp_counts[k];
    total += warp_counts[k];
  }
  if (pred) list[offset + __popc(ballot & ((1u << lane) - 1u))] = value;
  __syncthreads();
  return total;
}

// D[cell, tile pixel] = grad_out[cell, :] . features[pixel, :] for every cell whose tile covers the
// pixel. A block: one source row u, kDotPixels columns (the covering cells listed as in
// grad_features_kernel); a thread per (covering cell, column), consecutive threads on cells of
// one column (its features read once per warp, broadcast). Every source pixel's features are read
// from memory by one block, instead of by every cell whose window reads it (about 4 per jitter).
// Each D entry is written by one thread, summed over the channels in order.
template <typename T>
__global__ void __launch_bounds__(kMaxThreads) pixel_dots_kernel(const T* __restrict__ g, const T* __restrict__ F,
                                                                 const int32_t* __restrict__ origins, WindowDims d,
                                                                 T* __restrict__ dots) {
  __shared__ int rows[kMaxThreads], row_origin[kMaxThreads], cols[kMaxThreads], col_origin[kMaxThreads];
  __shared__ int warp_counts[kMaxThreads / 32];
  const int u = blockIdx.y, v0 = blockIdx.x * kDotPixels;
  const int side = static_cast<int>(d.K) + 3, area = side * side;
  const int64_t cells_per_jitter = d.FH * d.FW, C = d.C;
  for (int64_t j = 0; j < d.J; ++j) {
    const int32_t* first = origins + j * cells_per_jitter * 2;  // cell (j, 0, 0)
    for (int64_t ibase = 0; ibase < d.FH; ibase += blockDim.x) {
      const int64_t i = ibase + threadIdx.x;
      int r0 = 0;
      bool covers = false;
      if (i < d.FH) {
        r0 = first[i * d.FW * 2];
        covers = u >= r0 && u < r0 + side;
      }
      const int n_rows = ordered_append(covers, static_cast<int>(i), rows, 0, warp_counts);
      if (covers) row_origin[threadIdx.x] = r0;  // slot i - ibase
      __syncthreads();
      if (n_rows == 0) continue;  // the same count in every thread
      for (int64_t lbase = 0; lbase < d.FW; lbase += blockDim.x) {
        const int64_t l = lbase + threadIdx.x;
        int c0 = 0;
        bool reaches = false;
        if (l < d.FW) {
          c0 = first[l * 2 + 1];
          reaches = c0 < v0 + kDotPixels && c0 + side > v0;
        }
        const int n_cols = ordered_append(reaches, static_cast<int>(l), cols, 0, warp_counts);
        if (reaches) col_origin[threadIdx.x] = c0;  // slot l - lbase
        __syncthreads();
        const int pairs = n_rows * n_cols;
        for (int item = threadIdx.x; item < pairs * kDotPixels; item += blockDim.x) {
          const int q = item / pairs, pair = item - q * pairs;
          const int a = pair / n_cols, e = pair - a * n_cols;
          const int64_t i_cell = rows[a], l_cell = cols[e];
          const int dv = v0 + q - col_origin[l_cell - lbase];
          if (v0 + q >= d.W || dv < 0 || dv >= side) continue;
          const int dr = u - row_origin[i_cell - ibase];
          const int64_t cell = j * cells_per_jitter + i_cell * d.FW + l_cell;
          const T* gc = g + cell * C;
          const T* f = F + (static_cast<int64_t>(u) * d.W + v0 + q) * C;
          T acc = 0;
          for (int64_t c = 0; c < C; ++c) acc += gc[c] * f[c];
          dots[cell * area + dr * side + dv] = acc;
        }
        __syncthreads();
      }
    }
  }
}

// grad_features[u, v0 + q, c] = sum over cells whose tile covers the pixel of tile value * g[cell, c],
// and grad_logit_map[u, v0 + q] = the same sum over the cells' logit tiles (as channel C).
// A block: one source row u, kPixelsPerBlock columns, threads over channels. A cell's tile origin
// row depends on its jitter and window row only, its origin column on its jitter and window
// column only: per jitter the block lists the window rows whose tiles cover row u and the window
// columns whose tiles reach its columns (FH + FW tests instead of FH * FW), in index order, and
// sums over their pairs in that order (no atomics: the same result on every run).
template <typename T>
__global__ void __launch_bounds__(kMaxThreads) grad_features_kernel(const T* __restrict__ g,
                                                                    const T* __restrict__ tiles,
                                                                    const T* __restrict__ logit_tiles,
                                                                    const int32_t* __restrict__ origins,
                                                                    WindowDims d, T* __restrict__ gF,
                                                                    T* __restrict__ gL) {
  __shared__ int rows[kMaxThreads], row_origin[kMaxThreads], cols[kMaxThreads], col_origin[kMaxThreads];
  __shared__ int warp_counts[kMaxThreads / 32];
  const int u = blockIdx.y, v0 = blockIdx.x * kPixelsPerBlock;
  const int side = static_cast<int>(d.K) + 3, area = side * side;
  const int64_t cells_per_jitter = d.FH * d.FW;
  for (int64_t cbase = 0; cbase <= d.C; cbase += blockDim.x) {  // channels, then the logit (c = C)
    const int64_t c = cbase + threadIdx.x;
    T acc[kPixelsPerBlock];
#pragma unroll
    for (int q = 0; q < kPixelsPerBlock; ++q) acc[q] = T(0);
    for (int64_t j = 0; j < d.J; ++j) {
      const int32_t* first = origins + j * cells_per_jitter * 2;  // cell (j, 0, 0)
      for (int64_t ibase = 0; ibase < d.FH; ibase += blockDim.x) {
        const int64_t i = ibase + threadIdx.x;
        int r0 = 0;
        bool covers = false;
        if (i < d.FH) {
          r0 = first[i * d.FW * 2];
          covers = u >= r0 && u < r0 + side;
        }
        const int n_rows = ordered_append(covers, static_cast<int>(i), rows, 0, warp_counts);
        if (covers) row_origin[threadIdx.x] = r0;  // slot i - ibase
        __syncthreads();
        if (n_rows == 0) continue;  // the same count in every thread
        for (int64_t lbase = 0; lbase < d.FW; lbase += blockDim.x) {
          const int64_t l = lbase + threadIdx.x;
          int c0 = 0;
          bool reaches = false;
          if (l < d.FW) {
            c0 = first[l * 2 + 1];
            reaches = c0 < v0 + kPixelsPerBlock && c0 + side > v0;
          }
          const int n_cols = ordered_append(reaches, static_cast<int>(l), cols, 0, warp_counts);
          if (reaches) col_origin[threadIdx.x] = c0;  // slot l - lbase
          __syncthreads();
          if (c <= d.C)
            for (int a = 0; a < n_rows; ++a) {
              const int64_t i_cell = rows[a];
              const int dr = u - row_origin[i_cell - ibase];
              for (int e = 0; e < n_cols; ++e) {
                const int64_t l_cell = cols[e];
                const int c0e = col_origin[l_cell - lbase];
                const int64_t cell = j * cells_per_jitter + i_cell * d.FW + l_cell;
                const bool logit = c == d.C;
                const T gval = logit ? T(1) : g[cell * d.C + c];
                const T* trow = (logit ? logit_tiles : tiles) + cell * area + dr * side;
#pragma unroll
                for (int q = 0; q < kPixelsPerBlock; ++q) {
                  const int dv = v0 + q - c0e;
                  if (dv >= 0 && dv < side) acc[q] += trow[dv] * gval;
                }
              }
            }
          __syncthreads();
        }
      }
    }
    if (c < d.C) {
#pragma unroll
      for (int q = 0; q < kPixelsPerBlock; ++q)
        if (v0 + q < d.W) gF[(static_cast<int64_t>(u) * d.W + v0 + q) * d.C + c] = acc[q];
    } else if (c == d.C) {
#pragma unroll
      for (int q = 0; q < kPixelsPerBlock; ++q)
        if (v0 + q < d.W) gL[static_cast<int64_t>(u) * d.W + v0 + q] = acc[q];
    }
  }
}

// Threads per block: the channels rounded up to warps, 64 to 256.
inline int threads_for(int64_t C) {
  const int64_t t = (C + 31) / 32 * 32;
  return static_cast<int>(t < 64 ? 64 : (t > kMaxThreads ? kMaxThreads : t));
}

}  // namespace

template <typename scalar_t>
void launch_window_forward(const scalar_t* features, const scalar_t* logit_map, const scalar_t* coord_y,
                           const scalar_t* coord_x, const scalar_t* w, const scalar_t* b, const scalar_t* mask,
                           WindowDims d, scalar_t* out, scalar_t* attn, void* stream) {
  const int64_t cells = d.J * d.FH * d.FW;
  if (cells == 0) return;
  forward_kernel<scalar_t><<<static_cast<unsigned>(cells), threads_for(d.C), 0, static_cast<cudaStream_t>(stream)>>>(
      features, logit_map, coord_y, coord_x, w, b, mask, d, out, attn);
}

template <typename scalar_t>
void launch_window_backward_cells(const scalar_t* grad_out, const scalar_t* features, const scalar_t* logit_map,
                                  const scalar_t* coord_y, const scalar_t* coord_x, const scalar_t* w,
                                  const scalar_t* mask, const scalar_t* attn, WindowDims d, scalar_t* gz,
                                  scalar_t* gz_logit, scalar_t* logit_tiles, scalar_t* dots, scalar_t* tiles,
                                  int32_t* origins, void* stream) {
  const int64_t cells = d.J * d.FH * d.FW;
  if (cells == 0) return;
  auto st = static_cast<cudaStream_t>(stream);
  cell_tiles_kernel<scalar_t><<<static_cast<unsigned>(cells), kMaxThreads, 0, st>>>(coord_y, coord_x, attn, d, tiles,
                                                                                   origins);
  const dim3 rows(static_cast<unsigned>((d.W + kDotPixels - 1) / kDotPixels), static_cast<unsigned>(d.H));
  pixel_dots_kernel<scalar_t><<<rows, kMaxThreads, 0, st>>>(grad_out, features, origins, d, dots);
  backward_cells_kernel<scalar_t><<<static_cast<unsigned>(cells), kMaxThreads, 0, st>>>(
      dots, logit_map, coord_y, coord_x, w, mask, attn, d, gz, gz_logit, logit_tiles);
}

template <typename scalar_t>
void launch_window_grad_features(const scalar_t* grad_out, const scalar_t* tiles, const scalar_t* logit_tiles,
                                 const int32_t* origins, WindowDims d, scalar_t* grad_features,
                                 scalar_t* grad_logit_map, void* stream) {
  if (d.H * d.W == 0) return;
  const dim3 grid(static_cast<unsigned>((d.W + kPixelsPerBlock - 1) / kPixelsPerBlock), static_cast<unsigned>(d.H));
  grad_features_kernel<scalar_t><<<grid, threads_for(d.C + 1), 0, static_cast<cudaStream_t>(stream)>>>(
      grad_out, tiles, logit_tiles, origins, d, grad_features, grad_logit_map);
}

#define TIGER_INSTANTIATE(T)                                                                                    \
  template void launch_window_forward<T>(const T*, const T*, const T*, const T*, const T*, const T*, const T*,  \
                                         WindowDims, T*, T*, void*);                                            \
  template void launch_window_backward_cells<T>(const T*, const T*, const T*, const T*, const T*, const T*,     \
                                                const T*, const T*, WindowDims, T*, T*, T*, T*, T*, int32_t*,     \
                                                void*);                                                           \
  template void launch_window_grad_features<T>(const T*, const T*, const T*, const int32_t*, WindowDims, T*, T*, \
                                               void*);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace featup
}  // namespace tiger
