#pragma once
// Launcher of the head-dim-40 self-attention (attention_sm90a.cu; Hopper's warpgroup MMAs).
#include <cuda_bf16.h>
#include <cuda_runtime.h>

#include <cstdint>

namespace tiger {
namespace attention {

// Token rows of `batch` sequences of L tokens: q, k, v and out are [batch·L, heads·40] bf16
// with unit column stride and the given row strides (elements; multiples of 8, 16-byte aligned
// rows).
struct AttentionParams {
  const __nv_bfloat16* q;
  const __nv_bfloat16* k;
  const __nv_bfloat16* v;
  __nv_bfloat16* out;
  int64_t q_stride, k_stride, v_stride, out_stride;
  int L, heads, batch;
  float scale_log2;  // softmax scale × log2(e)
};

// Whether the kernel body was built for `device` (sm_90a: compute capability 9.0 only); `device`
// must be the current device.
bool attention_head40_available(int device);

// out = softmax(q kᵀ · scale) v per (sequence, head); L a multiple of 128. producer: the
// warp-specialised schedule (warpgroups 2-3) instead of the lockstep one (1-4); warpgroups: the
// CTA's consumer warpgroups, i.e. 64·warpgroups query rows sharing each key / value tile.
cudaError_t attention_head40_cuda(const AttentionParams& p, bool producer, int warpgroups, cudaStream_t stream);

}  // namespace attention
}  // namespace tiger
