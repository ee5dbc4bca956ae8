#pragma once
// Tile-based front-to-back alpha compositing of projected Gaussians.
//
// rasterize: means2d [N,2], conics [N,3], opacities [N], colors [N,C] (any C >= 1),
//   depths [N], background [C] or None, tile_offsets / gaussian_ids from bin_gaussians,
//   width, height, tile_size, alpha_max, alpha_threshold, t_min
//   -> color [H,W,C] = sum_i c_i a_i T_i + T_final * background,
//      alpha [H,W] = 1 - T_final, depth [H,W] = sum_i z_i a_i T_i (not normalised),
//      n_contrib [H,W] int32: entries of the pixel's tile list up to its last contributor,
//      transmittance [H,W] = T_final, kept apart from alpha because 1 - (1 - T) loses
//      T's relative precision in float32 where pixels saturate.
// rasterize_backward: gradients from v_color [H,W,C], v_alpha [H,W] or None, v_depth [H,W] or
//   None (None: zero, nothing is read); walks each list back to front. Returns v_geometry [N,8]
//   (per row: means2d u, v, conics a, b, c, opacity, depth, 0: one buffer that the CUDA kernel
//   accumulates into, handed on as column views without copies), v_colors [N,C] and
//   v_background [C].
// rasterize_backward_colors: the features-only backward: gradients w.r.t. colors and
//   background only (geometry and opacity frozen); walks front to back, no division.
#include <ATen/ATen.h>

#include <optional>
#include <tuple>

namespace tiger {

struct RasterArgs {
  int64_t width, height, tile_size;
  double alpha_max, alpha_threshold, t_min;
};

void check_raster_inputs(const char* op, const at::Tensor& means2d, const at::Tensor& conics,
                         const at::Tensor& opacities, const at::Tensor& depths,
                         const std::optional<at::Tensor>& background, int64_t channels,
                         const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids,
                         const RasterArgs& a);

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> rasterize_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& colors, const at::Tensor& depths, const std::optional<at::Tensor>& background,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min);

std::tuple<at::Tensor, at::Tensor, at::Tensor>
rasterize_backward_cpu(const at::Tensor& means2d, const at::Tensor& conics,
                       const at::Tensor& opacities, const at::Tensor& colors,
                       const at::Tensor& depths, const std::optional<at::Tensor>& background,
                       const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width,
                       int64_t height, int64_t tile_size, double alpha_max, double alpha_threshold,
                       double t_min, const at::Tensor& transmittance, const at::Tensor& n_contrib,
                       const at::Tensor& v_color, const std::optional<at::Tensor>& v_alpha,
                       const std::optional<at::Tensor>& v_depth);

std::tuple<at::Tensor, at::Tensor> rasterize_backward_colors_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min,
    const at::Tensor& n_contrib, const at::Tensor& v_color);

}  // namespace tiger
