// Schemas of the nms family (semantics in nms.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("box_nms(Tensor boxes, Tensor scores, float iou_threshold) -> Tensor");
  m.def("mask_intersections(Tensor masks) -> Tensor");
  m.def(
      "mask_nms(Tensor masks, Tensor scores, float iou_threshold=0.8, float score_threshold=0.7, "
      "float inner_threshold=0.5) -> Tensor");
}
