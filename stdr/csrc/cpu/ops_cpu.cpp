// The CPU extension: one module, five kernel families, each in its own header beside the math it
// shares with the CUDA backend, each with a torch twin that the tests pin it to:
//
//   rasterizer (raster_cpu.h)   forward, backward, score, bin_pairs_split, forward_bounded, project_forward/backward
//                               twins: stdr/render/reference.py, projection.py, sh.py
//   HexPlane (hexplane_cpu.h)   hexplane_forward/backward          twin: stdr/baselines/fourdgs.py
//   training loss (loss_cpu.h)  image_loss_forward/backward        twin: stdr/metrics.py image_loss
//   guard (guard_cpu.h)         nonfinite_flags, guard_update      twin: stdr/train/guard.py
//   nearest points (knn_cpu.h)  knn_direct                         twin: stdr/knn.py knn_direct
//
// Built and loaded by stdr/extension.py; the Python bindings of each family sit beside its twin.
// One translation unit, so that every kernel is compiled as one unit as it always was.
#include <torch/extension.h>

#include "guard_cpu.h"
#include "hexplane_cpu.h"
#include "knn_cpu.h"
#include "loss_cpu.h"
#include "raster_cpu.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  // rasterizer
  m.def("forward", &forward, "tile rasterizer forward (CPU)");
  m.def("forward_bounded", &forward_bounded, "the CUDA backend's capture-safe forward on the CPU (tests)");
  m.def("backward", &backward, "tile rasterizer backward (CPU)");
  m.def("score", &score, "contribution score: blending weight summed per Gaussian (CPU)");
  m.def("bin_pairs_split", &bin_pairs_split, "the CUDA backend's two-pass binning on the CPU (tests)");
  m.def("project_forward", &project_forward, "projection and SH forward (CPU)");
  m.def("project_backward", &project_backward, "projection and SH backward (CPU)");
  // HexPlane
  m.def("hexplane_forward", &hexplane_forward, "HexPlane features and the others-products (CPU)");
  m.def("hexplane_backward", &hexplane_backward, "HexPlane plane gradients (CPU, deterministic)");
  // training loss
  m.def("image_loss_forward", &image_loss_forward, "(1 - lam) L1 + lam (1 - SSIM), its stats and partials (CPU)");
  m.def("image_loss_backward", &image_loss_backward, "the image gradient of image_loss (CPU, deterministic)");
  // guard
  m.def("nonfinite_flags", &nonfinite_flags, "one bool per tensor: has a NaN or an infinity (CPU)");
  m.def("guard_update", &guard_update, "the sync-free guard's per-step update, in place (CPU)");
  // nearest points
  m.def("knn_direct", &knn_direct, "the k nearest points of each query, ties to the lower index (CPU)");
}
