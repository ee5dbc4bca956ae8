// Schema of the scaled_adam family: one Adam step of several tensors whose update each row's
// weight scales (TIGER's relevance-scaled update), optionally written into the rows of the full
// tensors the optimised rows were taken from.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def(
      "scaled_adam_(Tensor(a!)[] params, Tensor[] grads, Tensor(b!)[] exp_avgs, Tensor(c!)[] exp_avg_sqs, "
      "Tensor(d!)[] steps, float[] lrs, float beta1, float beta2, float eps, Tensor? weight, "
      "Tensor(e!)[] targets, Tensor? index) -> ()");
}
