// The HexPlane family of the CUDA extension's host side (ops_cuda.cpp binds it; twin
// stdr/baselines/fourdgs.py); the kernels live in kernels.cu.
#pragma once

#include <torch/extension.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <climits>
#include <vector>

#include "kernels.h"
#include "../hexplane_math.h"

namespace {

// ---------------------------------------------------------------- HexPlane sampling

stdr_cuda::HexPlanes hex_planes(const at::Tensor& coords, const std::vector<at::Tensor>& planes,
                                const std::vector<at::Tensor>* grads) {
  TORCH_CHECK(coords.is_cuda() && coords.is_contiguous() && coords.scalar_type() == at::kFloat &&
                  coords.dim() == 2 && coords.size(1) == 4,
              "stdr CUDA hexplane: coords must be a contiguous float32 [N, 4] CUDA tensor");
  TORCH_CHECK(!planes.empty() && planes.size() % stdr::HEX_PLANES == 0 &&
                  (int)planes.size() <= stdr_cuda::HEX_MAX_PLANES,
              "stdr CUDA hexplane: planes must be 6 per scale, at most 8 scales");
  stdr_cuda::HexPlanes pl;
  pl.M = (int)(planes.size() / stdr::HEX_PLANES);
  pl.C = (int)planes[0].size(0);
  for (size_t q = 0; q < planes.size(); ++q) {
    const auto& t = planes[q];
    TORCH_CHECK(t.is_cuda() && t.get_device() == coords.get_device() && t.is_contiguous() &&
                    t.scalar_type() == at::kFloat && t.dim() == 3 && t.size(0) == pl.C,
                "stdr CUDA hexplane: planes must be contiguous float32 [C, H, W] tensors on the coords' GPU");
    pl.ptr[q] = t.data_ptr<float>();
    pl.grad[q] = grads ? (*grads)[q].data_ptr<float>() : nullptr;
    pl.H[q] = (int)t.size(1);
    pl.W[q] = (int)t.size(2);
  }
  return pl;
}

std::vector<at::Tensor> hexplane_forward(at::Tensor coords, std::vector<at::Tensor> planes) {
  const auto pl = hex_planes(coords, planes, nullptr);
  const at::cuda::CUDAGuard guard(coords.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t N = coords.size(0);
  auto feats = at::empty({N, (int64_t)pl.M * pl.C}, coords.options());
  auto others = at::empty({N, (int64_t)pl.M, stdr::HEX_PLANES, (int64_t)pl.C}, coords.options());
  stdr_cuda::hexplane_forward(pl, N, coords.data_ptr<float>(), feats.data_ptr<float>(), others.data_ptr<float>(),
                              stream);
  C10_CUDA_CHECK(cudaGetLastError());
  return {feats, others};
}

std::vector<at::Tensor> hexplane_backward(at::Tensor coords, std::vector<at::Tensor> planes, at::Tensor others,
                                          at::Tensor g_feats) {
  std::vector<at::Tensor> grads;
  for (const auto& t : planes) grads.push_back(at::zeros_like(t));
  const auto pl = hex_planes(coords, planes, &grads);
  const int64_t N = coords.size(0);
  TORCH_CHECK(others.is_cuda() && others.is_contiguous() && others.numel() == N * pl.M * stdr::HEX_PLANES * pl.C,
              "stdr CUDA hexplane backward: others must be the forward's");
  TORCH_CHECK(g_feats.is_cuda() && g_feats.is_contiguous() && g_feats.scalar_type() == at::kFloat &&
                  g_feats.numel() == N * pl.M * pl.C,
              "stdr CUDA hexplane backward: g_feats must be a contiguous float32 [N, M*C] CUDA tensor");
  const at::cuda::CUDAGuard guard(coords.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  stdr_cuda::hexplane_backward(pl, N, coords.data_ptr<float>(), others.data_ptr<float>(), g_feats.data_ptr<float>(),
                               stream);
  C10_CUDA_CHECK(cudaGetLastError());
  return grads;
}

}  // namespace
