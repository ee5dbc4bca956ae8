// Schema of the tile-binning op (kernels: binning_cpu.cpp, binning_cuda.cpp).
#include <torch/library.h>

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

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def(
      "bin_gaussians(Tensor means2d, Tensor conics, Tensor opacities, Tensor depths, "
      "Tensor radii, int width, int height, int tile_size, float alpha_threshold) "
      "-> (Tensor tile_offsets, Tensor gaussian_ids)");
}

}  // namespace tiger
