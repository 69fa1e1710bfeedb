// The training-loss family of the CUDA extension's host side (ops_cuda.cpp binds it; twin
// stdr.metrics.image_loss); the kernels live in kernels.cu.
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

// ---------------------------------------------------------------- the training loss

void check_loss_images(const at::Tensor& img, const at::Tensor& gt) {
  TORCH_CHECK(img.is_cuda() && gt.is_cuda() && img.get_device() == gt.get_device() &&
                  img.scalar_type() == at::kFloat && gt.scalar_type() == at::kFloat && img.dim() == 3 &&
                  img.sizes() == gt.sizes(),
              "stdr CUDA image_loss: img and gt must be float32 [H, W, C] tensors of one shape on one GPU");
}

std::vector<at::Tensor> image_loss_forward(at::Tensor img, at::Tensor gt, double lam, int64_t window, double sigma) {
  check_loss_images(img, gt);
  TORCH_CHECK(window % 2 == 1 && window >= 1 && window <= stdr::LOSS_MAX_WINDOW,
              "stdr CUDA image_loss: window must be odd, 1..31");
  img = img.contiguous();
  gt = gt.contiguous();
  const at::cuda::CUDAGuard guard(img.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t H = img.size(0), W = img.size(1), C = img.size(2), n = H * W * C;
  const bool grad = lam != 0.0;
  auto loss = at::empty({}, img.options());
  auto stats = at::empty({3}, img.options());
  auto partials = grad ? at::empty({3, H, W, C}, img.options()) : at::empty({0}, img.options());
  auto vt = at::empty({5 * n}, img.options());
  auto sums = at::empty({3 * stdr_cuda::loss_blocks(n)}, img.options().dtype(at::kDouble));
  if (n > 0) {
    stdr_cuda::image_loss_forward(img.data_ptr<float>(), gt.data_ptr<float>(), H, W, C,
                                  stdr_cuda::loss_window_f(window, sigma), lam, vt.data_ptr<float>(),
                                  grad ? partials.data_ptr<float>() : nullptr, sums.data_ptr<double>(),
                                  loss.data_ptr<float>(), stats.data_ptr<float>(), stream);
    C10_CUDA_CHECK(cudaGetLastError());
  }
  return {loss, stats, partials};
}

at::Tensor image_loss_backward(at::Tensor g_loss, at::Tensor img, at::Tensor gt, at::Tensor partials, double lam,
                               int64_t window, double sigma) {
  check_loss_images(img, gt);
  TORCH_CHECK(g_loss.is_cuda() && g_loss.get_device() == img.get_device() && g_loss.numel() == 1 &&
                  g_loss.scalar_type() == at::kFloat,
              "stdr CUDA image_loss: the loss gradient must be a float32 scalar on the images' GPU");
  img = img.contiguous();
  gt = gt.contiguous();
  g_loss = g_loss.contiguous();
  const int64_t H = img.size(0), W = img.size(1), C = img.size(2), n = H * W * C;
  const bool grad = lam != 0.0;
  TORCH_CHECK(!grad || (partials.is_cuda() && partials.is_contiguous() && partials.numel() == 3 * n),
              "stdr CUDA image_loss: partials do not match the image");
  const at::cuda::CUDAGuard guard(img.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  auto out = at::empty_like(img);
  auto vt = at::empty({grad ? 3 * n : 0}, img.options());
  if (n > 0) {
    stdr_cuda::image_loss_backward(img.data_ptr<float>(), gt.data_ptr<float>(),
                                   grad ? partials.data_ptr<float>() : nullptr, H, W, C,
                                   stdr_cuda::loss_window_f(window, sigma), lam, g_loss.data_ptr<float>(),
                                   vt.data_ptr<float>(), out.data_ptr<float>(), stream);
    C10_CUDA_CHECK(cudaGetLastError());
  }
  return out;
}

}  // namespace
