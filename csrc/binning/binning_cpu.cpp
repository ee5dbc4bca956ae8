// CPU tile binning: count and list (tile, Gaussian) pairs in parallel (ranges of equal
// candidate-tile counts, not of equal Gaussian counts), bucket
// them by tile with a counting sort (stable, so ids stay ascending), then sort
// each tile's list by depth in parallel.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "binning.h"
#include "common/raster_math.h"
#include "common/torch_checks.h"

namespace tiger {

namespace {
// Splits [0, n) into about `parts` ranges of similar total cost (cost_ends = inclusive
// scan of per-item costs), so that threads get equal numbers of tile tests rather than
// equal numbers of Gaussians (a few Gaussians can cover thousands of tiles each).
std::vector<int64_t> balanced_bounds(const std::vector<int64_t>& cost_ends, int64_t parts) {
  const int64_t n = int64_t(cost_ends.size());
  const int64_t total = n ? cost_ends.back() : 0;
  std::vector<int64_t> bounds{0};
  for (int64_t p = 1; p < parts; ++p) {
    const int64_t target = total / parts * p + std::min<int64_t>(p, total % parts);
    const int64_t b = std::upper_bound(cost_ends.begin(), cost_ends.end(), target) - cost_ends.begin();
    if (b > bounds.back() && b < n) bounds.push_back(b);
  }
  bounds.push_back(n);
  return bounds;
}
}  // namespace

std::tuple<at::Tensor, at::Tensor> bin_gaussians_cpu(const at::Tensor& means2d,
                                                     const at::Tensor& conics,
                                                     const at::Tensor& opacities,
                                                     const at::Tensor& depths, const at::Tensor& radii,
                                                     int64_t width, int64_t height, int64_t tile_size,
                                                     double alpha_threshold, c10::string_view path,
                                                     int64_t block_sort_keys, int64_t warp_sort_keys,
                                                     int64_t giant_tiles, bool /*serial*/,
                                                     int64_t views) {
  check_binning_inputs("tiger.bin_gaussians", means2d, conics, opacities, depths, radii, width,
                       height, tile_size);
  // One walk on the CPU: the CUDA kernel choices are only checked (same errors on every device).
  check_binning_choices("tiger.bin_gaussians", path, block_sort_keys, warp_sort_keys, giant_tiles);
  const int64_t n = means2d.size(0);
  check_binning_views("tiger.bin_gaussians", n, views);
  const int64_t per_view = n / views;  // Gaussian i is in image i / per_view
  const int ts = static_cast<int>(tile_size);
  const int tiles_x = static_cast<int>((width + ts - 1) / ts);
  const int tiles_y = static_cast<int>((height + ts - 1) / ts);
  const int64_t view_tiles = int64_t(tiles_x) * tiles_y;
  const int64_t n_tiles = views * view_tiles;
  TORCH_CHECK(n_tiles < (int64_t(1) << 31), "tiger.bin_gaussians: ", views, " images of ",
              view_tiles, " tiles are more than 2^31 tiles");
  auto tile_offsets = at::zeros({n_tiles + 1}, means2d.options().dtype(at::kLong));
  const auto m_c = means2d.contiguous(), c_c = conics.contiguous(), o_c = opacities.contiguous(),
             d_c = depths.contiguous(), r_c = radii.contiguous();
  std::vector<int64_t> g_offsets(n + 1, 0);
  std::vector<int32_t> pair_tiles;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cpu", [&] {
    using T = scalar_t;
    const T *mp = m_c.data_ptr<T>(), *cp = c_c.data_ptr<T>(), *op = o_c.data_ptr<T>();
    const int32_t* rp = r_c.data_ptr<int32_t>();
    // Pass 1 counts, pass 2 writes: both visit a Gaussian's tiles the same way.
    auto visit = [&](int64_t i, auto&& emit) {
      if (rp[2 * i] <= 0 || rp[2 * i + 1] <= 0) return;
      const T u = mp[2 * i], v = mp[2 * i + 1];
      const TileRect r = tile_rect(u, v, rp[2 * i], rp[2 * i + 1], ts, tiles_x, tiles_y);
      const T qcut = cutoff_quadratic<T>(op[i], T(alpha_threshold));
      const int64_t first = i / per_view * view_tiles;  // its image's first tile
      for (int ty = r.y0; ty < r.y1; ++ty)
        for (int tx = r.x0; tx < r.x1; ++tx) {
          const int px0 = tx * ts, py0 = ty * ts;
          const int px1 = std::min<int>(px0 + ts, width), py1 = std::min<int>(py0 + ts, height);
          if (tile_touches<T>(u, v, cp[3 * i], cp[3 * i + 1], cp[3 * i + 2], qcut, px0, px1, py0, py1))
            emit(int32_t(first + ty * tiles_x + tx));
        }
    };
    // Work ranges of equal candidate-tile counts (+1 per Gaussian for its fixed cost).
    std::vector<int64_t> cost_ends(n);
    at::parallel_for(0, n, 16384, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        cost_ends[i] = 1 + ((rp[2 * i] > 0 && rp[2 * i + 1] > 0)
                                ? tile_rect(mp[2 * i], mp[2 * i + 1], rp[2 * i], rp[2 * i + 1], ts,
                                            tiles_x, tiles_y).count()
                                : 0);
    });
    for (int64_t i = 1; i < n; ++i) cost_ends[i] += cost_ends[i - 1];
    const int64_t total_cost = n ? cost_ends[n - 1] : 0;
    const int64_t parts = total_cost < 65536 ? 1 : 8 * int64_t(at::get_num_threads());
    const std::vector<int64_t> bounds = balanced_bounds(cost_ends, parts);
    const int64_t n_parts = int64_t(bounds.size()) - 1;
    at::parallel_for(0, n_parts, 1, [&](int64_t pb, int64_t pe) {
      for (int64_t i = bounds[pb]; i < bounds[pe]; ++i) {
        int64_t c = 0;
        visit(i, [&](int32_t) { ++c; });
        g_offsets[i + 1] = c;
      }
    });
    for (int64_t i = 0; i < n; ++i) g_offsets[i + 1] += g_offsets[i];
    pair_tiles.resize(g_offsets[n]);
    at::parallel_for(0, n_parts, 1, [&](int64_t pb, int64_t pe) {
      for (int64_t i = bounds[pb]; i < bounds[pe]; ++i) {
        int64_t k = g_offsets[i];
        visit(i, [&](int32_t t) { pair_tiles[k++] = t; });
      }
    });
  });
  const int64_t m = g_offsets[n];
  auto gaussian_ids = at::empty({m}, means2d.options().dtype(at::kInt));
  int64_t* to = tile_offsets.data_ptr<int64_t>();
  for (int64_t k = 0; k < m; ++k) ++to[pair_tiles[k] + 1];
  for (int64_t t = 0; t < n_tiles; ++t) to[t + 1] += to[t];
  {
    std::vector<int64_t> cursor(to, to + n_tiles);
    int32_t* ids = gaussian_ids.data_ptr<int32_t>();
    for (int64_t i = 0; i < n; ++i)
      for (int64_t k = g_offsets[i]; k < g_offsets[i + 1]; ++k) ids[cursor[pair_tiles[k]]++] = int32_t(i);
  }
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cpu_sort", [&] {
    using T = scalar_t;
    const T* dp = d_c.data_ptr<T>();
    int32_t* ids = gaussian_ids.data_ptr<int32_t>();
    at::parallel_for(0, n_tiles, m < 16384 ? std::max<int64_t>(n_tiles, 1) : 16, [&](int64_t b, int64_t e) {
      for (int64_t t = b; t < e; ++t)
        std::stable_sort(ids + to[t], ids + to[t + 1],
                         [&](int32_t a, int32_t c) { return dp[a] < dp[c]; });
    });
  });
  return {tile_offsets, gaussian_ids};
}

TORCH_LIBRARY_IMPL(tiger, CPU, m) { m.impl("bin_gaussians", &bin_gaussians_cpu); }

}  // namespace tiger
