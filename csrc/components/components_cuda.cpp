// Torch glue of the CUDA components kernels (built only with CUDA).
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <algorithm>
#include <tuple>

#include "components/components.h"
#include "components/components_glue.h"

namespace tiger {
namespace components {
namespace {

// Masks per launch: bounds the int32 scratch (three arrays of chunk x H x W) near 1.5 GiB.
int64_t chunk_masks(int64_t h, int64_t w) { return std::max<int64_t>(1, (int64_t(1) << 27) / std::max<int64_t>(1, h * w)); }

at::Tensor connected_components_cuda(const at::Tensor& masks_in) {
  check_masks(masks_in, "tiger.connected_components");
  TORCH_CHECK(masks_in.is_cuda(), "tiger.connected_components (CUDA): masks must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(masks_in.device());
  const auto masks = masks_in.contiguous();
  const int64_t M = masks.size(0), H = masks.size(1), W = masks.size(2), n = H * W;
  auto labels = at::empty({M, H, W}, masks.options().dtype(at::kInt));
  const int64_t chunk = std::min(M, chunk_masks(H, W));
  if (M == 0 || n == 0) return labels;
  auto local_size = at::empty({chunk * n}, labels.options());
  auto sizes = at::empty({chunk * n}, labels.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  for (int64_t m0 = 0; m0 < M; m0 += chunk) {
    const int64_t mc = std::min(chunk, M - m0);
    sizes.zero_();
    launch_label(masks.data_ptr<bool>() + m0 * n, false, mc, H, W, labels.data_ptr<int32_t>() + m0 * n,
                 local_size.data_ptr<int32_t>(), sizes.data_ptr<int32_t>(), stream);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return labels;
}

std::tuple<at::Tensor, at::Tensor> remove_small_regions_cuda(const at::Tensor& masks_in, int64_t area_threshold) {
  check_masks(masks_in, "tiger.remove_small_regions");
  check_area(area_threshold);
  TORCH_CHECK(masks_in.is_cuda(), "tiger.remove_small_regions (CUDA): masks must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(masks_in.device());
  const auto masks = masks_in.contiguous();
  const int64_t M = masks.size(0), H = masks.size(1), W = masks.size(2), n = H * W;
  auto out = at::empty_like(masks);
  auto changed = at::zeros({M}, masks.options());
  if (M == 0 || n == 0) return {out, changed};
  const int64_t chunk = std::min(M, chunk_masks(H, W));
  const auto iopt = masks.options().dtype(at::kInt);
  auto labels = at::empty({chunk * n}, iopt);
  auto local_size = at::empty({chunk * n}, iopt);
  auto sizes = at::empty({chunk * n}, iopt);
  auto filled = at::empty({chunk * n}, masks.options());
  auto has_big = at::empty({chunk}, iopt);
  auto best = at::empty({chunk}, masks.options().dtype(at::kLong));
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  auto* best_ptr = reinterpret_cast<unsigned long long*>(best.data_ptr<int64_t>());
  for (int64_t m0 = 0; m0 < M; m0 += chunk) {
    const int64_t mc = std::min(chunk, M - m0);
    const bool* src = masks.data_ptr<bool>() + m0 * n;
    bool* chg = changed.data_ptr<bool>() + m0;
    // holes: components of ~mask, small ones filled
    sizes.zero_(), has_big.zero_(), best.zero_();
    launch_label(src, true, mc, H, W, labels.data_ptr<int32_t>(), local_size.data_ptr<int32_t>(),
                 sizes.data_ptr<int32_t>(), stream);
    launch_small_region_step(src, true, mc, H, W, labels.data_ptr<int32_t>(), sizes.data_ptr<int32_t>(),
                             area_threshold, chg, has_big.data_ptr<int32_t>(), best_ptr, filled.data_ptr<bool>(),
                             stream);
    // islands: components of the filled mask, small ones dropped
    sizes.zero_(), has_big.zero_(), best.zero_();
    launch_label(filled.data_ptr<bool>(), false, mc, H, W, labels.data_ptr<int32_t>(),
                 local_size.data_ptr<int32_t>(), sizes.data_ptr<int32_t>(), stream);
    launch_small_region_step(filled.data_ptr<bool>(), false, mc, H, W, labels.data_ptr<int32_t>(),
                             sizes.data_ptr<int32_t>(), area_threshold, chg, has_big.data_ptr<int32_t>(), best_ptr,
                             out.data_ptr<bool>() + m0 * n, stream);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return {out, changed};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("connected_components", &connected_components_cuda);
  m.impl("remove_small_regions", &remove_small_regions_cuda);
}

}  // namespace components
}  // namespace tiger
