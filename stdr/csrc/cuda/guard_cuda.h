// The guard family of the CUDA extension's host side (ops_cuda.cpp binds it; twin
// stdr.train.guard's flag_step update); the kernels live in kernels.cu.
#pragma once

#include <torch/extension.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <climits>
#include <vector>

#include "kernels.h"

namespace {

// ---------------------------------------------------------------- the guard's check

// The sync-free guard's per-step update, in place, on the device (as the CPU's guard_update):
// float32 tensors only (the caller sends others to the torch form).
void guard_update(std::vector<at::Tensor> ts, at::Tensor flag, at::Tensor bad_step, at::Tensor bad_index,
                  int64_t step) {
  TORCH_CHECK(flag.is_cuda() && flag.numel() == 1 && flag.scalar_type() == at::kFloat && bad_step.is_cuda() &&
                  bad_step.numel() == 1 && bad_step.scalar_type() == at::kLong && bad_index.is_cuda() &&
                  bad_index.numel() == 1 && bad_index.scalar_type() == at::kLong,
              "stdr CUDA guard: flag must be a float32 CUDA scalar, bad_step and bad_index int64 CUDA scalars");
  const at::cuda::CUDAGuard guard(flag.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  std::vector<at::Tensor> keep;  // contiguous copies live until the launches are queued
  auto first = at::full({1}, INT_MAX, flag.options().dtype(at::kInt));
  stdr_cuda::GuardTable table;
  int count = 0;
  int64_t max_numel = 0;
  for (size_t i = 0; i < ts.size(); ++i) {
    const auto& t0 = ts[i];
    if (!t0.defined() || t0.numel() == 0) continue;
    TORCH_CHECK(t0.is_cuda() && t0.get_device() == flag.get_device() && t0.scalar_type() == at::kFloat,
                "stdr CUDA guard: every tensor must be float32 on the flag's GPU");
    keep.push_back(t0.contiguous());
    table.ptr[count] = keep.back().data_ptr();
    table.numel[count] = keep.back().numel();
    table.index[count] = (int)i;
    max_numel = std::max(max_numel, table.numel[count]);
    if (++count == stdr_cuda::GUARD_MAX) {
      stdr_cuda::guard_check(table, count, max_numel, first.data_ptr<int>(), stream);
      count = 0;
      max_numel = 0;
    }
  }
  stdr_cuda::guard_check(table, count, max_numel, first.data_ptr<int>(), stream);
  stdr_cuda::guard_finish(first.data_ptr<int>(), flag.data_ptr<float>(), bad_step.data_ptr<int64_t>(),
                          bad_index.data_ptr<int64_t>(), step, stream);
  C10_CUDA_CHECK(cudaGetLastError());
}

}  // namespace
