// CPU rasterization: one tile per task (at::parallel_for over tiles). Within a
// tile the Gaussians are visited in list order and each one sweeps the tile's
// pixels, so the per-Gaussian data stays in registers and the channel loops run
// over contiguous memory (they vectorise). Backward passes write one gradient
// row per (tile, Gaussian) intersection and reduce them per Gaussian afterwards:
// no atomics, and the result does not depend on the thread count.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <type_traits>
#include <vector>

#include "common/raster_math.h"
#include "common/torch_checks.h"
#include "raster.h"
#include "simd_cpu.h"

namespace tiger {

namespace {

template <typename T>
struct Scene2D {
  const T* means2d;
  const T* conics;
  const T* opac;
  const T* depths;
  const int64_t* tile_offsets;
  const int32_t* ids;
  int width, height, ts, tiles_x;
  int64_t tiles_per_view;  // tiles of one image (RasterArgs::views images stacked along the rows)
  RasterOptions<T> opt;
  const bool* trainable;  // [N] or null (all): the backward adds gradients only for these
  bool frozen(int32_t g) const { return trainable && !trainable[g]; }
};

// A tile's pixels: px0, py0 in its own image's coordinates (where Gaussians are evaluated),
// row0 the first output row of that image (image v of a views > 1 call starts at v * height).
struct TileGeom {
  int px0, py0, pw, ph;
  int64_t row0;
  // Output pixel index of the tile-local linear pixel p.
  int64_t pixel(int p, int width) const {
    return (row0 + py0 + p / pw) * width + px0 + p % pw;
  }
};

template <typename T>
inline TileGeom tile_geom(const Scene2D<T>& s, int64_t tile) {
  const int64_t view = tile / s.tiles_per_view, local = tile % s.tiles_per_view;
  const int tx = int(local % s.tiles_x), ty = int(local / s.tiles_x);
  const int px0 = tx * s.ts, py0 = ty * s.ts;
  return {px0, py0, std::min(s.ts, s.width - px0), std::min(s.ts, s.height - py0),
          view * s.height};
}

// The part of a tile where a Gaussian can reach alpha >= threshold: the
// bounding box of its cutoff ellipse (widened by a pixel against rounding),
// in tile-local pixel coordinates. Pixels outside are never evaluated.
struct SubRect {
  int x0, x1, y0, y1, pw;
  // f(p) for each pixel of the rectangle, p its tile-local linear index, row by row.
  template <typename F>
  void for_each(F&& f) const {
    for (int y = y0; y < y1; ++y)
      for (int p = y * pw + x0, e = y * pw + x1; p < e; ++p) f(p);
  }
};

template <typename T>
inline SubRect gaussian_subrect(T u, T v, T ca, T cb, T cc, T qcut, const TileGeom& tg) {
  SubRect r{0, tg.pw, 0, tg.ph, tg.pw};
  const T det = ca * cc - cb * cb;
  if (!(det > T(0))) return r;
  // Half extents of {d : d^T conic d <= qcut} are sqrt(qcut * Sigma_xx), Sigma = conic^-1.
  const double ex = std::sqrt(double(qcut) * double(cc) / double(det));
  const double ey = std::sqrt(double(qcut) * double(ca) / double(det));
  if (!(ex < 1e6 && ey < 1e6)) return r;
  auto clampi = [](double a, int hi) { return int(std::min<double>(std::max<double>(a, 0), hi)); };
  r.x0 = clampi(std::floor(double(u) - ex - 0.5) - tg.px0, tg.pw);
  r.x1 = clampi(std::ceil(double(u) + ex - 0.5) - tg.px0 + 1, tg.pw);
  r.y0 = clampi(std::floor(double(v) - ey - 0.5) - tg.py0, tg.ph);
  r.y1 = clampi(std::ceil(double(v) + ey - 0.5) - tg.py0 + 1, tg.ph);
  if (r.x1 <= r.x0 || r.y1 <= r.y0) r.x1 = r.x0, r.y1 = r.y0;
  return r;
}

// alpha = min(alpha_max, o exp(-q/2)) of Gaussian g at the pixel centres of the rows of its
// sub-rectangle, and 0 where the pair does not count (outside the rectangle, q above the
// cutoff, or alpha below the threshold). Every CPU pass reads its alphas from here, so
// forward and backward agree bit for bit on which pairs count. Returns the rectangle.
template <typename T>
inline SubRect tile_alpha(const Scene2D<T>& s, int32_t g, T qcut, const TileGeom& tg, T* alpha) {
  const T u = s.means2d[2 * g], v = s.means2d[2 * g + 1], o = s.opac[g];
  const T ca = s.conics[3 * g], cb = s.conics[3 * g + 1], cc = s.conics[3 * g + 2];
  const T amax = s.opt.alpha_max, thr = s.opt.alpha_threshold;
  const SubRect r = gaussian_subrect(u, v, ca, cb, cc, qcut, tg);
  for (int y = r.y0; y < r.y1; ++y) {
    const T dy = T(tg.py0 + y) + T(0.5) - v;
    T* row = alpha + y * tg.pw;
    if constexpr (std::is_same_v<T, float>) {
      // A vector of pixels at a time (8 with AVX, 4 without) with the polynomial exp; a short
      // last block goes through a padded buffer so the very same instructions compute it.
      using V = simd::Vec<float>;
      constexpr int L = simd::kLanes<float>;
      const V lane = simd::iota<float>();
      for (int x0 = r.x0 / L * L; x0 < r.x1; x0 += L) {  // only blocks the rectangle meets
        const V x = lane + float(x0);
        const V dx = (x + float(tg.px0) + 0.5f) - u;
        const V q = conic_quadratic(ca, cb, cc, dx, simd::broadcast(dy));
        V a = o * simd::exp(-0.5f * q);
        a = a > amax ? simd::broadcast(amax) : a;
        const auto keep = (x >= float(r.x0)) & (x < float(r.x1)) & (q <= qcut) & (a >= thr);
        a = keep ? a : V{};
        if (tg.pw - x0 >= L) {
          simd::store(row + x0, a);
        } else {
          float tail[L];
          simd::store(tail, a);
          std::copy(tail, tail + (tg.pw - x0), row + x0);
        }
      }
    } else {
      for (int x = 0; x < tg.pw; ++x) {
        const T dx = T(tg.px0 + x) + T(0.5) - u;
        const T q = conic_quadratic(ca, cb, cc, dx, dy);
        T gauss;
        bool clamped;
        const T a = splat_alpha(o, q, amax, gauss, clamped);
        row[x] = (x >= r.x0 && x < r.x1 && q <= qcut && a >= thr) ? a : T(0);
      }
    }
  }
  return r;
}

template <typename T>
void forward_tile(const Scene2D<T>& s, int64_t tile, int64_t C, const T* colors, const T* bg,
                  T* out_color, T* out_alpha, T* out_depth, int32_t* out_count, T* out_trans) {
  const TileGeom tg = tile_geom(s, tile);
  const int P = tg.pw * tg.ph;
  std::vector<T> Tr(P, T(1)), acc(size_t(P) * C, T(0)), accd(P, T(0)), alpha(P);
  std::vector<int32_t> cnt(P, 0);
  std::vector<char> done(P, 0);
  int n_done = 0;
  const int64_t start = s.tile_offsets[tile], end = s.tile_offsets[tile + 1];
  for (int64_t k = start; k < end && n_done < P; ++k) {
    const int32_t g = s.ids[k];
    const T z = s.depths[g];
    const T qcut = cutoff_quadratic(s.opac[g], s.opt.alpha_threshold);
    const T* col = colors + int64_t(g) * C;
    const SubRect rect = tile_alpha(s, g, qcut, tg, alpha.data());
    rect.for_each([&](const int p) {
      const T a = alpha[p];
      if (done[p] || a == T(0)) return;
      const T next_T = Tr[p] * (T(1) - a);
      if (next_T < s.opt.t_min) {
        done[p] = 1;
        ++n_done;
        return;
      }
      const T w = a * Tr[p];
      T* ap = acc.data() + int64_t(p) * C;
      for (int64_t c = 0; c < C; ++c) ap[c] += w * col[c];
      accd[p] += w * z;
      Tr[p] = next_T;
      cnt[p] = int32_t(k - start + 1);
    });
  }
  for (int p = 0; p < P; ++p) {
    const int64_t pix = tg.pixel(p, s.width);
    T* oc = out_color + pix * C;
    const T* a = acc.data() + int64_t(p) * C;
    for (int64_t c = 0; c < C; ++c) oc[c] = a[c] + (bg ? Tr[p] * bg[c] : T(0));
    out_alpha[pix] = T(1) - Tr[p];
    out_depth[pix] = accd[p];
    out_count[pix] = cnt[p];
    out_trans[pix] = Tr[p];
  }
}

// Per-intersection gradient row layout: [colors(C), u, v, ca, cb, cc, opacity, depth].
constexpr int kGeomGrads = 7;

template <typename T>
void backward_tile(const Scene2D<T>& s, int64_t tile, int64_t C, const T* colors, const T* bg,
                   const T* trans, const int32_t* count, const T* v_color, const T* v_alpha,
                   const T* v_depth, T* rows, T* v_bg_tile) {
  const TileGeom tg = tile_geom(s, tile);
  const int P = tg.pw * tg.ph;
  const int64_t S = C + kGeomGrads;
  std::vector<T> Tr(P), Tfin(P), R(size_t(P) * C), Rd(P, T(0)), vC(size_t(P) * C), vA(P), vD(P),
      alphas(P);
  std::vector<int32_t> cnt(P);
  int32_t max_cnt = 0;
  for (int p = 0; p < P; ++p) {
    const int64_t pix = tg.pixel(p, s.width);
    Tfin[p] = Tr[p] = trans[pix];
    cnt[p] = count[pix];
    max_cnt = std::max(max_cnt, cnt[p]);
    vA[p] = v_alpha ? v_alpha[pix] : T(0);  // null: no alpha / depth gradient
    vD[p] = v_depth ? v_depth[pix] : T(0);
    for (int64_t c = 0; c < C; ++c) {
      vC[p * C + c] = v_color[pix * C + c];
      R[p * C + c] = bg ? bg[c] : T(0);
      v_bg_tile[c] += Tfin[p] * vC[p * C + c];
    }
  }
  const int64_t start = s.tile_offsets[tile];
  std::vector<T> gcol(C);
  for (int64_t k = start + max_cnt - 1; k >= start; --k) {
    const int32_t g = s.ids[k];
    const T o = s.opac[g], z = s.depths[g];
    const T u = s.means2d[2 * g], v = s.means2d[2 * g + 1];
    const T ca = s.conics[3 * g], cb = s.conics[3 * g + 1], cc = s.conics[3 * g + 2];
    const T qcut = cutoff_quadratic(o, s.opt.alpha_threshold);
    const T* col = colors + int64_t(g) * C;
    std::fill(gcol.begin(), gcol.end(), T(0));
    // Geometry terms sum over up to a whole tile of pixels with cancellation:
    // accumulate them in double so float32 gradients keep their accuracy.
    double gu = 0, gv = 0, gca = 0, gcb = 0, gcc = 0, go = 0, gz = 0;
    bool touched = false;
    const int32_t rank = int32_t(k - start);
    const SubRect rect = tile_alpha(s, g, qcut, tg, alphas.data());
    rect.for_each([&](const int p) {
      const T alpha = alphas[p];
      if (rank >= cnt[p] || alpha == T(0)) return;
      const bool clamped = alpha >= s.opt.alpha_max;
      touched = true;
      const T ra = T(1) / (T(1) - alpha);
      const T Ti = Tr[p] * ra;  // transmittance in front of this Gaussian
      const T w = alpha * Ti;
      const T* vc = vC.data() + int64_t(p) * C;
      T* r = R.data() + int64_t(p) * C;
      T dot = T(0);
      // The dot product is a reduction: let it vectorise (reassociation is fine here).
#pragma omp simd reduction(+ : dot)
      for (int64_t c = 0; c < C; ++c) {
        gcol[c] += w * vc[c];
        dot += vc[c] * (col[c] - r[c]);
        r[c] = alpha * col[c] + (T(1) - alpha) * r[c];
      }
      const T v_a = Ti * dot + vD[p] * Ti * (z - Rd[p]) + vA[p] * Tfin[p] * ra;
      Rd[p] = alpha * z + (T(1) - alpha) * Rd[p];
      gz += w * vD[p];
      Tr[p] = Ti;
      if (!clamped) {
        go += v_a * alpha / o;                // d alpha / d o = G = alpha / o
        const T vq = T(-0.5) * v_a * alpha;  // d alpha / d q = -o G / 2
        const T dx = T(tg.px0 + p % tg.pw) + T(0.5) - u;
        const T dy = T(tg.py0 + p / tg.pw) + T(0.5) - v;
        gca += vq * dx * dx;
        gcb += vq * T(2) * dx * dy;
        gcc += vq * dy * dy;
        gu -= vq * T(2) * (ca * dx + cb * dy);
        gv -= vq * T(2) * (cb * dx + cc * dy);
      }
    });
    if (!touched || s.frozen(g)) continue;  // a frozen Gaussian's row stays zero
    T* row = rows + k * S;
    for (int64_t c = 0; c < C; ++c) row[c] = gcol[c];
    row[C] = T(gu);
    row[C + 1] = T(gv);
    row[C + 2] = T(gca);
    row[C + 3] = T(gcb);
    row[C + 4] = T(gcc);
    row[C + 5] = T(go);
    row[C + 6] = T(gz);
  }
}

// Features-only backward of one tile: d loss / d colors[g] = sum_p w_pg v_color[p] with the
// forward's weights w = alpha T recomputed front to back; no geometry term at all.
template <typename T>
void backward_colors_tile(const Scene2D<T>& s, int64_t tile, int64_t C, const int32_t* count,
                          const T* v_color, T* rows, T* per_gaussian, T* v_bg_tile) {
  const TileGeom tg = tile_geom(s, tile);
  const int P = tg.pw * tg.ph;
  std::vector<T> Tr(P, T(1)), alpha(P), wl(P);
  std::vector<int32_t> cnt(P);
  std::vector<const T*> vrow(P), src(P);
  int32_t max_cnt = 0;
  for (int p = 0; p < P; ++p) {
    const int64_t pix = tg.pixel(p, s.width);
    vrow[p] = v_color + pix * C;
    cnt[p] = count[pix];
    max_cnt = std::max(max_cnt, cnt[p]);
  }
  const int64_t start = s.tile_offsets[tile];
  for (int64_t k = start; k < start + max_cnt; ++k) {
    const int32_t g = s.ids[k];
    const T qcut = cutoff_quadratic(s.opac[g], s.opt.alpha_threshold);
    const int32_t rank = int32_t(k - start);
    const SubRect rect = tile_alpha(s, g, qcut, tg, alpha.data());
    // Gather the (pixel, weight) pairs first, so the channel sums below run over a dense list
    // with their accumulators in registers.
    int n = 0;
    rect.for_each([&](const int p) {  // branch-free: the test is unpredictable
      const T a = rank < cnt[p] ? alpha[p] : T(0);
      src[n] = vrow[p];
      wl[n] = a * Tr[p];
      Tr[p] *= T(1) - a;
      n += a != T(0);
    });
    if (n == 0 || s.frozen(g)) continue;  // the transmittance is updated, no gradient added
    T* out = per_gaussian ? per_gaussian + int64_t(g) * C  // this thread's own [N, C] buffer
                          : rows + k * C;
    simd::weighted_sum(src.data(), wl.data(), n, C, out);
  }
  // d loss / d background = sum_p T_final[p] v_color[p]: the same weighted sum.
  simd::weighted_sum(vrow.data(), Tr.data(), P, C, v_bg_tile);
}

// out[ids[k], :] += rows[k, :] for every intersection k; parallel over column
// blocks so no two threads write the same element.
template <typename T>
void reduce_rows(const T* rows, int64_t m, int64_t S, const int32_t* ids, T* out) {
  at::parallel_for(0, S, m * S < (1 << 16) ? S : 1, [&](int64_t c0, int64_t c1) {
    for (int64_t k = 0; k < m; ++k) {
      const T* r = rows + k * S;
      T* o = out + int64_t(ids[k]) * S;
      for (int64_t c = c0; c < c1; ++c) o[c] += r[c];
    }
  });
}

template <typename T>
Scene2D<T> make_scene(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                      const at::Tensor& depths, const at::Tensor& tile_offsets,
                      const at::Tensor& ids, const RasterArgs& a,
                      const at::Tensor& trainable = at::Tensor()) {
  Scene2D<T> s;
  s.means2d = means2d.data_ptr<T>();
  s.conics = conics.data_ptr<T>();
  s.opac = opac.data_ptr<T>();
  s.depths = depths.defined() ? depths.data_ptr<T>() : nullptr;
  s.tile_offsets = tile_offsets.data_ptr<int64_t>();
  s.ids = ids.data_ptr<int32_t>();
  s.width = int(a.width);
  s.height = int(a.height);
  s.ts = int(a.tile_size);
  s.tiles_x = int((a.width + a.tile_size - 1) / a.tile_size);
  s.tiles_per_view = int64_t(s.tiles_x) * ((a.height + a.tile_size - 1) / a.tile_size);
  s.opt = {T(a.alpha_max), T(a.alpha_threshold), T(a.t_min)};
  s.trainable = trainable.defined() ? trainable.data_ptr<bool>() : nullptr;
  return s;
}

// Tiles per task: small images or few intersections run on one thread, where
// waking a thread pool would cost more than the work.
int64_t tile_grain(int64_t tiles, int64_t isects) {
  return isects < 16384 ? std::max<int64_t>(tiles, 1) : 1;
}

int64_t num_tiles(const RasterArgs& a) {
  return a.views * ((a.width + a.tile_size - 1) / a.tile_size) * ((a.height + a.tile_size - 1) / a.tile_size);
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> rasterize_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& colors, const at::Tensor& depths, const std::optional<at::Tensor>& background,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min,
    int64_t channel_block, int64_t backward_channel_block, int64_t colors_channel_block,
    int64_t backward_pixels_per_thread, int64_t views, const std::optional<at::Tensor>& trainable,
    int64_t tile_order, bool warp_cull) {
  const char* op = "tiger.rasterize";
  const RasterArgs a{width, height, tile_size, alpha_max, alpha_threshold, t_min, views};
  const int64_t rows = views * height;  // the views' images, stacked
  // The CUDA kernel choices: checked only, so that every device rejects the same values.
  check_channel_block(op, "channel_block", channel_block);
  check_channel_block(op, "backward_channel_block", backward_channel_block);
  check_channel_block(op, "colors_channel_block", colors_channel_block);
  check_pixels_per_thread(op, "backward_pixels_per_thread", backward_pixels_per_thread);
  check_tile_order(op, tile_order);
  check_shape(colors, op, "colors", {means2d.size(0), -1});
  check_raster_inputs(op, means2d, conics, opacities, depths, background, colors.size(1),
                      tile_offsets, gaussian_ids, a);
  check_same(colors, means2d, op, "colors");
  check_row_mask(trainable, means2d.size(0), means2d, op, "trainable", "means2d");  // carried for the autograd formula
  const int64_t C = colors.size(1);
  auto out_color = at::empty({rows, width, C}, means2d.options());
  auto out_alpha = at::empty({rows, width}, means2d.options());
  auto out_depth = at::empty({rows, width}, means2d.options());
  auto out_count = at::empty({rows, width}, means2d.options().dtype(at::kInt));
  auto out_trans = at::empty({rows, width}, means2d.options());
  const auto m_c = means2d.contiguous(), c_c = conics.contiguous(), o_c = opacities.contiguous(),
             d_c = depths.contiguous(), col_c = colors.contiguous(), t_c = tile_offsets.contiguous(),
             i_c = gaussian_ids.contiguous();
  const auto bg_c = background.has_value() ? background->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_cpu", [&] {
    using T = scalar_t;
    const Scene2D<T> s = make_scene<T>(m_c, c_c, o_c, d_c, t_c, i_c, a);
    const T* bg = bg_c.defined() ? bg_c.data_ptr<T>() : nullptr;
    const int64_t tiles = num_tiles(a);
    at::parallel_for(0, tiles, tile_grain(tiles, i_c.size(0)), [&](int64_t b, int64_t e) {
      for (int64_t t = b; t < e; ++t)
        forward_tile<T>(s, t, C, col_c.data_ptr<T>(), bg, out_color.data_ptr<T>(),
                        out_alpha.data_ptr<T>(), out_depth.data_ptr<T>(),
                        out_count.data_ptr<int32_t>(), out_trans.data_ptr<T>());
    });
  });
  return {out_color, out_alpha, out_depth, out_count, out_trans};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor>
rasterize_backward_cpu(const at::Tensor& means2d, const at::Tensor& conics,
                       const at::Tensor& opacities, const at::Tensor& colors,
                       const at::Tensor& depths, const std::optional<at::Tensor>& background,
                       const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width,
                       int64_t height, int64_t tile_size, double alpha_max, double alpha_threshold,
                       double t_min, const at::Tensor& transmittance, const at::Tensor& n_contrib,
                       const at::Tensor& v_color, const std::optional<at::Tensor>& v_alpha,
                       const std::optional<at::Tensor>& v_depth, int64_t channel_block,
                       int64_t pixels_per_thread, int64_t views,
                       const std::optional<at::Tensor>& trainable, int64_t tile_order, bool warp_cull) {
  const char* op = "tiger.rasterize_backward";
  const RasterArgs a{width, height, tile_size, alpha_max, alpha_threshold, t_min, views};
  const int64_t H = views * height;  // the views' images, stacked
  check_channel_block(op, "channel_block", channel_block);  // CUDA choices: checked only
  check_pixels_per_thread(op, "pixels_per_thread", pixels_per_thread);
  check_tile_order(op, tile_order);
  const int64_t n = means2d.size(0);
  check_shape(colors, op, "colors", {n, -1});
  const int64_t C = colors.size(1);
  check_raster_inputs(op, means2d, conics, opacities, depths, background, C, tile_offsets,
                      gaussian_ids, a);
  check_shape(transmittance, op, "transmittance", {H, width});
  check_shape(n_contrib, op, "n_contrib", {H, width});
  check_dtype(n_contrib, at::kInt, op, "n_contrib");
  check_shape(v_color, op, "v_color", {H, width, C});
  if (v_alpha.has_value()) check_shape(*v_alpha, op, "v_alpha", {H, width});
  if (v_depth.has_value()) check_shape(*v_depth, op, "v_depth", {H, width});
  check_row_mask(trainable, means2d.size(0), means2d, op, "trainable", "means2d");
  const at::Tensor train = trainable.has_value() ? trainable->contiguous() : at::Tensor();
  const int64_t S = C + kGeomGrads, m = gaussian_ids.size(0), tiles = num_tiles(a);
  auto rows = at::zeros({m, S}, means2d.options());
  auto v_bg_tiles = at::zeros({tiles, C}, means2d.options());
  auto grads = at::zeros({n, S}, means2d.options());
  const auto m_c = means2d.contiguous(), c_c = conics.contiguous(), o_c = opacities.contiguous(),
             d_c = depths.contiguous(), col_c = colors.contiguous(), t_c = tile_offsets.contiguous(),
             i_c = gaussian_ids.contiguous(), a_c = transmittance.contiguous(), n_c = n_contrib.contiguous(),
             vc_c = v_color.contiguous();
  const auto va_c = v_alpha.has_value() ? v_alpha->contiguous() : at::Tensor(),
             vd_c = v_depth.has_value() ? v_depth->contiguous() : at::Tensor();
  const auto bg_c = background.has_value() ? background->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_backward_cpu", [&] {
    using T = scalar_t;
    const Scene2D<T> s = make_scene<T>(m_c, c_c, o_c, d_c, t_c, i_c, a, train);
    const T* bg = bg_c.defined() ? bg_c.data_ptr<T>() : nullptr;
    at::parallel_for(0, tiles, tile_grain(tiles, m), [&](int64_t b, int64_t e) {
      for (int64_t t = b; t < e; ++t)
        backward_tile<T>(s, t, C, col_c.data_ptr<T>(), bg, a_c.data_ptr<T>(),
                         n_c.data_ptr<int32_t>(), vc_c.data_ptr<T>(),
                         va_c.defined() ? va_c.data_ptr<T>() : nullptr,
                         vd_c.defined() ? vd_c.data_ptr<T>() : nullptr, rows.data_ptr<T>(),
                         v_bg_tiles.data_ptr<T>() + t * C);
    });
    reduce_rows<T>(rows.data_ptr<T>(), m, S, i_c.data_ptr<int32_t>(), grads.data_ptr<T>());
  });
  auto v_geom = at::zeros({n, 8}, means2d.options());  // the CUDA layout (raster.h)
  v_geom.narrow(1, 0, kGeomGrads).copy_(grads.narrow(1, C, kGeomGrads));
  return {v_geom, grads.narrow(1, 0, C).contiguous(), v_bg_tiles.sum(0)};
}

