// Torch glue of the head-dim-40 attention kernel (built only with CUDA). Rows the kernel does not
// take (another head dim or dtype, L not a multiple of 128, misaligned rows, a device other than
// compute capability 9.0) run the reference computation instead: the op is total. No host
// synchronisation: CUDA-graph capturable.
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <cmath>
#include <limits>

#include "attention/attention_cuda.h"
#include "attention/attention_glue.h"

namespace tiger {
namespace attention {
namespace {

bool kernel_rows(const at::Tensor& t) {
  return t.stride(1) == 1 && t.stride(0) % 8 == 0 && reinterpret_cast<uintptr_t>(t.data_ptr()) % 16 == 0;
}

at::Tensor attention_rows_cuda(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, int64_t batch,
                               int64_t heads, std::optional<double> scale, c10::string_view schedule, int64_t warpgroups) {
  const RowsShape s = check_inputs(q, k, v, batch, heads, schedule, warpgroups);
  const double sc = softmax_scale(scale, s.D);
  const c10::cuda::CUDAGuard guard(q.device());
  const bool fast = s.D == 40 && q.scalar_type() == at::kBFloat16 && s.L % 128 == 0 &&
                    s.L <= std::numeric_limits<int>::max() && s.batch <= 65535 && s.heads <= 65535 &&
                    kernel_rows(q) && kernel_rows(k) && kernel_rows(v) &&
                    attention_head40_available(q.get_device());
  if (!fast) return reference_rows(q, k, v, s, sc);
  auto out = at::empty({s.batch * s.L, s.heads * s.D}, q.options());
  AttentionParams p{};
  p.q = reinterpret_cast<const __nv_bfloat16*>(q.data_ptr());
  p.k = reinterpret_cast<const __nv_bfloat16*>(k.data_ptr());
  p.v = reinterpret_cast<const __nv_bfloat16*>(v.data_ptr());
  p.out = reinterpret_cast<__nv_bfloat16*>(out.data_ptr());
  p.q_stride = q.stride(0);
  p.k_stride = k.stride(0);
  p.v_stride = v.stride(0);
  p.out_stride = out.stride(0);
  p.L = static_cast<int>(s.L);
  p.heads = static_cast<int>(s.heads);
  p.batch = static_cast<int>(s.batch);
  p.scale_log2 = static_cast<float>(sc / std::log(2.0));
  C10_CUDA_CHECK(attention_head40_cuda(p, schedule == "producer", static_cast<int>(warpgroups),
                                      c10::cuda::getCurrentCUDAStream().stream()));
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("attention_rows", &attention_rows_cuda); }

}  // namespace attention
}  // namespace tiger
