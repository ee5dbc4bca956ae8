// Schemas of the rasterization ops (kernels: raster_cpu.cpp, raster_cuda.cpp).
#include <torch/library.h>

#include <string>

#include "common/torch_checks.h"
#include "raster.h"

namespace tiger {

void check_raster_inputs(const char* op, const at::Tensor& means2d, const at::Tensor& conics,
                         const at::Tensor& opacities, const at::Tensor& depths,
                         const std::optional<at::Tensor>& background, int64_t channels,
                         const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids,
                         const RasterArgs& a) {
  TORCH_CHECK(means2d.scalar_type() == at::kFloat || means2d.scalar_type() == at::kDouble, op,
              ": means2d must be float32 or float64, got ", means2d.scalar_type());
  check_shape(means2d, op, "means2d", {-1, 2});
  const int64_t n = means2d.size(0);
  check_shape(conics, op, "conics", {n, 3});
  check_shape(opacities, op, "opacities", {n});
  check_shape(depths, op, "depths", {n});
  check_same(conics, means2d, op, "conics");
  check_same(opacities, means2d, op, "opacities");
  check_same(depths, means2d, op, "depths");
  TORCH_CHECK(channels >= 1, op, ": colors must have at least one channel");
  if (background.has_value()) {
    check_shape(*background, op, "background", {channels});
    check_same(*background, means2d, op, "background");
  }
  TORCH_CHECK(a.width > 0 && a.height > 0, op, ": width and height must be positive, got ", a.width,
              "x", a.height);
  TORCH_CHECK(a.tile_size >= 1 && a.tile_size <= 64, op, ": tile_size must be in [1, 64]");
  TORCH_CHECK(a.views >= 1, op, ": views must be at least 1, got ", a.views);
  const int64_t tiles = a.views * ((a.width + a.tile_size - 1) / a.tile_size) *
                        ((a.height + a.tile_size - 1) / a.tile_size);
  check_shape(tile_offsets, op, "tile_offsets", {tiles + 1});
  check_dtype(tile_offsets, at::kLong, op, "tile_offsets");
  check_shape(gaussian_ids, op, "gaussian_ids", {-1});
  check_dtype(gaussian_ids, at::kInt, op, "gaussian_ids");
  TORCH_CHECK(a.alpha_max > 0 && a.alpha_max < 1, op, ": alpha_max must be in (0, 1), got ",
              a.alpha_max);
  TORCH_CHECK(a.alpha_threshold >= 0 && a.alpha_threshold < a.alpha_max, op,
              ": alpha_threshold must be in [0, alpha_max), got ", a.alpha_threshold);
  TORCH_CHECK(a.t_min >= 0 && a.t_min < 1, op, ": t_min must be in [0, 1), got ", a.t_min);
}

void check_channel_block(const char* op, const char* name, int64_t channel_block) {
  TORCH_CHECK(channel_block == kRasterChannelBlock || channel_block == 32, op, ": ", name,
              " must be ", kRasterChannelBlock, " or 32 (the compiled float32 channel blocks), got ",
              channel_block);
}

void check_pixels_per_thread(const char* op, const char* name, int64_t pixels_per_thread) {
  TORCH_CHECK(pixels_per_thread == 1 || pixels_per_thread == 2, op, ": ", name,
              " must be 1 or 2, got ", pixels_per_thread);
}

// The kernel choices' defaults come from raster.h (tiger.ops.raster.RasterKernelSettings repeats
// them; tests/ops/test_raster.py compares the two).
void check_tile_order(const char* op, int64_t tile_order) {
  TORCH_CHECK(tile_order == kTileOrderIndex || tile_order == kTileOrderHeavyFirst, op,
              ": tile_order must be ", kTileOrderIndex, " (index order) or ", kTileOrderHeavyFirst,
              " (longest tile lists first), got ", tile_order);
}

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  const std::string cb = std::to_string(kRasterChannelBlock);
  const std::string ppt = std::to_string(kRasterPixelsPerThread);
  const std::string order = ", int tile_order=" + std::to_string(kRasterTileOrder) +
                            ", bool warp_cull=" + (kRasterWarpCull ? "True" : "False");
  m.def((
      "rasterize(Tensor means2d, Tensor conics, Tensor opacities, Tensor colors, Tensor depths, "
      "Tensor? background, Tensor tile_offsets, Tensor gaussian_ids, int width, int height, "
      "int tile_size, float alpha_max, float alpha_threshold, float t_min, int channel_block=" + cb +
      ", int backward_channel_block=" + cb + ", int colors_channel_block=" + cb +
      ", int backward_pixels_per_thread=" + ppt + ", int views=1, Tensor? trainable=None" + order +
      ") -> (Tensor color, Tensor alpha, Tensor depth, Tensor n_contrib, Tensor transmittance)")
            .c_str());
  m.def((
      "rasterize_backward(Tensor means2d, Tensor conics, Tensor opacities, Tensor colors, "
      "Tensor depths, Tensor? background, Tensor tile_offsets, Tensor gaussian_ids, int width, "
      "int height, int tile_size, float alpha_max, float alpha_threshold, float t_min, "
      "Tensor transmittance, Tensor n_contrib, Tensor v_color, Tensor? v_alpha, Tensor? v_depth, "
      "int channel_block=" + cb + ", int pixels_per_thread=" + ppt + ", int views=1, "
      "Tensor? trainable=None" + order + ") -> (Tensor v_geometry, Tensor v_colors, Tensor v_background)")
            .c_str());
  m.def((
      "rasterize_backward_colors(Tensor means2d, Tensor conics, Tensor opacities, "
      "Tensor tile_offsets, Tensor gaussian_ids, int width, int height, int tile_size, "
      "float alpha_max, float alpha_threshold, float t_min, Tensor n_contrib, Tensor v_color, "
      "int channel_block=" + cb + ", int views=1, Tensor? trainable=None" + order +
      ") -> (Tensor v_colors, Tensor v_background)")
            .c_str());
}

}  // namespace tiger
