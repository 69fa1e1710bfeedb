// The CUDA extension: one module, four kernel families with the CPU extension's functions and
// return values (../cpu/ops_cpu.cpp lists them with their torch twins). The host side of each
// family is in its header (raster_cuda.h, hexplane_cuda.h, loss_cuda.h, guard_cuda.h); every
// kernel is in kernels.cu, whose launchers (kernels.h) need no torch headers, so that file
// compiles with nvcc alone. Built and loaded by stdr/extension.py.
#include <torch/extension.h>

#include "guard_cuda.h"
#include "hexplane_cuda.h"
#include "loss_cuda.h"
#include "raster_cuda.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  // rasterizer
  m.def("forward", &forward, "tile rasterizer forward (CUDA)");
  m.def("forward_bounded", &forward_bounded, "tile rasterizer forward without host syncs, pairs up to a capacity (CUDA)");
  m.def("backward", &backward, "tile rasterizer backward (CUDA)");
  m.def("score", &score, "contribution score: blending weight summed per Gaussian (CUDA)");
  m.def("bin_pairs_split", &bin_pairs_split, "Gaussian-tile binning, count and write passes on given rows (tests)");
  m.def("project_forward", &project_forward, "projection and SH forward (CUDA)");
  m.def("project_backward", &project_backward, "projection and SH backward (CUDA)");
  // HexPlane
  m.def("hexplane_forward", &hexplane_forward, "HexPlane features and the others-products (CUDA)");
  m.def("hexplane_backward", &hexplane_backward, "HexPlane plane gradients (CUDA, atomic adds)");
  // training loss
  m.def("image_loss_forward", &image_loss_forward, "(1 - lam) L1 + lam (1 - SSIM), its stats and partials (CUDA)");
  m.def("image_loss_backward", &image_loss_backward, "the image gradient of image_loss (CUDA, deterministic)");
  // guard
  m.def("guard_update", &guard_update, "the sync-free guard's per-step update, in place (CUDA)");
}
