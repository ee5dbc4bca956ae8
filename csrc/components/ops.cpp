// Schemas of the components family (semantics in components.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("connected_components(Tensor masks) -> Tensor");
  m.def("remove_small_regions(Tensor masks, int area_threshold) -> (Tensor, Tensor)");
}
