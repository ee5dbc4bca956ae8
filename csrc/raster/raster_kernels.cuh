#pragma once
// CUDA rasterization kernels (included by the raster_*_cuda.cu files, each of which
// instantiates one op). One block per tile, one thread per pixel; the tile's Gaussian
// list is walked in batches of blockDim Gaussians staged in shared memory. Channels
// are processed in register blocks of CB (a template parameter): a kernel walks the
// list once per channel block, main blocks of CBM channels then one tail block of CBT,
// so every C runs in one launch and C = 67 costs a 64-block plus a 4-block walk.
// Per-pixel alpha, skipping, termination and gradients follow common/raster_math.h and
// raster_cpu.cpp term by term.
#include <stdlib.h>

#include <type_traits>

#include "common/cuda_helpers.cuh"
#include "common/raster_math.h"
#include "raster_cuda.h"

namespace tiger {
namespace raster_cuda {

using cuda::kFullMask;

// One Gaussian of the current batch, packed so a thread reads it with two 16-byte loads.
template <typename T>
struct alignas(4 * sizeof(T)) SplatGeom {
  T u, v, ca, cb;
  T cc, o, z, qcut;
};

struct TilePixel {
  int tile, px, py;
  bool inside;
};

__device__ __forceinline__ TilePixel tile_pixel(int tile_size, int tiles_x, int width,
                                                int height) {
  TilePixel p;
  p.tile = blockIdx.x;
  const int tx = p.tile % tiles_x, ty = p.tile / tiles_x;
  const int t = threadIdx.x;
  p.px = tx * tile_size + t % tile_size;
  p.py = ty * tile_size + t / tile_size;
  p.inside = t < tile_size * tile_size && p.px < width && p.py < height;
  return p;
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
  for (int64_t b0 = start; b0 < end; b0 += BS) {
    // Also the barrier that protects the previous batch's shared memory.
    if (__syncthreads_count(done) == BS) break;
    const int nb = int(min(int64_t(BS), end - b0));
    if (int(threadIdx.x) < nb) load_geom(a, a.ids[b0 + threadIdx.x], s_geom[threadIdx.x]);
    load_colors<CB>(colors, a.ids, b0, nb, C, c0, s_col);
    __syncthreads();
    if (done) continue;
    for (int j = 0; j < nb; ++j) {
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
      cnt = int32_t(b0 + j - start + 1);
    }
  }
  if (!p.inside) return;
  const int64_t pix = int64_t(p.py) * a.width + p.px;
  T* oc = out.color + pix * C + c0;
#pragma unroll
  for (int c = 0; c < CB; ++c)
    if (c0 + c < C) oc[c] = acc[c] + (out.bg ? Tr * out.bg[c0 + c] : T(0));
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
  const TilePixel p = tile_pixel(a.tile_size, a.tiles_x, a.width, a.height);
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
template <typename T>
__device__ __forceinline__ int block_max_count(const int32_t* n_contrib, const TilePixel& p,
                                               int width, int* s_max) {
  if (threadIdx.x == 0) *s_max = 0;
  __syncthreads();
  const int32_t cnt = p.inside ? n_contrib[int64_t(p.py) * width + p.px] : 0;
  if (cnt > 0) atomicMax(s_max, cnt);
  __syncthreads();
  return *s_max;
}

// Adds the block's sum of vals[c] (one per pixel thread) to v_bg_tiles[tile, c0 + c].
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

// v_bg_tiles[tile, c0 + c] += sum over the block's pixels of t * vc[c], in pieces of 32.
template <int CB, typename T>
__device__ __forceinline__ void background_grads(const T (&vc)[CB], T t, int C, int c0, int tile,
                                                 T* s_bg, T* v_bg_tiles) {
  constexpr int PIECE = CB < 32 ? CB : 32;
#pragma unroll
  for (int h = 0; h < CB / PIECE; ++h) {
    T vals[PIECE];
#pragma unroll
    for (int c = 0; c < PIECE; ++c) vals[c] = t * vc[h * PIECE + c];
    block_background_grad<PIECE>(vals, C, c0 + h * PIECE, tile, s_bg, v_bg_tiles);
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

// Adds w * vc[c] of every lane to v_colors[gid, c0 + c], reduced over the warp first:
// pieces of at most 32 channels, so the temporaries stay at 32 registers for any CB.
template <int CB, typename T>
__device__ __forceinline__ void warp_add_color_grads(const T (&vc)[CB], T w, int64_t gid, int C,
                                                     int c0, int lane, T* v_colors) {
  constexpr int PIECE = CB < 32 ? CB : 32;
#pragma unroll
  for (int h = 0; h < CB / PIECE; ++h) {
    T gc[PIECE];
#pragma unroll
    for (int c = 0; c < PIECE; ++c) gc[c] = w * vc[h * PIECE + c];
    const T sc = cuda::warp_reduce_scatter<PIECE>(gc, lane);
    const int ch = c0 + h * PIECE + lane;
    if (lane < PIECE && ch < C) atomicAdd(&v_colors[gid * C + ch], sc);
  }
}

// Back-to-front walk for channels [c0, c0 + CB). The colour behind each Gaussian enters
// the gradient only through its dot product with v_color, so one scalar per pixel,
// P = <v_color, colour behind>, replaces the per-channel state:
//   dot_i = <v_color, c_i> - P,   P <- alpha_i <v_color, c_i> + (1 - alpha_i) P.
// The geometry gradients are linear in dot, so channel blocks add their shares.
template <int CB, typename T, typename TC>
__device__ __forceinline__ void backward_walk(const RasterLaunch<T>& a, const TC* colors,
                                              const BackwardIO<T>& io, const TilePixel& p,
                                              int max_cnt, int c0, bool first,
                                              SplatGeom<T>* s_geom, int32_t* s_id, T* s_col,
                                              T* s_bg) {
  const int C = a.channels;
  const int BS = blockDim.x;
  const int lane = threadIdx.x & 31;
  const int64_t start = a.tile_offsets[p.tile];
  const int64_t pix = int64_t(p.py) * a.width + p.px;
  T Tfin = T(1), vA = T(0), vD = T(0), P = T(0);
  int32_t cnt = 0;
  T vc[CB];
#pragma unroll
  for (int c = 0; c < CB; ++c) vc[c] = T(0);
  if (p.inside) {
    Tfin = io.trans[pix];
    cnt = io.count[pix];
    vA = io.v_alpha ? io.v_alpha[pix] : T(0);  // null: no alpha / depth gradient
    vD = io.v_depth ? io.v_depth[pix] : T(0);
#pragma unroll
    for (int c = 0; c < CB; ++c)
      if (c0 + c < C) {
        vc[c] = io.v_color[pix * C + c0 + c];
        if (io.bg) P += vc[c] * io.bg[c0 + c];
      }
  }
  background_grads<CB>(vc, Tfin, C, c0, p.tile, s_bg, io.v_bg_tiles);
  const T fx = T(p.px) + T(0.5), fy = T(p.py) + T(0.5);
  T Tr = Tfin, Rd = T(0);
  for (int64_t b1 = start + max_cnt; b1 > start; b1 -= BS) {
    const int64_t b0 = b1 - BS > start ? b1 - BS : start;
    const int nb = int(b1 - b0);
    __syncthreads();
    if (int(threadIdx.x) < nb) {
      const int32_t g = a.ids[b0 + threadIdx.x];
      s_id[threadIdx.x] = g;
      load_geom(a, g, s_geom[threadIdx.x]);
    }
    load_colors<CB>(colors, a.ids, b0, nb, C, c0, s_col);
    __syncthreads();
    for (int j = nb - 1; j >= 0; --j) {
      const int32_t rank = int32_t(b0 + j - start);
      const SplatGeom<T> g = s_geom[j];
      const T dx = fx - g.u, dy = fy - g.v;
      bool contrib = false, clamped = false;
      T alpha = T(0), gauss = T(0);
      if (rank < cnt) {
        const T q = conic_quadratic(g.ca, g.cb, g.cc, dx, dy);
        if (q <= g.qcut) {
          alpha = splat_alpha(g.o, q, a.alpha_max, gauss, clamped);
          contrib = alpha >= a.alpha_threshold;
        }
      }
      if (!__any_sync(kFullMask, contrib)) continue;
      T geo[8];
#pragma unroll
      for (int k = 0; k < 8; ++k) geo[k] = T(0);
      T w = T(0);
      if (contrib) {
        const T ra = T(1) / (T(1) - alpha);
        const T Ti = Tr * ra;  // transmittance in front of this Gaussian
        w = alpha * Ti;
        const T* col = s_col + j * CB;
        T sdot = T(0);
#pragma unroll
        for (int c = 0; c < CB; ++c) sdot += vc[c] * col[c];
        T v_a = Ti * (sdot - P);
        P = alpha * sdot + (T(1) - alpha) * P;
        if (first) {
          v_a += vD * Ti * (g.z - Rd) + vA * Tfin * ra;
          Rd = alpha * g.z + (T(1) - alpha) * Rd;
          geo[6] = w * vD;
        }
        Tr = Ti;
        if (!clamped) {
          geo[5] = v_a * gauss;
          const T vq = T(-0.5) * v_a * g.o * gauss;  // d alpha / d q = -o G / 2
          geo[2] = vq * dx * dx;
          geo[3] = vq * T(2) * dx * dy;
          geo[4] = vq * dy * dy;
          geo[0] = -vq * T(2) * (g.ca * dx + g.cb * dy);
          geo[1] = -vq * T(2) * (g.cb * dx + g.cc * dy);
        }
      }
      const int64_t gid = s_id[j];
      warp_add_color_grads<CB>(vc, w, gid, C, c0, lane, io.v_colors);
      // Lanes 0-6 add to one 32-byte row: a single sector per warp and Gaussian.
      const T sg = cuda::warp_reduce_scatter<8>(geo, lane);
      if (lane < (first ? 7 : 6)) atomicAdd(&io.v_geom[8 * gid + lane], sg);
    }
  }
}

template <typename T, typename TC, int CBM, int CBT>
__global__ void __launch_bounds__(256) backward_kernel(RasterLaunch<T> a, const TC* colors,
                                                       BackwardIO<T> io, int n_main) {
  extern __shared__ __align__(16) unsigned char smem[];
  constexpr int CBX = CBM > CBT ? CBM : CBT;
  SplatGeom<T>* s_geom = reinterpret_cast<SplatGeom<T>*>(smem);
  T* s_col = reinterpret_cast<T*>(s_geom + blockDim.x);
  T* s_bg = s_col + blockDim.x * CBX;
  int32_t* s_id = reinterpret_cast<int32_t*>(s_bg + CBX);
  int* s_max = s_id + blockDim.x;
  const TilePixel p = tile_pixel(a.tile_size, a.tiles_x, a.width, a.height);
  const int max_cnt = block_max_count<T>(io.count, p, a.width, s_max);
  int c0 = 0;
  if constexpr (CBM > 0) {
    for (int k = 0; k < n_main; ++k, c0 += CBM)
      backward_walk<CBM>(a, colors, io, p, max_cnt, c0, k == 0, s_geom, s_id, s_col,
                         s_bg);
  }
  if constexpr (CBT > 0)
    backward_walk<CBT>(a, colors, io, p, max_cnt, c0, c0 == 0, s_geom, s_id, s_col, s_bg);
}

// ----------------------------------------------------------------------------------------
// Features-only backward: front to back, no division, colours and background only
// ----------------------------------------------------------------------------------------
template <int CB, typename T>
__device__ __forceinline__ void colors_walk(const RasterLaunch<T>& a, const int32_t* count,
                                            const T* v_color, T* v_colors, T* v_bg_tiles,
                                            const TilePixel& p, int max_cnt, int c0,
                                            SplatGeom<T>* s_geom, int32_t* s_id, T* s_bg) {
  const int C = a.channels;
  const int BS = blockDim.x;
  const int lane = threadIdx.x & 31;
  const int64_t start = a.tile_offsets[p.tile];
  const int64_t pix = int64_t(p.py) * a.width + p.px;
  int32_t cnt = 0;
  T vc[CB];
#pragma unroll
  for (int c = 0; c < CB; ++c) vc[c] = T(0);
  if (p.inside) {
    cnt = count[pix];
#pragma unroll
    for (int c = 0; c < CB; ++c)
      if (c0 + c < C) vc[c] = v_color[pix * C + c0 + c];
  }
  const T fx = T(p.px) + T(0.5), fy = T(p.py) + T(0.5);
  T Tr = T(1);
  for (int64_t b0 = start; b0 < start + max_cnt; b0 += BS) {
    const int nb = int(min(int64_t(BS), start + max_cnt - b0));
    __syncthreads();
    if (int(threadIdx.x) < nb) {
      const int32_t g = a.ids[b0 + threadIdx.x];
      s_id[threadIdx.x] = g;
      load_geom(a, g, s_geom[threadIdx.x]);
    }
    __syncthreads();
    for (int j = 0; j < nb; ++j) {
      const int32_t rank = int32_t(b0 + j - start);
      bool contrib = false;
      T w = T(0);
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
            w = alpha * Tr;
            Tr *= T(1) - alpha;
          }
        }
      }
      if (!__any_sync(kFullMask, contrib)) continue;
      warp_add_color_grads<CB>(vc, w, s_id[j], C, c0, lane, v_colors);
    }
  }
  background_grads<CB>(vc, Tr, C, c0, p.tile, s_bg, v_bg_tiles);
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
  const TilePixel p = tile_pixel(a.tile_size, a.tiles_x, a.width, a.height);
  const int max_cnt = block_max_count<T>(count, p, a.width, s_max);
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

// Largest channel block, overridable for tuning through an environment variable that
// names one of the compiled sizes (read at every launch, so a benchmark can switch it).
inline int channel_block_max(const char* env, int fallback, int alt) {
  const char* v = getenv(env);
  if (v == nullptr) return fallback;
  const int x = atoi(v);
  return x == alt ? alt : fallback;
}

inline int block_threads(int tile_size) { return (tile_size * tile_size + 31) / 32 * 32; }

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
