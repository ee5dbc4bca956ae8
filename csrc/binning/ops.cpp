// Schema of the tile-binning op (kernels: binning_cpu.cpp, binning_cuda.cpp).
#include <torch/library.h>

#include <string>

#include "binning.h"
#include "common/torch_checks.h"

namespace tiger {

void check_binning_inputs(const char* op, const at::Tensor& means2d, const at::Tensor& conics,
                          const at::Tensor& opacities, const at::Tensor& depths,
                          const at::Tensor& radii, int64_t width, int64_t height, int64_t tile_size) {
  TORCH_CHECK(means2d.scalar_type() == at::kFloat || means2d.scalar_type() == at::kDouble, op,
              ": means2d must be float32 or float64, got ", means2d.scalar_type());
  check_shape(means2d, op, "means2d", {-1, 2});
  const int64_t n = means2d.size(0);
  check_shape(conics, op, "conics", {n, 3});
  check_shape(opacities, op, "opacities", {n});
  check_shape(depths, op, "depths", {n});
  check_shape(radii, op, "radii", {n, 2});
  check_same(conics, means2d, op, "conics");
  check_same(opacities, means2d, op, "opacities");
  check_same(depths, means2d, op, "depths");
  check_dtype(radii, at::kInt, op, "radii");
  TORCH_CHECK(radii.device() == means2d.device(), op, ": radii must be on ", means2d.device());
  TORCH_CHECK(width > 0 && height > 0, op, ": width and height must be positive, got ", width, "x",
              height);
  TORCH_CHECK(tile_size >= 1 && tile_size <= 64, op, ": tile_size must be in [1, 64], got ",
              tile_size);
}

void check_binning_views(const char* op, int64_t n, int64_t views) {
  TORCH_CHECK(views >= 1, op, ": views must be at least 1, got ", views);
  TORCH_CHECK(n % views == 0, op, ": views=", views, " must divide the number of Gaussians (",
              n, "): they are views consecutive blocks of one view's Gaussians each");
}

void check_binning_choices(const char* op, c10::string_view path, int64_t block_sort_keys,
                           int64_t warp_sort_keys, int64_t giant_tiles) {
  TORCH_CHECK(path == "auto" || path == "tiles" || path == "global", op,
              ": path must be 'auto', 'tiles' or 'global', got '", std::string(path), "'");
  TORCH_CHECK(block_sort_keys >= 2 && block_sort_keys <= kBinSortKeysMax &&
                  (block_sort_keys & (block_sort_keys - 1)) == 0,
              op, ": block_sort_keys must be a power of two in [2, ", kBinSortKeysMax, "], got ",
              block_sort_keys);
  TORCH_CHECK(warp_sort_keys >= 1 && warp_sort_keys <= kWarpSortKeys, op,
              ": warp_sort_keys must be in [1, ", kWarpSortKeys, "], got ", warp_sort_keys);
  TORCH_CHECK(giant_tiles >= 1, op, ": giant_tiles must be at least 1, got ", giant_tiles);
}

// The kernel choices' defaults come from binning_choices.h (tiger.ops.binning.BinningSettings
// repeats them; tests/ops/test_binning.py compares the two).
TORCH_LIBRARY_FRAGMENT(tiger, m) {
  const std::string schema =
      "bin_gaussians(Tensor means2d, Tensor conics, Tensor opacities, Tensor depths, "
      "Tensor radii, int width, int height, int tile_size, float alpha_threshold, "
      "str path=\"auto\", int block_sort_keys=" + std::to_string(kBinSortKeysMax) +
      ", int warp_sort_keys=" + std::to_string(kWarpSortKeys) +
      ", int giant_tiles=" + std::to_string(kBinGiantTiles) +
      ", bool _serial=False, int views=1) -> (Tensor tile_offsets, Tensor gaussian_ids)";
  m.def(schema.c_str());
}

}  // namespace tiger
