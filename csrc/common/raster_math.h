#pragma once
// Per-pixel alpha of a projected Gaussian, and the opacity-aware tile test.
#include <math.h>
#include <stdint.h>

#include <type_traits>

#include "macros.h"

namespace tiger {

template <typename T>
struct RasterOptions {
  T alpha_max;        // alpha is clamped here so 1 - alpha never vanishes (backward divides by it)
  T alpha_threshold;  // contributions below are skipped
  T t_min;            // a pixel stops once transmittance would fall below this
};

// Quadratic form q = d^T conic d with d = pixel centre - mean. The offsets may be a
// vector type of S (the CPU rasterizer evaluates 8 pixels at once).
template <typename T, typename S = T>
TIGER_HD T conic_quadratic(S ca, S cb, S cc, T dx, T dy) {
  return ca * dx * dx + S(2) * cb * dx * dy + cc * dy * dy;
}

// exp(-q / 2). On the device in float32 it is one ex2.approx of -q log2(e) / 2 (MUFU.EX2, as
// gsplat's __expf): expf's range reduction cost ~7 instructions per list entry of the raster
// walks, whose forward is bound by its instructions per entry. Relative error: the hardware's
// ~2^-22 plus the product's rounding, |q| log2(e) / 2 * 2^-24 (< 1e-6 wherever alpha can reach
// 1/255: q < 2 log(255)). Results below 2^-126 flush to 0 (their alpha is far below 1/255).
// float64 and the host keep exp.
template <typename T>
TIGER_HD T half_gauss(T q) {
#if defined(__CUDA_ARCH__)
  if constexpr (std::is_same<T, float>::value) {
    float r;
    asm("ex2.approx.ftz.f32 %0, %1;" : "=f"(r) : "f"(q * -0.72134752044448170f));
    return r;
  }
#endif
  return exp(T(-0.5) * q);
}

// alpha = min(alpha_max, o * exp(-q / 2)); `clamped` tells whether alpha_max applied.
template <typename T>
TIGER_HD T splat_alpha(T opacity, T q, T alpha_max, T& gauss, bool& clamped) {
  gauss = half_gauss(q);
  const T a = opacity * gauss;
  clamped = a > alpha_max;
  return clamped ? alpha_max : a;
}

// a * b + c with one rounding, on the host and the device alike. The tile test spells its
// multiply-adds out with this: left to the compiler, a * b + c is fused or not depending on
// the code around it after inlining (a term hoisted out of a loop is rounded on its own), so
// the same source gave the one-thread-per-Gaussian and the chunked CUDA binning different
// roundings, and different tile lists for borderline tiles of the heavy-tailed scene.
template <typename T>
TIGER_HD T fused_multiply_add(T a, T b, T c) {
  return fma(a, b, c);
}

// Quadratic threshold above which alpha surely falls below the threshold:
// o * exp(-q/2) < thr  <=>  q > 2 log(o / thr). The small relative margin keeps
// this pre-test conservative under rounding, so the exact alpha test decides.
template <typename T>
TIGER_HD T cutoff_quadratic(T opacity, T alpha_threshold) {
  const T k2 = T(2) * log(opacity / alpha_threshold);
  return fused_multiply_add(k2, T(1.0001), T(1e-4));
}

// Minimum of the 1D quadratic a t^2 + 2 b t + c over t in [lo, hi], evaluated as
// fma(fma(a, t, 2b), t, c) whatever the compiler (see fused_multiply_add).
template <typename T>
TIGER_HD T min_quadratic_on_segment(T a, T b, T c, T lo, T hi) {
  T t = a > T(0) ? -b / a : lo;
  t = t < lo ? lo : (t > hi ? hi : t);
  return fused_multiply_add(fused_multiply_add(a, t, T(2) * b), t, c);
}

// Minimum of q(d) = d^T conic d over the rectangle [x0,x1]x[y0,y1] of offsets
// d = point - mean: zero if the mean lies inside, else the best point on an edge.
// (Products such as ca * x0 * x0 feed only fused_multiply_add operands: nothing is left for
// the compiler to contract, so every caller rounds the same way.)
template <typename T>
TIGER_HD T min_quadratic_on_rect(T ca, T cb, T cc, T x0, T x1, T y0, T y1) {
  if (x0 <= T(0) && T(0) <= x1 && y0 <= T(0) && T(0) <= y1) return T(0);
  // Along a vertical edge x = X: q(y) = cc y^2 + 2 (cb X) y + ca X^2.
  T m = min_quadratic_on_segment(cc, cb * x0, ca * x0 * x0, y0, y1);
  T e = min_quadratic_on_segment(cc, cb * x1, ca * x1 * x1, y0, y1);
  m = e < m ? e : m;
  e = min_quadratic_on_segment(ca, cb * y0, cc * y0 * y0, x0, x1);
  m = e < m ? e : m;
  e = min_quadratic_on_segment(ca, cb * y1, cc * y1 * y1, x0, x1);
  return e < m ? e : m;
}

// Does the Gaussian reach alpha >= threshold at some pixel centre of the tile
// spanning pixels [px0, px1) x [py0, py1)? Pixel centres sit at +0.5.
template <typename T>
TIGER_HD bool tile_touches(T u, T v, T ca, T cb, T cc, T qcut, int px0, int px1, int py0, int py1) {
  const T x0 = T(px0) + T(0.5) - u, x1 = T(px1) - T(0.5) - u;
  const T y0 = T(py0) + T(0.5) - v, y1 = T(py1) - T(0.5) - v;
  return min_quadratic_on_rect(ca, cb, cc, x0, x1, y0, y1) <= qcut;
}

// Tiles [x0, x1) x [y0, y1) under a Gaussian's screen-space bounding box (centre u, v;
// radii rx, ry in pixels), clamped to the tile grid. Binning tests only these tiles
// (CPU and CUDA alike), so both walk the same candidates in the same row-major order.
struct TileRect {
  int x0, x1, y0, y1;
  TIGER_HD int width() const { return x1 - x0; }
  TIGER_HD int64_t count() const { return int64_t(x1 - x0) * int64_t(y1 - y0); }
};

TIGER_HD int clamp_tile(double a, int hi) { return a < 0.0 ? 0 : (a > double(hi) ? hi : int(a)); }

template <typename T>
TIGER_HD TileRect tile_rect(T u, T v, int32_t rx, int32_t ry, int tile_size, int tiles_x,
                            int tiles_y) {
  const double ts = tile_size;
  return {clamp_tile(floor((double(u) - rx) / ts), tiles_x),
          clamp_tile(floor((double(u) + rx) / ts) + 1.0, tiles_x),
          clamp_tile(floor((double(v) - ry) / ts), tiles_y),
          clamp_tile(floor((double(v) + ry) / ts) + 1.0, tiles_y)};
}

}  // namespace tiger
