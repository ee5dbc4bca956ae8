#pragma once
// ATen-side checks of the components family.
#include <ATen/ATen.h>

#include <limits>

namespace tiger {
namespace components {

inline void check_masks(const at::Tensor& masks, const char* op) {
  TORCH_CHECK(masks.dim() == 3, op, ": masks must be [M, H, W], got ", masks.sizes());
  TORCH_CHECK(masks.scalar_type() == at::kBool, op, ": masks must be bool, got ", masks.scalar_type());
  TORCH_CHECK(masks.size(1) * masks.size(2) < std::numeric_limits<int32_t>::max(), op, ": masks of ",
              masks.size(1), "x", masks.size(2), " pixels exceed the int32 labels");
}

inline void check_area(int64_t area_threshold) {
  TORCH_CHECK(area_threshold >= 0, "tiger.remove_small_regions: area_threshold must be >= 0, got ",
              area_threshold);
}

}  // namespace components
}  // namespace tiger
