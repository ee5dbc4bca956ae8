#pragma once
// ATen-side checks and the device-independent part of mask_nms (the pairwise counts come from the
// device's mask_intersections kernel; the O(M^2) decision is plain tensor algebra).
#include <ATen/ATen.h>

#include <cmath>

namespace tiger {
namespace nms {

inline void check_boxes(const at::Tensor& boxes, const at::Tensor& scores, double thr) {
  TORCH_CHECK(boxes.dim() == 2 && boxes.size(1) == 4, "tiger.box_nms: boxes must be [N, 4] (x1, y1, x2, y2), got ",
              boxes.sizes());
  TORCH_CHECK(boxes.scalar_type() == at::kFloat || boxes.scalar_type() == at::kDouble,
              "tiger.box_nms: boxes must be float32 or float64, got ", boxes.scalar_type());
  TORCH_CHECK(scores.dim() == 1 && scores.size(0) == boxes.size(0), "tiger.box_nms: scores must be [N] with N = ",
              boxes.size(0), ", got ", scores.sizes());
  TORCH_CHECK(scores.device() == boxes.device(), "tiger.box_nms: boxes and scores must be on one device");
  TORCH_CHECK(std::isfinite(thr), "tiger.box_nms: iou_threshold must be finite, got ", thr);
}

inline void check_masks(const at::Tensor& masks, const char* op) {
  TORCH_CHECK(masks.dim() == 3, op, ": masks must be [M, H, W], got ", masks.sizes());
  TORCH_CHECK(masks.scalar_type() == at::kBool, op, ": masks must be bool, got ", masks.scalar_type());
}

// LangSplat's decision on the [M, M] intersection counts of the score-sorted masks, in float32 as
// LangSplat computes it (its IoU and nesting ratios are float32 tensors compared with float32
// thresholds): a ratio within float32 rounding of a threshold decides as it does there. The counts
// are exact in float32 up to 2^24 pixels per mask (checked by mask_nms_impl).
inline at::Tensor mask_nms_decide(const at::Tensor& inter_counts, const at::Tensor& sorted_scores,
                                  double iou_threshold, double score_threshold, double inner_threshold) {
  const auto inter = inter_counts.to(at::kFloat);
  const int64_t M = inter.size(0);
  const auto area = inter.diagonal();
  const auto area_i = area.unsqueeze(1), area_j = area.unsqueeze(0);
  const auto uni = area_i + area_j - inter;
  const auto iou = at::where(uni > 0, inter / uni.clamp_min(1), at::zeros_like(inter));
  const auto ri = at::where(area_i > 0, inter / area_i.clamp_min(1), at::zeros_like(inter));
  const auto rj = at::where(area_j > 0, inter / area_j.clamp_min(1), at::zeros_like(inter));
  const auto upper = at::ones({M, M}, inter.options().dtype(at::kBool)).triu(1);
  const auto zero = at::zeros_like(inter);
  const auto inner = 1.0f - rj * ri;
  const auto iou_max = at::where(upper, iou, zero).amax(0);
  const float nested = 0.85f, outer = 0.5f;  // LangSplat's fixed nesting ratios
  // (i before j) j nested in i: drops j; i nested in j: drops i.
  const auto a = at::where(upper & (ri < outer) & (rj >= nested), inner, zero).amax(0);
  const auto b = at::where(upper & (ri >= nested) & (rj < outer), inner, zero).amax(1);
  const float inner_max = static_cast<float>(1.0 - inner_threshold);
  return (iou_max <= static_cast<float>(iou_threshold)) & (sorted_scores.to(at::kDouble) > score_threshold) &
         (a <= inner_max) & (b <= inner_max);
}

template <typename IntersectFn>
at::Tensor mask_nms_impl(const at::Tensor& masks, const at::Tensor& scores, double iou_threshold,
                         double score_threshold, double inner_threshold, IntersectFn intersections) {
  check_masks(masks, "tiger.mask_nms");
  TORCH_CHECK(scores.dim() == 1 && scores.size(0) == masks.size(0), "tiger.mask_nms: scores must be [M] with M = ",
              masks.size(0), ", got ", scores.sizes());
  TORCH_CHECK(at::isFloatingType(scores.scalar_type()), "tiger.mask_nms: scores must be floating, got ",
              scores.scalar_type());
  TORCH_CHECK(scores.device() == masks.device(), "tiger.mask_nms: masks and scores must be on one device");
  TORCH_CHECK(masks.size(1) * masks.size(2) <= (int64_t(1) << 24), "tiger.mask_nms: masks of ",
              masks.size(1), "x", masks.size(2), " pixels exceed 2^24, where float32 counts stop being exact");
  if (masks.size(0) == 0) return at::empty({0}, scores.options().dtype(at::kLong));
  const auto order = std::get<1>(scores.sort(/*stable=*/true, /*dim=*/0, /*descending=*/true));
  const auto inter = intersections(masks.index_select(0, order));
  const auto keep = mask_nms_decide(inter, scores.index_select(0, order), iou_threshold, score_threshold,
                                    inner_threshold);
  return order.masked_select(keep);
}

}  // namespace nms
}  // namespace tiger
