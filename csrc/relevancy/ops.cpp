// Schemas of the relevancy family (shapes and formula in relevancy.h).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def(
      "relevancy(Tensor features, Tensor positives, Tensor negatives, float temperature=10.0, "
      "float eps=1e-12) -> (Tensor, Tensor)");
}