std::tuple<at::Tensor, at::Tensor> rasterize_backward_colors_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min,
    const at::Tensor& n_contrib, const at::Tensor& v_color, int64_t channel_block, int64_t views,
    const std::optional<at::Tensor>& trainable, int64_t tile_order, bool warp_cull) {
  const char* op = "tiger.rasterize_backward_colors";
  const RasterArgs a{width, height, tile_size, alpha_max, alpha_threshold, t_min, views};
  const int64_t H = views * height;  // the views' images, stacked
  check_channel_block(op, "channel_block", channel_block);  // CUDA choices: checked only
  check_tile_order(op, tile_order);
  const int64_t n = means2d.size(0);
  check_shape(v_color, op, "v_color", {H, width, -1});
  const int64_t C = v_color.size(2);
  check_raster_inputs(op, means2d, conics, opacities, opacities.new_empty({n}), std::nullopt, C,
                      tile_offsets, gaussian_ids, a);
  check_same(v_color, means2d, op, "v_color");
  check_shape(n_contrib, op, "n_contrib", {H, width});
  check_dtype(n_contrib, at::kInt, op, "n_contrib");
  check_row_mask(trainable, means2d.size(0), means2d, op, "trainable", "means2d");
  const at::Tensor train = trainable.has_value() ? trainable->contiguous() : at::Tensor();
  const int64_t m = gaussian_ids.size(0), tiles = num_tiles(a);
  // Gradients go either straight into one [N, C] buffer per thread (summed at the end), or,
  // when that would take more memory than one row per intersection, into per-intersection
  // rows reduced per Gaussian afterwards. Both are deterministic for a given thread count.
  const int64_t threads = at::get_num_threads();
  const bool per_thread = threads * n <= m;
  auto rows = per_thread ? at::Tensor() : at::zeros({m, C}, means2d.options());
  auto partial = per_thread ? at::zeros({threads, n, C}, means2d.options()) : at::Tensor();
  auto v_bg_tiles = at::zeros({tiles, C}, means2d.options());
  auto v_colors = per_thread ? at::Tensor() : at::zeros({n, C}, means2d.options());
  const auto m_c = means2d.contiguous(), c_c = conics.contiguous(), o_c = opacities.contiguous(),
             t_c = tile_offsets.contiguous(), i_c = gaussian_ids.contiguous(),
             n_c = n_contrib.contiguous(), vc_c = v_color.contiguous();
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_backward_colors_cpu", [&] {
    using T = scalar_t;
    const Scene2D<T> s = make_scene<T>(m_c, c_c, o_c, at::Tensor(), t_c, i_c, a, train);
    at::parallel_for(0, tiles, tile_grain(tiles, m), [&](int64_t b, int64_t e) {
      T* mine = per_thread ? partial.data_ptr<T>() + int64_t(at::get_thread_num()) * n * C : nullptr;
      for (int64_t t = b; t < e; ++t)
        backward_colors_tile<T>(s, t, C, n_c.data_ptr<int32_t>(), vc_c.data_ptr<T>(),
                                per_thread ? nullptr : rows.data_ptr<T>(), mine,
                                v_bg_tiles.data_ptr<T>() + t * C);
    });
    if (!per_thread)
      reduce_rows<T>(rows.data_ptr<T>(), m, C, i_c.data_ptr<int32_t>(), v_colors.data_ptr<T>());
  });
  if (per_thread) v_colors = threads == 1 ? partial[0] : partial.sum(0);
  return {v_colors, v_bg_tiles.sum(0)};
}

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("rasterize", &rasterize_cpu);
  m.impl("rasterize_backward", &rasterize_backward_cpu);
  m.impl("rasterize_backward_colors", &rasterize_backward_colors_cpu);
}

}  // namespace tiger
