#pragma once
// Launchers of the CUDA row softmax (softmax_cuda.cu).
#include <cstdint>

namespace tiger {
namespace softmax {

// Whether the kernels take rows of L values of T at these addresses (16-byte vectors, a row in one
// block's registers); otherwise the glue runs torch's softmax.
template <typename T>
bool rows_supported(int64_t L, const void* a, const void* b, const void* c);

// y[r, :] = softmax(x[r, :]) for M contiguous rows of L values, in float, rounded once.
template <typename T>
void launch_softmax_rows(const T* x, T* y, int64_t M, int64_t L, void* stream);

// dx[r, :] = y[r, :] * (dy[r, :] - <dy[r, :], y[r, :]>), in float, rounded once.
template <typename T>
void launch_softmax_rows_backward(const T* y, const T* dy, T* dx, int64_t M, int64_t L, void* stream);

}  // namespace softmax
}  // namespace tiger
