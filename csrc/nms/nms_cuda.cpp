// Torch glue of the CUDA nms kernels (built only with CUDA).
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAStream.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <vector>

#include "nms/nms.h"
#include "nms/nms_glue.h"

namespace tiger {
namespace nms {
namespace {

// The O(N^2) IoU tests run on the GPU as bitmasks; the greedy walk over them (N^2/64 word ops)
// runs on the host, as in torchvision.
at::Tensor box_nms_cuda(const at::Tensor& boxes_in, const at::Tensor& scores, double iou_threshold) {
  check_boxes(boxes_in, scores, iou_threshold);
  TORCH_CHECK(boxes_in.is_cuda(), "tiger.box_nms (CUDA): boxes must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(boxes_in.device());
  const int64_t n = boxes_in.size(0);
  if (n == 0) return at::empty({0}, scores.options().dtype(at::kLong));
  const auto order = std::get<1>(scores.sort(/*stable=*/true, 0, /*descending=*/true));
  const auto sorted = boxes_in.index_select(0, order).contiguous();
  const int64_t words = (n + 63) / 64;
  auto mask = at::empty({n, words}, boxes_in.options().dtype(at::kLong));
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(sorted.scalar_type(), "tiger.box_nms", [&] {
    launch_box_iou_bits<scalar_t>(sorted.data_ptr<scalar_t>(), n, iou_threshold,
                                  reinterpret_cast<uint64_t*>(mask.data_ptr<int64_t>()), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  const auto host = mask.cpu();
  const uint64_t* bits = reinterpret_cast<const uint64_t*>(host.data_ptr<int64_t>());
  std::vector<uint64_t> removed(words, 0);
  std::vector<int64_t> keep;
  for (int64_t i = 0; i < n; ++i) {
    if (removed[i / 64] >> (i % 64) & 1) continue;
    keep.push_back(i);
    const uint64_t* row = bits + i * words;
    for (int64_t w = i / 64; w < words; ++w) removed[w] |= row[w];
  }
  auto kept = at::empty({static_cast<int64_t>(keep.size())}, at::TensorOptions().dtype(at::kLong));
  std::copy(keep.begin(), keep.end(), kept.data_ptr<int64_t>());
  return order.index_select(0, kept.to(order.device()));
}

at::Tensor mask_intersections_cuda(const at::Tensor& masks_in) {
  check_masks(masks_in, "tiger.mask_intersections");
  TORCH_CHECK(masks_in.is_cuda(), "tiger.mask_intersections (CUDA): masks must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(masks_in.device());
  const auto masks = masks_in.contiguous();
  const int64_t M = masks.size(0), L = masks.size(1) * masks.size(2), W = (L + 63) / 64;
  auto packed = at::empty({M, W}, masks.options().dtype(at::kLong));
  auto out = at::empty({M, M}, masks.options().dtype(at::kLong));
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  auto* pk = reinterpret_cast<uint64_t*>(packed.data_ptr<int64_t>());
  launch_pack_masks(masks.data_ptr<bool>(), M, L, pk, W, stream);
  launch_pair_intersections(pk, M, W, out.data_ptr<int64_t>(), stream);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

at::Tensor mask_nms_cuda(const at::Tensor& masks, const at::Tensor& scores, double iou_threshold,
                         double score_threshold, double inner_threshold) {
  TORCH_CHECK(masks.is_cuda(), "tiger.mask_nms (CUDA): masks must be on a CUDA device");
  return mask_nms_impl(masks, scores, iou_threshold, score_threshold, inner_threshold,
                       [](const at::Tensor& m) { return mask_intersections_cuda(m); });
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("box_nms", &box_nms_cuda);
  m.impl("mask_intersections", &mask_intersections_cuda);
  m.impl("mask_nms", &mask_nms_cuda);
}

}  // namespace nms
}  // namespace tiger
