// CPU implementation of tiger::attention_rows: the reference semantics (attention_glue.h).
#include <torch/library.h>

#include "attention/attention_glue.h"

namespace tiger {
namespace attention {
namespace {

at::Tensor attention_rows_cpu(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, int64_t batch,
                              int64_t heads, std::optional<double> scale, c10::string_view schedule, int64_t warpgroups) {
  const RowsShape s = check_inputs(q, k, v, batch, heads, schedule, warpgroups);
  return reference_rows(q, k, v, s, softmax_scale(scale, s.D));
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) { m.impl("attention_rows", &attention_rows_cpu); }

}  // namespace attention
}  // namespace tiger
