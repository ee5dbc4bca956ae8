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
//   views (default 1): V images of width x height in one call, stacked along the rows: every
//   per-pixel tensor (outputs, transmittance, n_contrib, v_color, ...) is [V*H, W(, C)] and
//   tile_offsets has V*tiles_y*tiles_x + 1 entries (bin_gaussians(views=V)); image v's tiles
//   come after image v-1's and its pixels are evaluated at their own coordinates, so each image
//   is bit-identical to a views=1 call with its own Gaussians.
// rasterize_backward: gradients from v_color [H,W,C], v_alpha [H,W] or None, v_depth [H,W] or
//   None (None: zero, nothing is read); walks each list back to front. Returns v_geometry [N,8]
//   (per row: means2d u, v, conics a, b, c, opacity, depth, 0: one buffer that the CUDA kernel
//   accumulates into, handed on as column views without copies), v_colors [N,C] and
//   v_background [C].
// rasterize_backward_colors: the features-only backward: gradients w.r.t. colors and
//   background only (geometry and opacity frozen); walks front to back, no division.
// trainable (optional, all three ops): bool [N] (N the stacked count with views > 1): the
//   Gaussians whose gradients are wanted. The backward ops still walk the frozen Gaussians
//   behind a trainable one (they shape the transmittance and the colour behind), but add no
//   gradient for a frozen one: its rows of v_geometry and v_colors are zero, and on CUDA it
//   costs no reduction and no atomics. On CUDA the full backward's back-to-front walk of a tile
//   also stops at its front-most trainable Gaussian, and tiles without one only add their
//   background gradient (an edit's views: most tiles). The trainable ones' gradients are those
//   of the full backward (the same sums; on CUDA up to the atomics' order). rasterize only
//   checks and carries it for its autograd formula.
//
// Kernel choices of the CUDA kernels (op arguments, float32 only: float64 runs blocks of 8
// channels, one pixel per thread; the CPU kernels only check them). Every choice gives the same
// result up to float32 rounding:
//   channel_block: the largest channel block held in registers, kRasterChannelBlock or 32.
//     rasterize takes one per kernel (channel_block for itself, backward_channel_block and
//     colors_channel_block for the backward ops, which its autograd formula calls with them).
//   pixels_per_thread (backward): kRasterPixelsPerThread where they apply (16-px tiles,
//     channel blocks of at most 16), or 1.
//   tile_order (all three ops): the order the CUDA kernels draw tiles in, kTileOrderIndex or
//     kTileOrderHeavyFirst (the default): tiles with longer lists first (within a factor of
//     sqrt 2), so that the longest walks do not run alone at the end of the kernel. Only the
//     order of the blocks changes: the forward's values are the same bit for bit, the backward's
//     up to the order of its atomic sums.
//   warp_cull (all three ops, default kRasterWarpCull): each warp of a tile's block walks only
//     the list entries whose cutoff ellipse may reach one of its own pixel centres (the exact
//     minimum of the conic along each of its pixel rows, with a rounding margin). The backward
//     walks, either way, take only entries below the warp's pixels' largest n_contrib. The
//     entries skipped are those every pixel of the warp would skip: the values are the same bit
//     for bit.
#include <ATen/ATen.h>

#include <optional>
#include <tuple>

namespace tiger {

struct RasterArgs {
  int64_t width, height, tile_size;
  double alpha_max, alpha_threshold, t_min;
  // Images drawn in one call: `views` images of width x height stacked along the rows (outputs
  // [views * height, width, ...]); tile t belongs to image t / tiles_per_view, whose pixels are
  // evaluated at their own image's coordinates (bin_gaussians(views=) makes such tile lists).
  int64_t views = 1;
};

// Defaults: the measured best on the H100 (docs/BENCHMARKS.md). 64-channel blocks walk a
// C <= 64 list once; two pixels per backward thread cut the float32 C = 3 backward of 1M
// Gaussians at 1080x1920 from 3.09 to 2.28 ms per training step.
constexpr int64_t kRasterChannelBlock = 64;
constexpr int64_t kRasterPixelsPerThread = 2;
constexpr int64_t kTileOrderIndex = 0;
constexpr int64_t kTileOrderHeavyFirst = 1;
constexpr int64_t kRasterTileOrder = kTileOrderHeavyFirst;
constexpr bool kRasterWarpCull = true;

// Rejects a channel block other than 64 or 32, or pixels_per_thread other than 1 or 2, naming
// the argument.
void check_channel_block(const char* op, const char* name, int64_t channel_block);
void check_pixels_per_thread(const char* op, const char* name, int64_t pixels_per_thread);
void check_tile_order(const char* op, int64_t tile_order);

void check_raster_inputs(const char* op, const at::Tensor& means2d, const at::Tensor& conics,
                         const at::Tensor& opacities, const at::Tensor& depths,
                         const std::optional<at::Tensor>& background, int64_t channels,
                         const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids,
                         const RasterArgs& a);

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> rasterize_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& colors, const at::Tensor& depths, const std::optional<at::Tensor>& background,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min,
    int64_t channel_block, int64_t backward_channel_block, int64_t colors_channel_block,
    int64_t backward_pixels_per_thread, int64_t views, const std::optional<at::Tensor>& trainable,
    int64_t tile_order, bool warp_cull);

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
                       const std::optional<at::Tensor>& trainable, int64_t tile_order, bool warp_cull);

std::tuple<at::Tensor, at::Tensor> rasterize_backward_colors_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min,
    const at::Tensor& n_contrib, const at::Tensor& v_color, int64_t channel_block, int64_t views,
    const std::optional<at::Tensor>& trainable, int64_t tile_order, bool warp_cull);

}  // namespace tiger
