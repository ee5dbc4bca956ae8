#pragma once
// tiger NMS ops for SAM's automatic masks (SPEC §4).
//
// box_nms(boxes [N, 4] xyxy float, scores [N], iou_threshold) -> keep [K] int64
//   Greedy NMS in decreasing score order (ties: lower index first); a box is dropped when its IoU
//   with an already kept box is > iou_threshold. IoU = inter / (area_a + area_b - inter) with
//   area = (x2 - x1) * (y2 - y1), as torchvision.ops.nms.
// mask_intersections(masks [M, H, W] bool) -> [M, M] int64 pixel counts of masks_i AND masks_j
//   (the diagonal holds the areas). Masks are packed into 64-bit words and counted by popcount.
// mask_nms(masks [M, H, W] bool, scores [M], iou_threshold=0.8, score_threshold=0.7,
//          inner_threshold=0.5) -> keep [K] int64 (indices into masks, by decreasing score)
//   LangSplat's mask NMS, its ratios in float32 as there (so ties within float32 rounding of a
//   threshold decide as in LangSplat; frames up to 2^24 pixels). In score order, mask j is dropped when
//     * max_{i before j} IoU(i, j) > iou_threshold (i counted whether or not it is kept), or
//     * scores[j] <= score_threshold, or
//     * j is the contained one of a nested pair (i, j): the smaller mask has >= 85 % of its area in
//       the larger one, the larger has < 50 % in the smaller, and
//       1 - (inter/area_i)(inter/area_j) > 1 - inner_threshold.
//   An empty mask has IoU 0 with everything (LangSplat's 0/0 = NaN would drop the second of two
//   empty masks; the pipeline drops masks under 100 px before this op).
#include <cstdint>

namespace tiger {
namespace nms {

// mask[i * words + w] bit b set when IoU(sorted box i, sorted box 64w+b) > thr and 64w+b > i.
template <typename scalar_t>
void launch_box_iou_bits(const scalar_t* boxes, int64_t n, double iou_threshold, uint64_t* mask,
                         void* stream);

// packed[m * words + w] bit b = masks[m * length + 64 w + b] (0 past the end).
void launch_pack_masks(const bool* masks, int64_t m, int64_t length, uint64_t* packed, int64_t words,
                       void* stream);

// out[i * m + j] = popcount(packed_i & packed_j), for all i, j.
void launch_pair_intersections(const uint64_t* packed, int64_t m, int64_t words, int64_t* out,
                               void* stream);

}  // namespace nms
}  // namespace tiger
