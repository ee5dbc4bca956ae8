#pragma once
// CUDA rasterization kernels (included by the raster_*_cuda.cu files, each of which
// instantiates one op). One block per tile, one thread per pixel (two in the backward where
// pixels_per_thread says so); the tile's Gaussian list is walked in batches of blockDim x
// pixels-per-thread Gaussians staged in shared memory. Channels
// are processed in register blocks of CB (a template parameter): a kernel walks the
// list once per channel block, main blocks of CBM channels then one tail block of CBT,
// so every C runs in one launch and C = 67 costs a 64-block plus a 4-block walk.
// Per-pixel alpha, skipping, termination and gradients follow common/raster_math.h and
// raster_cpu.cpp term by term. With warp_cull (raster.h) each warp walks only the staged entries
// that may reach one of its own pixels (WarpSpan, span_reaches): the same values, fewer steps.
#include <type_traits>

#include "common/cuda_helpers.cuh"
#include "common/raster_math.h"
#include "raster_cuda.h"

namespace tiger {
namespace raster_cuda {

using cuda::kFullMask;

// span_reaches' margin relative to the size of the conic's terms: ~100 float32 roundings.
constexpr double kCullMargin = 1e-5;

// One Gaussian of the current batch, packed so a thread reads it with two 16-byte loads.
template <typename T>
struct alignas(4 * sizeof(T)) SplatGeom {
  T u, v, ca, cb;
  T cc, o, z, qcut;
};

// The block's tile: blockIdx.x over the views' tile grids one after the other (raster.h);
// (tx, ty) its place in its own image.
struct BlockTile {
  int tile, tx, ty;
};

template <typename T>
__device__ __forceinline__ BlockTile block_tile(const RasterLaunch<T>& a) {
  BlockTile b;
  b.tile = a.tile_order ? a.tile_order[blockIdx.x] : int(blockIdx.x);
  const int view_tiles = a.tiles_x * a.tiles_y;
  const int local = b.tile - b.tile / view_tiles * view_tiles;
  b.tx = local % a.tiles_x;
  b.ty = local / a.tiles_x;
  return b;
}

// Index in the stacked [views * H, W] outputs of pixel (px, py) of tile `tile`'s image. Computed
// where it is used rather than kept in registers across the list walk.
template <typename T>
__device__ __forceinline__ int64_t stacked_pixel(const RasterLaunch<T>& a, int tile, int px, int py) {
  const int view = tile / (a.tiles_x * a.tiles_y);
  return (int64_t(view) * a.height + py) * a.width + px;
}

// One thread's pixel: (px, py) in its own image's coordinates (where the Gaussians are
// evaluated; stacked_pixel gives its output index).
struct TilePixel {
  int tile, px, py;
  bool inside;
};

// Where the tile size is a multiple of 8, a warp's 32 pixels are an 8-wide, 4-tall block
// (warps in row-major order over the tile's 8x4 blocks) rather than 32 consecutive pixels of
// row-major order (two rows of a 16-px tile): the same area with a shorter boundary, so fewer
// list entries reach some pixel of the warp (warp_cull) and the warp walks fewer of them. For
// 8-px tiles the two orders are the same. warp_span<1> follows this layout. H100 kernel ms
// (docs/BENCHMARKS.md): fox forward 0.484 -> 0.457, the edit's forward 1.06 -> 1.03 and
// editable backward 1.93 -> 1.81; splats seen edge-on (flat, wide) favour rows: the demo
// tabletop's orbit forward 1.44 -> 1.52. A bounding-box pre-test before span_reaches' rows
// was slower everywhere (fox 0.469, orbit 1.56).
struct WarpBlock {
  int c0, r0;  // the warp's first column and row in its tile
};

__device__ __forceinline__ bool warp_blocks(int tile_size) { return (tile_size & 7) == 0; }

__device__ __forceinline__ WarpBlock warp_block(int tile_size, int warp) {
  const int per_row = tile_size >> 3;  // 8-px blocks across the tile
  return WarpBlock{8 * (warp % per_row), 4 * (warp / per_row)};
}

template <typename T>
__device__ __forceinline__ TilePixel tile_pixel(const RasterLaunch<T>& a) {
  const BlockTile b = block_tile(a);
  TilePixel p;
  p.tile = b.tile;
  const int t = threadIdx.x, ts = a.tile_size;
  int cx = t % ts, cy = t / ts;
  if (warp_blocks(ts)) {
    const WarpBlock w = warp_block(ts, t >> 5);
    cx = w.c0 + (t & 7);
    cy = w.r0 + ((t & 31) >> 3);
  }
  p.px = b.tx * ts + cx;
  p.py = b.ty * ts + cy;
  p.inside = t < ts * ts && p.px < a.width && p.py < a.height;
  return p;
}

// The pixels of one backward thread. PPT = 1: tile_pixel's pixel, as in the forward. PPT = 2
// (16-px tiles, 128 threads): warp w covers rows 4w..4w+3, lane l column l % 16 of rows
// 4w + l / 16 and 4w + 2 + l / 16, so one warp reduction sums a Gaussian's gradient over 64
// pixels instead of 32 (half the shuffles and atomics per pixel), and a Gaussian staged in
// shared memory is read once for two pixels.
template <int PPT>
struct TilePixels {
  int tile;
  int px[PPT], py[PPT];  // in the pixel's own image (stacked_pixel: the output index)
  bool inside[PPT];
};

template <int PPT, typename T>
__device__ __forceinline__ TilePixels<PPT> tile_pixels(const RasterLaunch<T>& a) {
  TilePixels<PPT> p;
  if constexpr (PPT == 1) {
    const TilePixel q = tile_pixel(a);
    p.tile = q.tile;
    p.px[0] = q.px;
    p.py[0] = q.py;
    p.inside[0] = q.inside;
  } else {
    static_assert(PPT == 2, "1 or 2 pixels per thread");
    const BlockTile b = block_tile(a);
    p.tile = b.tile;
    const int t = threadIdx.x, lane = t & 31;
    const int row0 = 4 * (t >> 5) + (lane >> 4);
#pragma unroll
    for (int k = 0; k < 2; ++k) {
      p.px[k] = b.tx * a.tile_size + (lane & 15);
      p.py[k] = b.ty * a.tile_size + row0 + 2 * k;
      p.inside[k] = p.px[k] < a.width && p.py[k] < a.height;
    }
  }
  return p;
}

// The pixel centres of this thread's warp: rows [y0, y0 + rows) of its tile, columns [x0, x1]
// in its image's coordinates (a box around them where a warp holds part of a row). PPT = 1:
// tile_pixel's layout (an 8x4 block a warp where the tile size is a multiple of 8, else
// row-major pixel order); PPT = 2: TilePixels' four rows a warp. A warp beyond its tile's
// pixels gets rows = 0.
template <typename T>
struct WarpSpan {
  T x0, x1, y0;
  int rows;
};

template <int PPT, typename T>
__device__ __forceinline__ WarpSpan<T> warp_span(const RasterLaunch<T>& a) {
  const BlockTile b = block_tile(a);
  const int ts = a.tile_size, w = int(threadIdx.x >> 5);
  int r0, r1, c0 = 0, c1 = ts - 1;
  if constexpr (PPT == 2) {
    r0 = 4 * w;
    r1 = 4 * w + 3;
  } else if (warp_blocks(ts)) {         // tile_pixel's 8x4 block
    const WarpBlock wb = warp_block(ts, w);
    c0 = wb.c0;
    c1 = wb.c0 + 7;
    r0 = wb.r0;
    r1 = 32 * w < ts * ts ? wb.r0 + 3 : wb.r0 - 1;
  } else {
    const int t0 = 32 * w, t1 = 32 * w + 31;
    r0 = t0 / ts;
    r1 = min(t1 / ts, ts - 1);
    if (r1 == r0) c0 = t0 % ts;           // the warp starts inside its only row
    if (t1 / ts == r0) c1 = t1 % ts;      // and ends inside it
  }
  WarpSpan<T> s;
  s.x0 = T(b.tx * ts + c0) + T(0.5);
  s.x1 = T(b.tx * ts + c1) + T(0.5);
  s.y0 = T(b.ty * ts + r0) + T(0.5);
  s.rows = max(r1 - r0 + 1, 0);
  return s;
}

// False only where every pixel centre of the span surely fails the walk's first test,
// q > qcut: per row, the minimum of q over the segment of centres (the conic's minimum along
// the row, clamped to the segment) exceeds qcut by more than its rounding. The walk's own q at
// a pixel is evaluated in another order; the relative margin covers both roundings where the
// terms nearly cancel (elongated Gaussians), and qcut's own margin (cutoff_quadratic) puts
// every contributing pixel below qcut by more than that. A NaN anywhere reaches (the walk's
// test lets NaN through, so the cull must too).
template <typename T>
__device__ __forceinline__ bool span_reaches(const SplatGeom<T>& g, const WarpSpan<T>& s) {
  const T lo = s.x0 - g.u, hi = s.x1 - g.u;
  if (!(g.ca > T(0)) || !(lo <= hi)) return true;
  const T slope = -g.cb / g.ca;
  for (int r = 0; r < s.rows; ++r) {
    const T dy = s.y0 + T(r) - g.v;
    T t = slope * dy;
    t = t < lo ? lo : (t > hi ? hi : t);
    const T cross = T(2) * g.cb * dy, yy = g.cc * dy * dy;
    const T q = fused_multiply_add(fused_multiply_add(g.ca, t, cross), t, yy);
    const T scale = fused_multiply_add(g.ca * t, t, fabs(cross * t)) + yy;
    if (!(q > fused_multiply_add(scale, T(kCullMargin), g.qcut))) return true;
  }
  return false;
}

template <typename T>
__device__ __forceinline__ void load_geom(const RasterLaunch<T>& a, int32_t g, SplatGeom<T>& s) {
  s.u = a.means2d[2 * g];
  s.v = a.means2d[2 * g + 1];
  s.ca = a.conics[3 * g];
  s.cb = a.conics[3 * g + 1];
  s.cc = a.conics[3 * g + 2];
  s.o = a.opacities[g];
  s.z = a.depths ? a.depths[g] : T(0);
  s.qcut = cutoff_quadratic(s.o, a.alpha_threshold);
}

// Float32 rows of C values starting at `base` are all 16-byte aligned (C % 4 == 0 and an
// aligned base): with c0 a multiple of 4, a float4 at row + c0 + 4v lies wholly inside the row
// or wholly past it.
__device__ __forceinline__ bool rows_vectorizable(const float* base, int C) {
  return (C & 3) == 0 && (reinterpret_cast<uintptr_t>(base) & 15) == 0;
}

// Stages colors[ids[b0 + j], c0 : c0 + CB] (zero past C) for j < nb into s_col[j * CB + c].
template <int CB, typename T, typename TC>
__device__ __forceinline__ void load_colors(const TC* colors, const int32_t* ids, int64_t b0,
                                            int nb, int C, int c0, T* s_col) {
  if constexpr (std::is_same<T, float>::value && std::is_same<TC, float>::value && CB % 4 == 0) {
    // 16-byte loads when every row start is 16-byte aligned (c0 is a multiple of 4, and
    // with C % 4 == 0 a vector is either wholly inside the row or wholly past it).
    if ((C & 3) == 0 && (reinterpret_cast<uintptr_t>(colors) & 15) == 0) {
      constexpr int V = CB / 4;
      for (int e = threadIdx.x; e < nb * V; e += blockDim.x) {
        const int j = e / V, c = (e % V) * 4;
        float4 val = make_float4(0.f, 0.f, 0.f, 0.f);
        if (c0 + c < C)
          val = *reinterpret_cast<const float4*>(colors + int64_t(ids[b0 + j]) * C + c0 + c);
        reinterpret_cast<float4*>(s_col)[e] = val;
      }
      return;
    }
  }
  for (int e = threadIdx.x; e < nb * CB; e += blockDim.x) {
    const int j = e / CB, c = e % CB;
    T val = T(0);
    if (c0 + c < C) val = cuda::load_as<T>(colors[int64_t(ids[b0 + j]) * C + c0 + c]);
    s_col[e] = val;
  }
}


// Per-pixel channel rows of an [H, W, C] image: a thread's CB channels lie at pix * C + c0.
// Moved as 16-byte vectors when every row start is 16-byte aligned (rows_vectorizable): a
// warp's access then touches 32 sectors per 4 channels instead of per channel, which at C = 64
// was the cost of the forward's stores and the backward's loads.

// vals[c] = src[pix * C + c0 + c] for c0 + c < C, 0 past C.
template <int CB, typename T>
__device__ __forceinline__ void load_channel_row(const T* src, int64_t pix, int C, int c0,
                                                 T (&vals)[CB]) {
  const T* row = src + pix * C + c0;
  if constexpr (std::is_same<T, float>::value && CB % 4 == 0) {
    if (rows_vectorizable(src, C)) {
#pragma unroll
      for (int v = 0; v < CB / 4; ++v) {
        float4 x = make_float4(0.f, 0.f, 0.f, 0.f);
        if (c0 + 4 * v < C) x = *reinterpret_cast<const float4*>(row + 4 * v);
        vals[4 * v] = x.x;
        vals[4 * v + 1] = x.y;
        vals[4 * v + 2] = x.z;
        vals[4 * v + 3] = x.w;
      }
      return;
    }
  }
#pragma unroll
  for (int c = 0; c < CB; ++c) vals[c] = c0 + c < C ? row[c] : T(0);
}

// dst[pix * C + c0 + c] = vals[c] for c0 + c < C.
template <int CB, typename T>
__device__ __forceinline__ void store_channel_row(T* dst, int64_t pix, int C, int c0,
                                                  const T (&vals)[CB]) {
  T* row = dst + pix * C + c0;
  if constexpr (std::is_same<T, float>::value && CB % 4 == 0) {
    if (rows_vectorizable(dst, C)) {
#pragma unroll
      for (int v = 0; v < CB / 4; ++v)
        if (c0 + 4 * v < C)
          *reinterpret_cast<float4*>(row + 4 * v) =
              make_float4(vals[4 * v], vals[4 * v + 1], vals[4 * v + 2], vals[4 * v + 3]);
      return;
    }
  }
#pragma unroll
  for (int c = 0; c < CB; ++c)
    if (c0 + c < C) row[c] = vals[c];
}

// ----------------------------------------------------------------------------------------
// Forward
// ----------------------------------------------------------------------------------------
template <typename T>
struct ForwardOut {
  const T* bg;
  T *color, *alpha, *depth, *trans;
  int32_t* count;
};

template <int CB, typename T, typename TC>
__device__ __forceinline__ void forward_walk(const RasterLaunch<T>& a, const TC* colors,
                                             const ForwardOut<T>& out, const TilePixel& p, int c0,
                                             bool first, SplatGeom<T>* s_geom, T* s_col) {
  const int C = a.channels;
  const int BS = blockDim.x;
  const int64_t start = a.tile_offsets[p.tile], end = a.tile_offsets[p.tile + 1];
  const T fx = T(p.px) + T(0.5), fy = T(p.py) + T(0.5);
  T acc[CB];
#pragma unroll
  for (int c = 0; c < CB; ++c) acc[c] = T(0);
  T Tr = T(1), accd = T(0);
  int32_t cnt = 0;
  bool done = !p.inside;
  const int lane = threadIdx.x & 31;
  const WarpSpan<T> span = warp_span<1>(a);
  for (int64_t b0 = start; b0 < end; b0 += BS) {
    // Also the barrier that protects the previous batch's shared memory.
    if (__syncthreads_count(done) == BS) break;
    const int nb = int(min(int64_t(BS), end - b0));
    const int32_t rank1 = int32_t(b0 - start) + 1;  // n_contrib of the batch's entry 0 (32-bit adds in the walk)
    if (int(threadIdx.x) < nb) load_geom(a, a.ids[b0 + threadIdx.x], s_geom[threadIdx.x]);
    load_colors<CB>(colors, a.ids, b0, nb, C, c0, s_col);
    __syncthreads();
    // The batch in groups of 32 entries: each lane tests one entry against the warp's pixels
    // (warp_cull), and the warp walks only the entries that may reach one, in list order.
    // Lanes that are done keep voting until the whole warp is.
    for (int g0 = 0; g0 < nb; g0 += 32) {
      if (__all_sync(kFullMask, done)) break;
      const int e = g0 + lane;
      const bool reach = e < nb && (!a.warp_cull || span_reaches(s_geom[e], span));
      uint32_t hits = __ballot_sync(kFullMask, reach);
      if (done) continue;
      while (hits) {
        const int j = g0 + __ffs(hits) - 1;
        hits &= hits - 1;
        const SplatGeom<T> g = s_geom[j];
        const T dx = fx - g.u, dy = fy - g.v;
        const T q = conic_quadratic(g.ca, g.cb, g.cc, dx, dy);
        if (q > g.qcut) continue;
        T gauss;
        bool clamped;
        const T alpha = splat_alpha(g.o, q, a.alpha_max, gauss, clamped);
        if (alpha < a.alpha_threshold) continue;
        const T next_T = Tr * (T(1) - alpha);
        if (next_T < a.t_min) {
          done = true;
          break;
        }
        const T w = alpha * Tr;
        const T* col = s_col + j * CB;
#pragma unroll
        for (int c = 0; c < CB; ++c) acc[c] += w * col[c];
        accd += w * g.z;
        Tr = next_T;
        cnt = rank1 + j;
      }
    }
  }
  if (!p.inside) return;
  const int64_t pix = stacked_pixel(a, p.tile, p.px, p.py);
  if (out.bg) {
#pragma unroll
    for (int c = 0; c < CB; ++c)
      if (c0 + c < C) acc[c] += Tr * out.bg[c0 + c];
  }
  store_channel_row<CB>(out.color, pix, C, c0, acc);
  if (first) {
    out.alpha[pix] = T(1) - Tr;
    out.depth[pix] = accd;
    out.count[pix] = cnt;
    out.trans[pix] = Tr;
  }
}

template <typename T, typename TC, int CBM, int CBT>
__global__ void __launch_bounds__(256) forward_kernel(RasterLaunch<T> a, const TC* colors,
                                                      ForwardOut<T> out, int n_main) {
  extern __shared__ __align__(16) unsigned char smem[];
  SplatGeom<T>* s_geom = reinterpret_cast<SplatGeom<T>*>(smem);
  T* s_col = reinterpret_cast<T*>(s_geom + blockDim.x);
  const TilePixel p = tile_pixel(a);
  int c0 = 0;
  if constexpr (CBM > 0) {
    for (int k = 0; k < n_main; ++k, c0 += CBM) {
      __syncthreads();
      forward_walk<CBM>(a, colors, out, p, c0, k == 0, s_geom, s_col);
    }
  }
  if constexpr (CBT > 0) {
    __syncthreads();
    forward_walk<CBT>(a, colors, out, p, c0, c0 == 0, s_geom, s_col);
  }
}

// ----------------------------------------------------------------------------------------
// Shared by the two backward kernels
// ----------------------------------------------------------------------------------------
template <int PPT, typename T>
__device__ __forceinline__ int block_max_count(const RasterLaunch<T>& a, const int32_t* n_contrib,
                                               const TilePixels<PPT>& p, int* s_max) {
  if (threadIdx.x == 0) *s_max = 0;
  __syncthreads();
  int32_t cnt = 0;
#pragma unroll
  for (int k = 0; k < PPT; ++k)
    if (p.inside[k]) cnt = max(cnt, n_contrib[stacked_pixel(a, p.tile, p.px[k], p.py[k])]);
  if (cnt > 0) atomicMax(s_max, cnt);
  __syncthreads();
  return *s_max;
}

// The list rank of the tile's front-most trainable Gaussian among its first max_cnt entries;
// max_cnt when there is none, 0 when every Gaussian is trainable (a.trainable null). The
// back-to-front walk stops there: the entries in front of it are frozen, and the state a
// trainable Gaussian's gradient needs (transmittance in front, colour and depth behind) comes
// from behind it, so skipping them changes no value. Tiles the edited object does not reach
// skip the walk altogether.
template <typename T>
__device__ __forceinline__ int first_trainable_rank(const RasterLaunch<T>& a, int tile, int max_cnt, int* s_first) {
  if (a.trainable == nullptr) return 0;
  const int64_t start = a.tile_offsets[tile];
  for (int r0 = 0; r0 < max_cnt; r0 += blockDim.x) {  // max_cnt is uniform: every thread loops alike
    const int r = r0 + int(threadIdx.x);
    const bool hit = r < max_cnt && a.trainable[a.ids[start + r]];
    if (__syncthreads_or(hit)) {
      if (threadIdx.x == 0) *s_first = max_cnt;
      __syncthreads();
      if (hit) atomicMin(s_first, r);
      __syncthreads();
      return *s_first;
    }
  }
  return max_cnt;
}

// Adds the block's sum of vals[c] (one per thread) to v_bg_tiles[tile, c0 + c].
template <int CB, typename T>
__device__ __forceinline__ void block_background_grad(T (&vals)[CB], int C, int c0, int tile,
                                                      T* s_bg, T* v_bg_tiles) {
  const int lane = threadIdx.x & 31;
  __syncthreads();
  if (int(threadIdx.x) < CB) s_bg[threadIdx.x] = T(0);
  __syncthreads();
  const T s = cuda::warp_reduce_scatter<CB>(vals, lane);
  if (lane < CB) atomicAdd(&s_bg[lane], s);
  __syncthreads();
  if (int(threadIdx.x) < CB && c0 + int(threadIdx.x) < C)
    v_bg_tiles[int64_t(tile) * C + c0 + threadIdx.x] = s_bg[threadIdx.x];
}

// The per-thread weighted channel sums go in pieces of at most 32 channels, so the temporaries
// stay at 32 registers for any CB.
template <int CB>
constexpr int kWeightedPiece = CB < 32 ? CB : 32;

// f(h, out) for each piece h, out[c] = sum over the thread's pixels k of
// w[k] * vc[k][h * kWeightedPiece<CB> + c].
template <int CB, int PPT, typename T, typename F>
__device__ __forceinline__ void for_each_weighted_piece(const T (&vc)[PPT][CB], const T (&w)[PPT],
                                                        F&& f) {
  constexpr int PIECE = kWeightedPiece<CB>;
#pragma unroll
  for (int h = 0; h < CB / PIECE; ++h) {
    T out[PIECE];
#pragma unroll
    for (int c = 0; c < PIECE; ++c) {
      out[c] = w[0] * vc[0][h * PIECE + c];
#pragma unroll
      for (int k = 1; k < PPT; ++k) out[c] += w[k] * vc[k][h * PIECE + c];
    }
    f(h, out);
  }
}

// v_bg_tiles[tile, c0 + c] += sum over the block's pixels of t * vc[c], piece by piece.
template <int CB, int PPT, typename T>
__device__ __forceinline__ void background_grads(const T (&vc)[PPT][CB], const T (&t)[PPT],
                                                 int C, int c0, int tile, T* s_bg,
                                                 T* v_bg_tiles) {
  constexpr int PIECE = kWeightedPiece<CB>;
  for_each_weighted_piece(vc, t, [&](int h, T (&vals)[PIECE]) {
    block_background_grad<PIECE>(vals, C, c0 + h * PIECE, tile, s_bg, v_bg_tiles);
  });
}

// Adds sum_k w[k] * vc[k][c] of every lane to v_colors[gid, c0 + c], reduced over the warp
// first, piece by piece.
template <int CB, int PPT, typename T>
__device__ __forceinline__ void warp_add_color_grads(const T (&vc)[PPT][CB], const T (&w)[PPT],
                                                     int64_t gid, int C, int c0, int lane,
                                                     T* v_colors) {
  constexpr int PIECE = kWeightedPiece<CB>;
  for_each_weighted_piece(vc, w, [&](int h, T (&gc)[PIECE]) {
    const T sc = cuda::warp_reduce_scatter<PIECE>(gc, lane);
    const int ch = c0 + h * PIECE + lane;
    if (lane < PIECE && ch < C) atomicAdd(&v_colors[gid * C + ch], sc);
  });
}

// Stages the batch entries [b0, b0 + nb) of the tile list: geometry and id per entry, the id
// of a frozen Gaussian (a.trainable) as ~id < 0: the walk updates the pixels' state through it
// but adds no gradient (no reduction, no atomics).
template <typename T>
__device__ __forceinline__ void load_batch_geometry(const RasterLaunch<T>& a, int64_t b0, int nb,
                                                    SplatGeom<T>* s_geom, int32_t* s_id) {
  for (int e = threadIdx.x; e < nb; e += blockDim.x) {
    const int32_t g = a.ids[b0 + e];
    s_id[e] = a.trainable && !a.trainable[g] ? ~g : g;
    load_geom(a, g, s_geom[e]);
  }
}

// ----------------------------------------------------------------------------------------
// Full backward: back to front, dividing by (1 - alpha)
// ----------------------------------------------------------------------------------------
template <typename T>
struct BackwardIO {
  const T* bg;
  const T* trans;
  const int32_t* count;
  const T *v_color, *v_alpha, *v_depth;  // v_alpha, v_depth may be null (zero)
  T* v_geom;  // [N, 8]: u, v, conic a, b, c, opacity, depth, (pad): one 32-byte row
  T *v_colors, *v_bg_tiles;
};

// The per-pixel state of the back-to-front walk.
template <typename T>
struct BackPixel {
  T Tfin, vA, vD, P, Tr, Rd, fx, fy;
  int32_t cnt;
};

// Back-to-front walk for channels [c0, c0 + CB), PPT pixels per thread. The colour behind
// each Gaussian enters the gradient only through its dot product with v_color, so one
// scalar per pixel, P = <v_color, colour behind>, replaces the per-channel state:
//   dot_i = <v_color, c_i> - P,   P <- alpha_i <v_color, c_i> + (1 - alpha_i) P.
// The geometry gradients are linear in dot, so channel blocks add their shares. Batches
// hold blockDim * PPT list entries.
template <int CB, int PPT, typename T, typename TC>
__device__ __forceinline__ void backward_walk(const RasterLaunch<T>& a, const TC* colors,
                                              const BackwardIO<T>& io, const TilePixels<PPT>& p,
                                              int max_cnt, int min_rank, int c0, bool first,
                                              SplatGeom<T>* s_geom, int32_t* s_id, T* s_col,
                                              T* s_bg) {
  const int C = a.channels;
  const int BS = blockDim.x * PPT;
  const int lane = threadIdx.x & 31;
  const int64_t start = a.tile_offsets[p.tile];
  BackPixel<T> s[PPT];
  T vc[PPT][CB];
#pragma unroll
  for (int k = 0; k < PPT; ++k) {
    BackPixel<T>& q = s[k];
    q.Tfin = T(1);
    q.vA = q.vD = q.P = q.Rd = T(0);
    q.cnt = 0;
#pragma unroll
    for (int c = 0; c < CB; ++c) vc[k][c] = T(0);
    if (p.inside[k]) {
      const int64_t pix = stacked_pixel(a, p.tile, p.px[k], p.py[k]);
      q.Tfin = io.trans[pix];
      q.cnt = io.count[pix];
      q.vA = io.v_alpha ? io.v_alpha[pix] : T(0);  // null: no alpha / depth gradient
      q.vD = io.v_depth ? io.v_depth[pix] : T(0);
      load_channel_row<CB>(io.v_color, pix, C, c0, vc[k]);
      if (io.bg) {
#pragma unroll
        for (int c = 0; c < CB; ++c)
          if (c0 + c < C) q.P += vc[k][c] * io.bg[c0 + c];
      }
    }
    q.Tr = q.Tfin;
    q.fx = T(p.px[k]) + T(0.5);
    q.fy = T(p.py[k]) + T(0.5);
  }
  {
    T tfin[PPT];
#pragma unroll
    for (int k = 0; k < PPT; ++k) tfin[k] = s[k].Tfin;
    background_grads<CB, PPT>(vc, tfin, C, c0, p.tile, s_bg, io.v_bg_tiles);
  }
  const int64_t stop = start + min_rank;  // entries in front of min_rank are frozen
  // The warp's pixels use list entries up to rank warp_cnt - 1 (n_contrib) and, with warp_cull,
  // only those whose cutoff ellipse reaches one of them (span_reaches).
  int32_t warp_cnt = 0;
#pragma unroll
  for (int k = 0; k < PPT; ++k) warp_cnt = max(warp_cnt, s[k].cnt);
  warp_cnt = __reduce_max_sync(kFullMask, warp_cnt);
  const WarpSpan<T> span = warp_span<PPT>(a);
  for (int64_t b1 = start + max_cnt; b1 > stop; b1 -= BS) {
    const int64_t b0 = b1 - BS > stop ? b1 - BS : stop;
    const int nb = int(b1 - b0);
    __syncthreads();
    load_batch_geometry(a, b0, nb, s_geom, s_id);
    load_colors<CB>(colors, a.ids, b0, nb, C, c0, s_col);
    __syncthreads();
    // Groups of 32 entries from the back: each lane tests one, the warp walks the hits back to
    // front (the same order as walking every entry).
    for (int g1 = nb; g1 > 0; g1 -= 32) {
      const int g0 = g1 > 32 ? g1 - 32 : 0;
      const int e = g0 + lane;
      const bool reach = e < g1 && int32_t(b0 + e - start) < warp_cnt &&
                         (!a.warp_cull || span_reaches(s_geom[e], span));
      uint32_t hits = __ballot_sync(kFullMask, reach);
      while (hits) {
        const int top = 31 - __clz(hits);
        hits &= ~(1u << top);
        const int j = g0 + top;
        const int32_t rank = int32_t(b0 + j - start);
        const SplatGeom<T> g = s_geom[j];
        T alpha[PPT], gauss[PPT], dx[PPT], dy[PPT];
        bool contrib[PPT], clamped[PPT];
        bool any = false;
#pragma unroll
        for (int k = 0; k < PPT; ++k) {
          dx[k] = s[k].fx - g.u;
          dy[k] = s[k].fy - g.v;
          contrib[k] = clamped[k] = false;
          alpha[k] = gauss[k] = T(0);
          if (rank < s[k].cnt) {
            const T q = conic_quadratic(g.ca, g.cb, g.cc, dx[k], dy[k]);
            if (q <= g.qcut) {
              alpha[k] = splat_alpha(g.o, q, a.alpha_max, gauss[k], clamped[k]);
              contrib[k] = alpha[k] >= a.alpha_threshold;
            }
          }
          any = any || contrib[k];
        }
        if (!__any_sync(kFullMask, any)) continue;
        const int32_t sid = s_id[j];  // < 0: frozen (uniform in the block)
        const bool train = sid >= 0;
        T geo[8];
#pragma unroll
        for (int i = 0; i < 8; ++i) geo[i] = T(0);
        T w[PPT];
        const T* col = s_col + j * CB;
#pragma unroll
        for (int k = 0; k < PPT; ++k) {
          w[k] = T(0);
          if (!contrib[k]) continue;
          BackPixel<T>& q = s[k];
          const T ra = T(1) / (T(1) - alpha[k]);
          const T Ti = q.Tr * ra;  // transmittance in front of this Gaussian
          w[k] = alpha[k] * Ti;
          T sdot = T(0);
#pragma unroll
          for (int c = 0; c < CB; ++c) sdot += vc[k][c] * col[c];
          T v_a = Ti * (sdot - q.P);
          q.P = alpha[k] * sdot + (T(1) - alpha[k]) * q.P;
          if (first) {
            v_a += q.vD * Ti * (g.z - q.Rd) + q.vA * q.Tfin * ra;
            q.Rd = alpha[k] * g.z + (T(1) - alpha[k]) * q.Rd;
            geo[6] += w[k] * q.vD;
          }
          q.Tr = Ti;
          if (train && !clamped[k]) {
            const T ddx = dx[k], ddy = dy[k];
            geo[5] += v_a * gauss[k];
            const T vq = T(-0.5) * v_a * g.o * gauss[k];  // d alpha / d q = -o G / 2
            geo[2] += vq * ddx * ddx;
            geo[3] += vq * T(2) * ddx * ddy;
            geo[4] += vq * ddy * ddy;
            geo[0] += -vq * T(2) * (g.ca * ddx + g.cb * ddy);
            geo[1] += -vq * T(2) * (g.cb * ddx + g.cc * ddy);
          }
        }
        if (!train) continue;  // the state is updated; a frozen Gaussian gets no gradient
        const int64_t gid = sid;
        warp_add_color_grads<CB, PPT>(vc, w, gid, C, c0, lane, io.v_colors);
        // Lanes 0-6 add to one 32-byte row: a single sector per warp and Gaussian.
        const T sg = cuda::warp_reduce_scatter<8>(geo, lane);
        if (lane < (first ? 7 : 6)) atomicAdd(&io.v_geom[8 * gid + lane], sg);
      }
    }
  }
}

// Blocks of 64 channels: two blocks per SM, as before the warp cull's extra state (without the
// bound ptxas took 172 registers a thread for the float32 64 + tail instances, one block per SM).
template <int CBM, int CBT>
constexpr int kBackwardMinBlocks = (CBM >= 64 || CBT >= 64) ? 2 : 1;

template <typename T, typename TC, int CBM, int CBT, int PPT>
__global__ void __launch_bounds__(256, (kBackwardMinBlocks<CBM, CBT>)) backward_kernel(RasterLaunch<T> a, const TC* colors,
                                                       BackwardIO<T> io, int n_main) {
  extern __shared__ __align__(16) unsigned char smem[];
  constexpr int CBX = CBM > CBT ? CBM : CBT;
  const int BS = blockDim.x * PPT;
  SplatGeom<T>* s_geom = reinterpret_cast<SplatGeom<T>*>(smem);
  T* s_col = reinterpret_cast<T*>(s_geom + BS);
  T* s_bg = s_col + BS * CBX;
  int32_t* s_id = reinterpret_cast<int32_t*>(s_bg + CBX);
  int* s_max = s_id + BS;
  const TilePixels<PPT> p = tile_pixels<PPT>(a);
  const int max_cnt = block_max_count<PPT>(a, io.count, p, s_max);
  const int min_rank = first_trainable_rank(a, p.tile, max_cnt, s_max + 1);
  int c0 = 0;
  if constexpr (CBM > 0) {
    for (int k = 0; k < n_main; ++k, c0 += CBM)
      backward_walk<CBM, PPT>(a, colors, io, p, max_cnt, min_rank, c0, k == 0, s_geom, s_id, s_col,
                              s_bg);
  }
  if constexpr (CBT > 0)
    backward_walk<CBT, PPT>(a, colors, io, p, max_cnt, min_rank, c0, c0 == 0, s_geom, s_id, s_col,
                            s_bg);
}

// ----------------------------------------------------------------------------------------
// Features-only backward: front to back, no division, colours and background only
// ----------------------------------------------------------------------------------------
template <int CB, typename T>
__device__ __forceinline__ void colors_walk(const RasterLaunch<T>& a, const int32_t* count,
                                            const T* v_color, T* v_colors, T* v_bg_tiles,
                                            const TilePixels<1>& p, int max_cnt, int c0,
                                            SplatGeom<T>* s_geom, int32_t* s_id, T* s_bg) {
  const int C = a.channels;
  const int BS = blockDim.x;
  const int lane = threadIdx.x & 31;
  const int64_t start = a.tile_offsets[p.tile];
  int32_t cnt = 0;
  T vc[1][CB];
#pragma unroll
  for (int c = 0; c < CB; ++c) vc[0][c] = T(0);
  if (p.inside[0]) {
    const int64_t pix = stacked_pixel(a, p.tile, p.px[0], p.py[0]);
    cnt = count[pix];
    load_channel_row<CB>(v_color, pix, C, c0, vc[0]);
  }
  const T fx = T(p.px[0]) + T(0.5), fy = T(p.py[0]) + T(0.5);
  T Tr[1] = {T(1)};
  // As in backward_walk: the warp walks the entries below its largest count that may reach
  // one of its pixels, in list order.
  const int32_t warp_cnt = __reduce_max_sync(kFullMask, cnt);
  const WarpSpan<T> span = warp_span<1>(a);
  for (int64_t b0 = start; b0 < start + max_cnt; b0 += BS) {
    const int nb = int(min(int64_t(BS), start + max_cnt - b0));
    __syncthreads();
    load_batch_geometry(a, b0, nb, s_geom, s_id);
    __syncthreads();
    for (int g0 = 0; g0 < nb; g0 += 32) {
      const int e = g0 + lane;
      const bool reach = e < nb && int32_t(b0 + e - start) < warp_cnt &&
                         (!a.warp_cull || span_reaches(s_geom[e], span));
      uint32_t hits = __ballot_sync(kFullMask, reach);
      while (hits) {
        const int j = g0 + __ffs(hits) - 1;
        hits &= hits - 1;
        const int32_t rank = int32_t(b0 + j - start);
        bool contrib = false;
        T w[1] = {T(0)};
        if (rank < cnt) {
          const SplatGeom<T> g = s_geom[j];
          const T dx = fx - g.u, dy = fy - g.v;
          const T q = conic_quadratic(g.ca, g.cb, g.cc, dx, dy);
          if (q <= g.qcut) {
            T gauss;
            bool clamped;
            const T alpha = splat_alpha(g.o, q, a.alpha_max, gauss, clamped);
            if (alpha >= a.alpha_threshold) {
              contrib = true;
              w[0] = alpha * Tr[0];
              Tr[0] *= T(1) - alpha;
            }
          }
        }
        // a frozen Gaussian (s_id < 0, uniform in the block) only updates the transmittance
        if (s_id[j] < 0 || !__any_sync(kFullMask, contrib)) continue;
        warp_add_color_grads<CB, 1>(vc, w, s_id[j], C, c0, lane, v_colors);
      }
    }
  }
  background_grads<CB, 1>(vc, Tr, C, c0, p.tile, s_bg, v_bg_tiles);
}

template <typename T, int CBM, int CBT>
__global__ void __launch_bounds__(256) backward_colors_kernel(RasterLaunch<T> a,
                                                              const int32_t* count,
                                                              const T* v_color, T* v_colors,
                                                              T* v_bg_tiles, int n_main) {
  extern __shared__ __align__(16) unsigned char smem[];
  constexpr int CBX = CBM > CBT ? CBM : CBT;
  SplatGeom<T>* s_geom = reinterpret_cast<SplatGeom<T>*>(smem);
  T* s_bg = reinterpret_cast<T*>(s_geom + blockDim.x);
  int32_t* s_id = reinterpret_cast<int32_t*>(s_bg + CBX);
  int* s_max = s_id + blockDim.x;
  const TilePixels<1> p = tile_pixels<1>(a);
  const int max_cnt = block_max_count<1>(a, count, p, s_max);
  int c0 = 0;
  if constexpr (CBM > 0) {
    for (int k = 0; k < n_main; ++k, c0 += CBM)
      colors_walk<CBM>(a, count, v_color, v_colors, v_bg_tiles, p, max_cnt, c0, s_geom, s_id,
                       s_bg);
  }
  if constexpr (CBT > 0)
    colors_walk<CBT>(a, count, v_color, v_colors, v_bg_tiles, p, max_cnt, c0, s_geom, s_id, s_bg);
}

// ----------------------------------------------------------------------------------------
// Host-side choice of the channel blocks
// ----------------------------------------------------------------------------------------
// Main blocks of cb_max channels, then one tail block of the smallest power of two >= 4
// that holds the rest (0 = none); n_main main blocks. C <= cb_max runs as one "tail" block.
struct ChannelPlan {
  int cbm, cbt, n_main;
};

inline int pow2_at_least(int c) {
  int p = 4;
  while (p < c) p *= 2;
  return p;
}

inline ChannelPlan plan_channels(int C, int cb_max) {
  if (C <= cb_max) return {0, pow2_at_least(C), 0};
  const int r = C % cb_max;
  if (r == 0) return {cb_max, 0, C / cb_max};
  const int t = pow2_at_least(r);
  if (t >= cb_max) return {cb_max, 0, C / cb_max + 1};
  return {cb_max, t, C / cb_max};
}

inline int block_threads(int tile_size) { return (tile_size * tile_size + 31) / 32 * 32; }

// Two pixels per backward thread (TilePixels<2>): float32, 16-px tiles, channel blocks small
// enough for twice the per-pixel registers. H100, 1M Gaussians at 1080x1920, C = 3: backward
// 3.09 -> 2.28 ms per training step. The forward stays at one pixel per thread: two were no
// faster (standard scene 0.312 ms against 0.272). Both in docs/BENCHMARKS.md.
// `wanted` = 1 (the op's pixels_per_thread) selects one pixel per thread (comparisons).
constexpr int kTwoPixelMaxChannels = 16;
constexpr int kTwoPixelThreads = 128;

template <typename T>
int pixels_per_thread(const RasterLaunch<T>& a, int cbx, int wanted) {
  if (!std::is_same<T, float>::value || a.tile_size != 16 || cbx > kTwoPixelMaxChannels) return 1;
  return wanted == 1 ? 1 : 2;
}

template <int V>
using IC = std::integral_constant<int, V>;

// Calls f(IC<M>(), IC<cbt>()) for cbt in {4, 8, ..., MAXT}.
template <int M, int MAXT, typename F>
cudaError_t dispatch_tail(int cbt, F& f) {
  if (cbt == 4) return f(IC<M>(), IC<4>());
  if constexpr (MAXT >= 8) {
    if (cbt == 8) return f(IC<M>(), IC<8>());
  }
  if constexpr (MAXT >= 16) {
    if (cbt == 16) return f(IC<M>(), IC<16>());
  }
  if constexpr (MAXT >= 32) {
    if (cbt == 32) return f(IC<M>(), IC<32>());
  }
  if constexpr (MAXT >= 64) {
    if (cbt == 64) return f(IC<M>(), IC<64>());
  }
  return cudaErrorInvalidValue;
}

// Calls f(IC<CBM>(), IC<CBT>()) for a plan made by plan_channels(C, CB_MAX): only block
// sizes up to CB_MAX are compiled.
template <int CB_MAX, typename F>
cudaError_t dispatch_plan(const ChannelPlan& plan, F&& f) {
  if (plan.cbm == 0) return dispatch_tail<0, CB_MAX>(plan.cbt, f);
  if (plan.cbm != CB_MAX) return cudaErrorInvalidValue;
  if (plan.cbt == 0) return f(IC<CB_MAX>(), IC<0>());
  return dispatch_tail<CB_MAX, CB_MAX / 2>(plan.cbt, f);
}

// Raises the kernel's dynamic shared-memory limit when it needs more than 48 KiB.
template <typename K>
cudaError_t set_smem_limit(K kernel, size_t smem) {
  if (smem <= 48 * 1024) return cudaSuccess;
  return cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, int(smem));
}

}  // namespace raster_cuda
}  // namespace tiger
