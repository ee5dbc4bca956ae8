// One launch for the whole relevance-scaled Adam step of an edit: every element of every
// tensor is one thread's, and the updated row goes straight into the scene's full tensor.
// torch's fused Adam splits its tensors into 64k-element chunks, one block each: the ~600k
// elements of an edit's editable rows made 3-9 blocks per tensor, each thread walking ~128
// elements, ~58 us a launch on an H100 for 2.3 MB; then the update's scaling and the copy
// into the scene took 20 more launches (tiger.recon.step.SceneOptimizer.update).
#include <cuda_runtime.h>

#include <algorithm>

#include "scaled_adam/scaled_adam_cuda.h"
#include "scaled_adam/scaled_adam_math.h"

namespace tiger {
namespace scaled_adam {
namespace {

constexpr int kThreads = 256;

template <typename T>
__global__ void __launch_bounds__(kThreads) scaled_adam_kernel(const Lists<T> L, const T* __restrict__ weight,
                                                               const int64_t* __restrict__ index, T beta1, T beta2,
                                                               T eps) {
  const int64_t total = L.start[L.n];
  const int64_t stride = int64_t(gridDim.x) * blockDim.x;
  for (int64_t e = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; e < total; e += stride) {
    int k = 0;
    while (k + 1 < L.n && e >= L.start[k + 1]) ++k;
    const int64_t local = e - L.start[k], row = L.row[k];
    const int64_t r = local / row;
    const T t = L.step_double[k] ? T(*static_cast<const double*>(L.step[k])) : T(*static_cast<const float*>(L.step[k]));
    const StepScalars<T> s = step_scalars(L.lr[k], beta1, beta2, t);
    T p = L.p[k][local], m = L.m[k][local], v = L.v[k][local];
    update_element(p, L.g[k][local], m, v, weight ? weight[r] : T(1), beta1, beta2, eps, s);
    L.p[k][local] = p;
    L.m[k][local] = m;
    L.v[k][local] = v;
    if (index) L.target[k][index[r] * row + (local - r * row)] = p;
  }
}

}  // namespace

template <typename T>
void launch_scaled_adam(const Lists<T>& lists, const T* weight, const int64_t* index, T beta1, T beta2, T eps,
                        void* stream) {
  const int64_t total = lists.start[lists.n];
  if (total == 0) return;
  const int64_t blocks = std::min<int64_t>((total + kThreads - 1) / kThreads, 65535LL * 8);
  scaled_adam_kernel<T><<<unsigned(blocks), kThreads, 0, static_cast<cudaStream_t>(stream)>>>(lists, weight, index,
                                                                                              beta1, beta2, eps);
}

template void launch_scaled_adam<float>(const Lists<float>&, const float*, const int64_t*, float, float, float, void*);
template void launch_scaled_adam<double>(const Lists<double>&, const double*, const int64_t*, double, double, double,
                                         void*);

}  // namespace scaled_adam
}  // namespace tiger
