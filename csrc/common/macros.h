#pragma once
// Shared by the C++ and CUDA compilers: every formula in csrc/common is written
// once and compiled for both.
#if defined(__CUDACC__) || defined(__HIPCC__)
#define TIGER_HD __host__ __device__ __forceinline__
#define TIGER_DEVICE_CODE 1
#else
#define TIGER_HD inline
#endif
