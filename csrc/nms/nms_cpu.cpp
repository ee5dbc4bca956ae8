// CPU kernels of the nms family: greedy box NMS, bit-packed pairwise mask intersections.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <vector>

#include "nms/nms.h"
#include "nms/nms_glue.h"

namespace tiger {
namespace nms {
namespace {

template <typename scalar_t>
at::Tensor box_nms_kernel(const at::Tensor& boxes, const at::Tensor& order, double thr) {
  const int64_t n = boxes.size(0);
  const scalar_t* b = boxes.data_ptr<scalar_t>();
  const int64_t* ord = order.data_ptr<int64_t>();
  std::vector<char> removed(n, 0);
  std::vector<int64_t> keep;
  for (int64_t a = 0; a < n; ++a) {
    if (removed[a]) continue;
    const int64_t i = ord[a];
    keep.push_back(i);
    const scalar_t* bi = b + 4 * i;
    const double area_i = double(bi[2] - bi[0]) * double(bi[3] - bi[1]);
    for (int64_t c = a + 1; c < n; ++c) {
      if (removed[c]) continue;
      const scalar_t* bj = b + 4 * ord[c];
      const double w = std::max(0.0, double(std::min(bi[2], bj[2]) - std::max(bi[0], bj[0])));
      const double h = std::max(0.0, double(std::min(bi[3], bj[3]) - std::max(bi[1], bj[1])));
      const double inter = w * h;
      const double area_j = double(bj[2] - bj[0]) * double(bj[3] - bj[1]);
      const double uni = area_i + area_j - inter;
      if (uni > 0 && inter / uni > thr) removed[c] = 1;
    }
  }
  auto out = at::empty({static_cast<int64_t>(keep.size())}, order.options());
  std::copy(keep.begin(), keep.end(), out.data_ptr<int64_t>());
  return out;
}

at::Tensor box_nms_cpu(const at::Tensor& boxes_in, const at::Tensor& scores, double iou_threshold) {
  check_boxes(boxes_in, scores, iou_threshold);
  TORCH_CHECK(boxes_in.device().is_cpu(), "tiger.box_nms (CPU): boxes must be on the CPU");
  const auto boxes = boxes_in.contiguous();
  const auto order = std::get<1>(scores.sort(/*stable=*/true, 0, /*descending=*/true)).contiguous();
  at::Tensor keep;
  AT_DISPATCH_FLOATING_TYPES(boxes.scalar_type(), "tiger.box_nms",
                             [&] { keep = box_nms_kernel<scalar_t>(boxes, order, iou_threshold); });
  return keep;
}

at::Tensor mask_intersections_cpu(const at::Tensor& masks_in) {
  check_masks(masks_in, "tiger.mask_intersections");
  TORCH_CHECK(masks_in.device().is_cpu(), "tiger.mask_intersections (CPU): masks must be on the CPU");
  const auto masks = masks_in.contiguous();
  const int64_t M = masks.size(0), L = masks.size(1) * masks.size(2), W = (L + 63) / 64;
  std::vector<uint64_t> packed(M * W, 0);
  const bool* src = masks.data_ptr<bool>();
  at::parallel_for(0, M, 1, [&](int64_t m0, int64_t m1) {
    for (int64_t m = m0; m < m1; ++m)
      for (int64_t p = 0; p < L; ++p)
        if (src[m * L + p]) packed[m * W + p / 64] |= uint64_t(1) << (p % 64);
  });
  auto out = at::empty({M, M}, masks.options().dtype(at::kLong));
  int64_t* o = out.data_ptr<int64_t>();
  at::parallel_for(0, M, 1, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const uint64_t* a = packed.data() + i * W;
      for (int64_t j = i; j < M; ++j) {
        const uint64_t* b = packed.data() + j * W;
        int64_t s = 0;
        for (int64_t w = 0; w < W; ++w) s += __builtin_popcountll(a[w] & b[w]);
        o[i * M + j] = s;
        o[j * M + i] = s;
      }
    }
  });
  return out;
}

at::Tensor mask_nms_cpu(const at::Tensor& masks, const at::Tensor& scores, double iou_threshold,
                        double score_threshold, double inner_threshold) {
  return mask_nms_impl(masks, scores, iou_threshold, score_threshold, inner_threshold,
                       [](const at::Tensor& m) { return mask_intersections_cpu(m); });
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("box_nms", &box_nms_cpu);
  m.impl("mask_intersections", &mask_intersections_cpu);
  m.impl("mask_nms", &mask_nms_cpu);
}

}  // namespace nms
}  // namespace tiger
