#pragma once
// tiger::masked_average — SAM aggregation of per-pixel features (SPEC §4).
//
//   features [P, C] float32/float64, ids [P] int64 with -1 = "in no mask", else 0 <= id < M.
//   counts[m] = #{p : ids[p] == m}                            [M] int64
//   means[m]  = sum_{p : ids[p] == m} features[p] / counts[m]  [M, C] (0 for an empty mask)
//   out[p]    = means[ids[p]] if ids[p] >= 0 else features[p]  [P, C]
//
// Backward (masked_average_backward): with S[m] = sum_{p : ids[p] == m} grad_out[p],
//   grad_features[p] = (S[ids[p]] + grad_means[ids[p]]) / counts[ids[p]]   if ids[p] >= 0
//                    = grad_out[p]                                         otherwise.
//
// The CUDA launchers below take raw pointers so the .cu compiles without torch headers.
#include <cstdint>

namespace tiger {
namespace masked_average {

// sums[M, C] += segment sums of values[P, C] by ids; counts[M] += pixel counts (counts may be null).
template <typename scalar_t>
void launch_segment_sum(const scalar_t* values, const int64_t* ids, int64_t P, int64_t C, int64_t M,
                        scalar_t* sums, int64_t* counts, void* stream);

// out[p] = ids[p] >= 0 ? (sums[ids[p]] + extra[ids[p]]) / counts[ids[p]] : fallback[p]; extra may be null.
template <typename scalar_t>
void launch_scatter_mean(const scalar_t* sums, const scalar_t* extra, const int64_t* counts,
                         const int64_t* ids, const scalar_t* fallback, int64_t P, int64_t C,
                         scalar_t* out, void* stream);

// means[m] = sums[m] / max(counts[m], 1).
template <typename scalar_t>
void launch_divide(const scalar_t* sums, const int64_t* counts, int64_t M, int64_t C, scalar_t* means,
                   void* stream);

}  // namespace masked_average
}  // namespace tiger
