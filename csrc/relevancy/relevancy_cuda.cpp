// Torch glue for the CUDA relevancy kernels (built only with CUDA).
// c10/cuda only (not ATen/cuda/CUDAContext.h, which pulls in cuSPARSE/cuBLAS headers).
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_runtime_api.h>
#include <torch/library.h>

#include "relevancy/relevancy_glue.h"

namespace tiger {
namespace relevancy {

int relevancy_cuda_f16(const void* feat, int64_t n, int d, const float* texts, int q, int m,
                       double temperature, double eps, float* cos_out, float* rel_out,
                       size_t max_smem, cudaStream_t stream);
int relevancy_cuda_f32(const float* feat, int64_t n, int d, const float* texts, int q, int m,
                       double temperature, double eps, float* cos_out, float* rel_out,
                       size_t max_smem, cudaStream_t stream);
int relevancy_cuda_f64(const double* feat, int64_t n, int d, const double* texts, int q, int m,
                       double temperature, double eps, double* cos_out, double* rel_out,
                       size_t max_smem, cudaStream_t stream);

namespace {

std::tuple<at::Tensor, at::Tensor> relevancy_cuda(const at::Tensor& features, const at::Tensor& positives,
                                                  const at::Tensor& negatives, double temperature,
                                                  double eps) {
  TORCH_CHECK(features.is_cuda(), "tiger.relevancy (CUDA): features must be a CUDA tensor");
  const c10::cuda::CUDAGuard guard(features.device());
  Prepared p = prepare(features, positives, negatives, temperature, eps);
  TORCH_CHECK(p.d <= INT32_MAX && p.q <= INT32_MAX && p.m <= INT32_MAX,
              "tiger.relevancy (CUDA): D, Q and M must fit in 32 bits");
  if (p.n == 0 || p.q == 0) return {p.cosine, p.relevancy};
  int optin = 0;
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin,
                                        features.device().index()));
  const size_t max_smem = static_cast<size_t>(optin);
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(features.device().index()).stream();
  const int d = static_cast<int>(p.d), q = static_cast<int>(p.q), m = static_cast<int>(p.m);
  int rc = 0;
  switch (p.features.scalar_type()) {
    case at::kHalf:
      rc = relevancy_cuda_f16(p.features.data_ptr<at::Half>(), p.n, d, p.texts.data_ptr<float>(), q, m,
                              temperature, eps, p.cosine.data_ptr<float>(),
                              m > 0 ? p.relevancy.data_ptr<float>() : nullptr, max_smem, stream);
      break;
    case at::kFloat:
      rc = relevancy_cuda_f32(p.features.data_ptr<float>(), p.n, d, p.texts.data_ptr<float>(), q, m,
                              temperature, eps, p.cosine.data_ptr<float>(),
                              m > 0 ? p.relevancy.data_ptr<float>() : nullptr, max_smem, stream);
      break;
    default:
      rc = relevancy_cuda_f64(p.features.data_ptr<double>(), p.n, d, p.texts.data_ptr<double>(), q, m,
                              temperature, eps, p.cosine.data_ptr<double>(),
                              m > 0 ? p.relevancy.data_ptr<double>() : nullptr, max_smem, stream);
  }
  TORCH_CHECK(rc != -1, "tiger.relevancy (CUDA): D = ", p.d, " with M = ", p.m,
              " negatives does not fit in shared memory (", max_smem, " bytes per block)");
  TORCH_CHECK(rc == 0, "tiger.relevancy (CUDA): kernel launch failed: ",
              cudaGetErrorString(static_cast<cudaError_t>(rc)));
  return {p.cosine, p.relevancy};
}

}  // namespace
}  // namespace relevancy
}  // namespace tiger

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("relevancy", &tiger::relevancy::relevancy_cuda); }
