// Torch binding of the CUDA rasterizer: same functions and return values as the CPU backend
// (raster_cpu.cpp), so stdr/render/compiled.py drives both the same way. Sorting (depth order,
// Gaussian-tile keys) and scans use ATen; the kernels live in raster_kernels.cu.
#include <torch/extension.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "../raster_math.h"
#include "../hexplane_math.h"
#include "raster_kernels.h"

#include <algorithm>
#include <climits>

namespace {

// The Gaussian-tile pairs of packed rows, by tile then depth (pair_ids [P] int32, tile_offsets
// [n_tiles + 1]): a pass counts each row's tiles, a scan gives its slots, a second pass writes
// its keys there (both passes: raster_math.h's gaussian_tile_keys, which keeps the second inside
// the first's slots). The second pass reads `emit`, which is `packed` except in the test that
// makes the two passes disagree on purpose (bin_pairs_split). Keys of slots a row did not fill
// sort after the last tile: pair_ids may hold a few ids past tile_offsets[n_tiles], in no list.
void bin_pairs(const at::Tensor& packed, const at::Tensor& emit, const at::Tensor& vradii, int64_t width,
               int64_t height, int64_t tile, cudaStream_t stream, at::Tensor& pair_ids, at::Tensor& tile_offsets) {
  const int64_t V = packed.size(0);
  const int D = (int)packed.size(1);
  const int ntx = (int)((width + tile - 1) / tile), nty = (int)((height + tile - 1) / tile);
  const int64_t n_tiles = (int64_t)ntx * nty;
  auto counts = at::zeros({V}, vradii.options());
  stdr_cuda::count_tiles(packed.data_ptr<float>(), vradii.data_ptr<int32_t>(), V, D, (int)width, (int)height,
                         (int)tile, counts.data_ptr<int32_t>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  auto ends = at::cumsum(counts, 0, at::kLong);
  const int64_t P = V > 0 ? ends[-1].item<int64_t>() : 0;
  auto offsets = ends - counts.to(at::kLong);
  auto keys = at::empty({P}, packed.options().dtype(at::kLong));
  stdr_cuda::emit_pairs(emit.data_ptr<float>(), vradii.data_ptr<int32_t>(), V, D, (int)width, (int)height,
                        (int)tile, counts.data_ptr<int32_t>(), offsets.data_ptr<int64_t>(),
                        keys.data_ptr<int64_t>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  auto sorted = std::get<0>(at::sort(keys));  // (tile, depth rank): radix sort on the GPU
  pair_ids = at::bitwise_and(sorted, 0xffffffffLL).to(at::kInt);
  auto tiles = at::bitwise_right_shift(sorted, 32);
  auto bounds = at::arange(n_tiles + 1, tiles.options());
  tile_offsets = at::searchsorted(tiles, bounds);  // first pair of each tile; the last: end of the lists
}

// The visible Gaussians front to back, packed one row each (packed [V, 6+F], order [V]: packed row
// v is Gaussian order[v]), and their Gaussian-tile pairs (bin_pairs): what forward() and score()
// composite.
void pack_and_bin(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                  const at::Tensor& feats, const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                  int64_t height, int64_t tile, cudaStream_t stream, at::Tensor& packed, at::Tensor& order,
                  at::Tensor& pair_ids, at::Tensor& tile_offsets) {
  const int64_t F = feats.size(1);
  const int D = stdr::PACK_BASE + (int)F;
  auto vis = at::nonzero(radii > 0).squeeze(1);
  order = vis.index_select(0, at::argsort(depths.index_select(0, vis), /*stable=*/true));
  const int64_t V = order.size(0);
  packed = at::empty({V, D}, means2d.options());
  auto vradii = at::empty({V}, radii.options());
  stdr_cuda::pack_rows(means2d.data_ptr<float>(), conics.data_ptr<float>(),
                       opac.data_ptr<float>(), feats.data_ptr<float>(),
                       radii.data_ptr<int32_t>(), order.data_ptr<int64_t>(), V, (int)F,
                       packed.data_ptr<float>(), vradii.data_ptr<int32_t>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  bin_pairs(packed, packed, vradii, width, height, tile, stream, pair_ids, tile_offsets);
}

// For the tests: bin_pairs with the count pass reading `packed` and the write pass `emit` (rows
// of the same shape), so that the two disagree as far as a test wants. Returns (pair_ids,
// tile_offsets).
std::vector<at::Tensor> bin_pairs_split(at::Tensor packed, at::Tensor emit, at::Tensor vradii, int64_t width,
                                        int64_t height, int64_t tile) {
  TORCH_CHECK(packed.is_cuda() && emit.is_cuda() && vradii.is_cuda(),
              "stdr CUDA bin_pairs_split: every input must be a CUDA tensor");
  TORCH_CHECK(packed.scalar_type() == at::kFloat && emit.scalar_type() == at::kFloat &&
                  vradii.scalar_type() == at::kInt && packed.dim() == 2 && packed.sizes() == emit.sizes() &&
                  packed.size(1) > stdr::PACK_BASE && vradii.numel() == packed.size(0),
              "stdr CUDA bin_pairs_split: packed and emit float32 [V, D], vradii int32 [V]");
  TORCH_CHECK(tile == 8 || tile == 16, "stdr CUDA rasterizer: render.tile_size must be 8 or 16");
  const at::cuda::CUDAGuard guard(packed.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  at::Tensor pair_ids, tile_offsets;
  bin_pairs(packed.contiguous(), emit.contiguous(), vradii.contiguous(), width, height, tile, stream, pair_ids,
            tile_offsets);
  return {pair_ids, tile_offsets};
}

std::vector<at::Tensor> forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac,
                                at::Tensor feats, at::Tensor depths, at::Tensor radii,
                                int64_t width, int64_t height, int64_t tile) {
  // compiled.check_inputs checks the whole contract first, with the values in its messages;
  // these checks keep literal messages (see there: formatted ones crashed one toolchain)
  const int64_t N = means2d.size(0);
  for (auto* p : {&means2d, &conics, &opac, &feats, &depths, &radii})
    TORCH_CHECK(p->is_cuda(), "stdr CUDA rasterizer: every input must be a CUDA tensor");
  TORCH_CHECK(conics.size(0) == N && opac.size(0) == N && feats.size(0) == N && depths.size(0) == N &&
              radii.size(0) == N, "stdr CUDA rasterizer: every input must have one row per Gaussian");
  TORCH_CHECK(means2d.scalar_type() == at::kFloat, "stdr CUDA rasterizer: float32 inputs only");
  // whole warps per block (the backward's warp sums) and shared memory under the 48 KB default
  TORCH_CHECK(tile == 8 || tile == 16, "stdr CUDA rasterizer: render.tile_size must be 8 or 16");
  const int64_t F = feats.size(1);
  TORCH_CHECK(F >= 1 && F <= stdr::MAX_CHANNELS,
              "stdr CUDA rasterizer: 1..stdr::MAX_CHANNELS feature channels only");
  const at::cuda::CUDAGuard guard(means2d.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  feats = feats.contiguous(); depths = depths.contiguous(); radii = radii.contiguous();
  at::Tensor packed, order, pair_ids, tile_offsets;
  pack_and_bin(means2d, conics, opac, feats, depths, radii, width, height, tile, stream, packed, order, pair_ids,
               tile_offsets);
  auto acc = at::zeros({height, width, F}, means2d.options());
  auto T_img = at::ones({height, width}, means2d.options());
  auto last = at::zeros({height, width}, radii.options());
  stdr_cuda::forward(packed.data_ptr<float>(), (int)F, pair_ids.data_ptr<int32_t>(),
                     tile_offsets.data_ptr<int64_t>(), (int)width, (int)height, (int)tile,
                     acc.data_ptr<float>(), T_img.data_ptr<float>(), last.data_ptr<int32_t>(),
                     stream);
  C10_CUDA_CHECK(cudaGetLastError());
  return {acc, T_img, last, pair_ids, tile_offsets, packed, order};
}

std::vector<at::Tensor> backward(at::Tensor packed, at::Tensor order, int64_t N,
                                 at::Tensor pair_ids, at::Tensor tile_offsets, at::Tensor T_img,
                                 at::Tensor last, at::Tensor g_acc, at::Tensor g_T,
                                 int64_t width, int64_t height, int64_t tile) {
  for (auto* p : {&packed, &order, &pair_ids, &tile_offsets, &T_img, &last, &g_acc, &g_T})
    TORCH_CHECK(p->is_cuda(), "stdr CUDA rasterizer backward: every input must be a CUDA tensor");
  const at::cuda::CUDAGuard guard(packed.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  g_acc = g_acc.contiguous().to(at::kFloat);
  g_T = g_T.contiguous().to(at::kFloat);
  const int64_t D = packed.size(1), F = D - stdr::PACK_BASE;
  auto grad_packed = at::zeros_like(packed);
  stdr_cuda::backward(packed.data_ptr<float>(), (int)F, pair_ids.data_ptr<int32_t>(),
                      tile_offsets.data_ptr<int64_t>(), (int)width, (int)height, (int)tile,
                      g_acc.data_ptr<float>(), g_T.data_ptr<float>(), T_img.data_ptr<float>(),
                      last.data_ptr<int32_t>(), grad_packed.data_ptr<float>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  auto full = at::zeros({N, D}, packed.options());
  full.index_copy_(0, order, grad_packed);
  return {full.slice(1, 0, 2).contiguous(), full.slice(1, 2, 5).contiguous(),
          full.select(1, 5).contiguous(), full.slice(1, stdr::PACK_BASE, D).contiguous()};
}

// score [N]: each Gaussian's blending weight alpha * T summed over the image (0 where not rendered);
// the same contract as the CPU backend's score().
at::Tensor score(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor depths, at::Tensor radii,
                 int64_t width, int64_t height, int64_t tile) {
  const int64_t N = means2d.size(0);
  for (auto* p : {&means2d, &conics, &opac, &depths, &radii})
    TORCH_CHECK(p->is_cuda(), "stdr CUDA score: every input must be a CUDA tensor");
  TORCH_CHECK(conics.size(0) == N && opac.size(0) == N && depths.size(0) == N && radii.size(0) == N,
              "stdr CUDA score: every input must have one row per Gaussian");
  TORCH_CHECK(means2d.scalar_type() == at::kFloat, "stdr CUDA score: float32 inputs only");
  TORCH_CHECK(tile == 8 || tile == 16, "stdr CUDA score: render.tile_size must be 8 or 16");
  const at::cuda::CUDAGuard guard(means2d.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  depths = depths.contiguous(); radii = radii.contiguous();
  auto ones = at::ones({N, 1}, means2d.options());
  at::Tensor packed, order, pair_ids, tile_offsets;
  pack_and_bin(means2d, conics, opac, ones, depths, radii, width, height, tile, stream, packed, order, pair_ids,
               tile_offsets);
  auto sums = at::zeros({packed.size(0)}, means2d.options());
  stdr_cuda::score(packed.data_ptr<float>(), pair_ids.data_ptr<int32_t>(), tile_offsets.data_ptr<int64_t>(),
                   (int)width, (int)height, (int)tile, sums.data_ptr<float>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  auto out = at::zeros({N}, means2d.options());
  out.index_copy_(0, order, sums);
  return out;
}

// ---------------------------------------------------------------- projection and SH (project_math.h)

void check_project_cuda(const std::vector<at::Tensor*>& ts, const std::vector<double>& cam) {
  for (const at::Tensor* t : ts) {
    TORCH_CHECK(t->is_cuda(), "stdr CUDA projection: every input must be a CUDA tensor");
    TORCH_CHECK(t->scalar_type() == at::kFloat, "stdr CUDA projection: float32 inputs only");
    TORCH_CHECK(t->is_contiguous(), "stdr CUDA projection: inputs must be contiguous");
  }
  TORCH_CHECK((int)cam.size() == stdr::PROJ_CAM_VALUES, "stdr projection: the camera must be 26 values");
}

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opac,
                                        at::Tensor sh, std::vector<double> cam, int64_t width, int64_t height,
                                        bool antialiased, int64_t degree) {
  check_project_cuda({&means, &quats, &scales, &opac, &sh}, cam);
  TORCH_CHECK(sh.dim() == 3 && sh.size(1) >= (degree + 1) * (degree + 1) && sh.size(1) <= 16 && degree >= 0 &&
                  degree <= 3,
              "stdr projection: SH degree must be in [0, 3] with (degree + 1)^2 <= K <= 16");
  const at::cuda::CUDAGuard guard(means.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t N = means.size(0), K = sh.size(1);
  auto o = means.options();
  auto means2d = at::empty({N, 2}, o), depths = at::empty({N}, o), conics = at::empty({N, 3}, o);
  auto opac_out = at::empty({N}, o), colors = at::empty({N, 3}, o);
  auto radii = at::empty({N}, o.dtype(at::kInt));
  const auto c = stdr::make_proj_cam<float>(cam.data(), (int)width, (int)height, antialiased, (int)degree, (int)K);
  stdr_cuda::project_forward(c, N, means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(),
                             opac.data_ptr<float>(), sh.data_ptr<float>(), means2d.data_ptr<float>(),
                             depths.data_ptr<float>(), conics.data_ptr<float>(), opac_out.data_ptr<float>(),
                             radii.data_ptr<int32_t>(), colors.data_ptr<float>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  return {means2d, depths, conics, opac_out, radii, colors};
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opac,
                                         at::Tensor sh, at::Tensor g_m2d, at::Tensor g_depth, at::Tensor g_conic,
                                         at::Tensor g_opac, at::Tensor g_color, std::vector<double> cam,
                                         int64_t width, int64_t height, bool antialiased, int64_t degree) {
  check_project_cuda({&means, &quats, &scales, &opac, &sh, &g_m2d, &g_depth, &g_conic, &g_opac, &g_color}, cam);
  const at::cuda::CUDAGuard guard(means.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t N = means.size(0), K = sh.size(1);
  auto gm = at::empty_like(means), gq = at::empty_like(quats), gs = at::empty_like(scales);
  auto go = at::empty_like(opac), gh = at::empty_like(sh);
  const auto c = stdr::make_proj_cam<float>(cam.data(), (int)width, (int)height, antialiased, (int)degree, (int)K);
  stdr_cuda::project_backward(c, N, means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(),
                              opac.data_ptr<float>(), sh.data_ptr<float>(), g_m2d.data_ptr<float>(),
                              g_depth.data_ptr<float>(), g_conic.data_ptr<float>(), g_opac.data_ptr<float>(),
                              g_color.data_ptr<float>(), gm.data_ptr<float>(), gq.data_ptr<float>(),
                              gs.data_ptr<float>(), go.data_ptr<float>(), gh.data_ptr<float>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  return {gm, gq, gs, go, gh};
}

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

// ---------------------------------------------------------------- the training loss and the guard's check

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

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "tile rasterizer forward (CUDA)");
  m.def("backward", &backward, "tile rasterizer backward (CUDA)");
  m.def("score", &score, "contribution score: blending weight summed per Gaussian (CUDA)");
  m.def("bin_pairs_split", &bin_pairs_split, "Gaussian-tile binning, count and write passes on given rows (tests)");
  m.def("project_forward", &project_forward, "projection and SH forward (CUDA)");
  m.def("project_backward", &project_backward, "projection and SH backward (CUDA)");
  m.def("hexplane_forward", &hexplane_forward, "HexPlane features and the others-products (CUDA)");
  m.def("hexplane_backward", &hexplane_backward, "HexPlane plane gradients (CUDA, atomic adds)");
  m.def("image_loss_forward", &image_loss_forward, "(1 - lam) L1 + lam (1 - SSIM), its stats and partials (CUDA)");
  m.def("image_loss_backward", &image_loss_backward, "the image gradient of image_loss (CUDA, deterministic)");
  m.def("guard_update", &guard_update, "the sync-free guard's per-step update, in place (CUDA)");
}
