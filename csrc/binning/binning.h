#pragma once
// Tile binning: which Gaussians touch which 16x16 tile, front to back.
//
// bin_gaussians: means2d [N,2], conics [N,3], opacities [N], depths [N], radii [N,2] int32
//   (from project_gaussians; radii 0 = culled), image width/height, tile_size,
//   alpha_threshold (a tile is kept only if the ellipse reaches o*G >= threshold there)
//   -> tile_offsets [tiles_y*tiles_x + 1] int64 (row-major tiles; list of tile t is
//      gaussian_ids[tile_offsets[t] : tile_offsets[t+1]]),
//      gaussian_ids [M] int32 sorted by (tile, depth, id).
#include <ATen/ATen.h>

#include <tuple>

namespace tiger {

void check_binning_inputs(const char* op, const at::Tensor& means2d, const at::Tensor& conics,
                          const at::Tensor& opacities, const at::Tensor& depths,
                          const at::Tensor& radii, int64_t width, int64_t height, int64_t tile_size);

std::tuple<at::Tensor, at::Tensor> bin_gaussians_cpu(const at::Tensor& means2d,
                                                     const at::Tensor& conics,
                                                     const at::Tensor& opacities,
                                                     const at::Tensor& depths, const at::Tensor& radii,
                                                     int64_t width, int64_t height, int64_t tile_size,
                                                     double alpha_threshold);

}  // namespace tiger
