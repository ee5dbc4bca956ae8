#pragma once
// ATen-side argument checks shared by the CPU and CUDA implementations.
#include <ATen/ATen.h>

namespace tiger {
namespace masked_average {

inline void check_features_ids(const at::Tensor& features, const at::Tensor& ids, const char* name) {
  TORCH_CHECK(features.dim() == 2, "tiger.masked_average: ", name, " must be [P, C], got ",
              features.sizes());
  TORCH_CHECK(features.scalar_type() == at::kFloat || features.scalar_type() == at::kDouble,
              "tiger.masked_average: ", name, " must be float32 or float64, got ",
              features.scalar_type());
  TORCH_CHECK(ids.dim() == 1 && ids.size(0) == features.size(0),
              "tiger.masked_average: ids must be [P] with P = ", features.size(0), ", got ",
              ids.sizes());
  TORCH_CHECK(ids.scalar_type() == at::kLong, "tiger.masked_average: ids must be int64, got ",
              ids.scalar_type());
  TORCH_CHECK(ids.device() == features.device(), "tiger.masked_average: ids (", ids.device(),
              ") and ", name, " (", features.device(), ") must be on one device");
}

// ids must lie in [-1, M): checked on the host once per call (cheap next to the reduction).
inline void check_id_range(const at::Tensor& ids, int64_t num_masks) {
  TORCH_CHECK(num_masks >= 0, "tiger.masked_average: num_masks must be >= 0, got ", num_masks);
  if (ids.numel() == 0) return;
  const auto mn = ids.min().item<int64_t>();
  const auto mx = ids.max().item<int64_t>();
  TORCH_CHECK(mn >= -1 && mx < num_masks, "tiger.masked_average: ids must lie in [-1, num_masks = ",
              num_masks, "), got values in [", mn, ", ", mx, "]");
}

}  // namespace masked_average
}  // namespace tiger
