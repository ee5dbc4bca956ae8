#pragma once
// Tile binning: which Gaussians touch which 16x16 tile, front to back.
//
// bin_gaussians: means2d [N,2], conics [N,3], opacities [N], depths [N], radii [N,2] int32
//   (from project_gaussians; radii 0 = culled), image width/height, tile_size,
//   alpha_threshold (a tile is kept only if the ellipse reaches o*G >= threshold there)
//   -> tile_offsets [tiles_y*tiles_x + 1] int64 (row-major tiles; list of tile t is
//      gaussian_ids[tile_offsets[t] : tile_offsets[t+1]]),
//      gaussian_ids [M] int32 sorted by (tile, depth, id).
//   The CUDA kernel's choices (binning_choices.h; the lists are identical whichever runs):
//   path "auto" | "tiles" | "global", block_sort_keys, warp_sort_keys, giant_tiles, and
//   _serial (every Gaussian walked by one thread: the former walk, for comparisons). The CPU
//   kernel has one walk and only checks them.
//   views (default 1): the N Gaussians are V consecutive blocks of N / V, block v projected
//   into image v of V images of width x height; the tiles are V consecutive grids (image v's
//   tile (ty, tx) is v * tiles_y * tiles_x + ty * tiles_x + tx) and a Gaussian of block v is
//   listed only in image v's tiles: the tile lists of rasterize(views=V). Each image's lists
//   are those of a views=1 call on its block (ids offset by v * N / V).
#include <ATen/ATen.h>

#include <c10/util/string_view.h>

#include <tuple>

#include "binning_choices.h"

namespace tiger {

void check_binning_inputs(const char* op, const at::Tensor& means2d, const at::Tensor& conics,
                          const at::Tensor& opacities, const at::Tensor& depths,
                          const at::Tensor& radii, int64_t width, int64_t height, int64_t tile_size);

// Rejects views < 1 or a Gaussian count n that views does not divide.
void check_binning_views(const char* op, int64_t n, int64_t views);

// Rejects kernel choices outside their bounds (binning_choices.h), naming the argument.
void check_binning_choices(const char* op, c10::string_view path, int64_t block_sort_keys,
                           int64_t warp_sort_keys, int64_t giant_tiles);

std::tuple<at::Tensor, at::Tensor> bin_gaussians_cpu(const at::Tensor& means2d,
                                                     const at::Tensor& conics,
                                                     const at::Tensor& opacities,
                                                     const at::Tensor& depths, const at::Tensor& radii,
                                                     int64_t width, int64_t height, int64_t tile_size,
                                                     double alpha_threshold, c10::string_view path,
                                                     int64_t block_sort_keys, int64_t warp_sort_keys,
                                                     int64_t giant_tiles, bool serial,
                                                     int64_t views);

}  // namespace tiger
