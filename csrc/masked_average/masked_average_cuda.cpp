// Torch glue of the CUDA masked_average kernels (built only with CUDA).
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAStream.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <tuple>

#include "masked_average/masked_average.h"
#include "masked_average/masked_average_glue.h"

namespace tiger {
namespace masked_average {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> masked_average_cuda(const at::Tensor& features_in,
                                                                   const at::Tensor& ids_in,
                                                                   int64_t num_masks) {
  check_features_ids(features_in, ids_in, "features");
  TORCH_CHECK(features_in.is_cuda(), "tiger.masked_average (CUDA): features must be on a CUDA device");
  check_id_range(ids_in, num_masks);
  const c10::cuda::CUDAGuard guard(features_in.device());
  const auto features = features_in.contiguous();
  const auto ids = ids_in.contiguous();
  const int64_t P = features.size(0), C = features.size(1), M = num_masks;
  auto sums = at::zeros({M, C}, features.options());
  auto counts = at::zeros({M}, ids.options());
  auto means = at::empty({M, C}, features.options());
  auto out = at::empty_like(features);
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "tiger.masked_average", [&] {
    launch_segment_sum<scalar_t>(features.data_ptr<scalar_t>(), ids.data_ptr<int64_t>(), P, C, M,
                                 sums.data_ptr<scalar_t>(), counts.data_ptr<int64_t>(), stream);
    launch_divide<scalar_t>(sums.data_ptr<scalar_t>(), counts.data_ptr<int64_t>(), M, C,
                            means.data_ptr<scalar_t>(), stream);
    launch_scatter_mean<scalar_t>(sums.data_ptr<scalar_t>(), nullptr, counts.data_ptr<int64_t>(),
                                  ids.data_ptr<int64_t>(), features.data_ptr<scalar_t>(), P, C,
                                  out.data_ptr<scalar_t>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, means, counts};
}

at::Tensor masked_average_backward_cuda(const at::Tensor& grad_out_in, const at::Tensor& grad_means_in,
                                        const at::Tensor& ids_in, const at::Tensor& counts_in) {
  check_features_ids(grad_out_in, ids_in, "grad_out");
  const int64_t P = grad_out_in.size(0), C = grad_out_in.size(1), M = counts_in.size(0);
  TORCH_CHECK(grad_means_in.dim() == 2 && grad_means_in.size(0) == M && grad_means_in.size(1) == C,
              "tiger.masked_average_backward: grad_means must be [M, C] = [", M, ", ", C, "], got ",
              grad_means_in.sizes());
  TORCH_CHECK(counts_in.scalar_type() == at::kLong && counts_in.dim() == 1,
              "tiger.masked_average_backward: counts must be [M] int64");
  const c10::cuda::CUDAGuard guard(grad_out_in.device());
  const auto grad_out = grad_out_in.contiguous();
  const auto grad_means = grad_means_in.to(grad_out.scalar_type()).contiguous();
  const auto ids = ids_in.contiguous();
  const auto counts = counts_in.contiguous();
  auto sums = at::zeros({M, C}, grad_out.options());
  auto grad = at::empty_like(grad_out);
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(grad_out.scalar_type(), "tiger.masked_average_backward", [&] {
    launch_segment_sum<scalar_t>(grad_out.data_ptr<scalar_t>(), ids.data_ptr<int64_t>(), P, C, M,
                                 sums.data_ptr<scalar_t>(), nullptr, stream);
    launch_scatter_mean<scalar_t>(sums.data_ptr<scalar_t>(), grad_means.data_ptr<scalar_t>(),
                                  counts.data_ptr<int64_t>(), ids.data_ptr<int64_t>(),
                                  grad_out.data_ptr<scalar_t>(), P, C, grad.data_ptr<scalar_t>(),
                                  stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return grad;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("masked_average", &masked_average_cuda);
  m.impl("masked_average_backward", &masked_average_backward_cuda);
}

}  // namespace masked_average
}  // namespace tiger
