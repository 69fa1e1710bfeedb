// STDR_HD marks the math headers' functions: host and, under nvcc, device code (one definition
// that the CPU extension, the CUDA kernels and the CPU tests share).
#pragma once

#ifndef STDR_HD
#ifdef __CUDACC__
#define STDR_HD __host__ __device__ __forceinline__
#else
#define STDR_HD inline
#endif
#endif
