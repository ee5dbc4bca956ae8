// Zero-filled CUDA buffers by one cudaMemsetAsync on the current stream. at::zeros launches its
// fill kernel through TensorIterator, ~10 us of host time each; a render's forward and backward
// make several of these buffers, and on real scenes their host time is not hidden behind the GPU.
// Include only from CUDA glue (needs the CUDA runtime); the caller sets the device guard.
#pragma once

#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAStream.h>

namespace tiger {

inline at::Tensor cuda_zeros(at::IntArrayRef size, const at::TensorOptions& opts) {
  auto t = at::empty(size, opts);
  if (t.nbytes() > 0)
    C10_CUDA_CHECK(cudaMemsetAsync(t.data_ptr(), 0, t.nbytes(), c10::cuda::getCurrentCUDAStream()));
  return t;
}

}  // namespace tiger
