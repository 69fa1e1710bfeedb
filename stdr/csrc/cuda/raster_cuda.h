// The rasterizer family of the CUDA extension's host side (ops_cuda.cpp binds it): the same
// functions and return values as the CPU backend (../cpu/raster_cpu.h), so stdr/render/compiled.py
// drives both the same way. Sorting (depth order, Gaussian-tile keys) and scans use ATen; the
// kernels live in kernels.cu.
#pragma once

#include <torch/extension.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <climits>
#include <vector>

#include "kernels.h"
#include "../raster_math.h"

namespace {

// The Gaussian-tile pairs of packed rows, by tile then depth (pair_ids [P] int32, tile_offsets
// [n_tiles + 1]): a pass counts each row's tiles, a scan gives its slots, a second pass writes
// its keys there (both passes: raster_math.h's gaussian_tile_keys, which keeps the second inside
// the first's slots). The second pass reads `emit`, which is `packed` except in the test that
// makes the two passes disagree on purpose (bin_pairs_split). Keys of slots a row did not fill
// sort after the last tile: pair_ids may hold a few ids past tile_offsets[n_tiles], in no list.
//
// capacity < 0: the key buffer is sized by the total, read on the host (one sync). capacity >= 0
// (the capture-safe form): a buffer of that many keys, filled first with a key that sorts after
// every tile's; a row's keys past the capacity are dropped (the deepest rows', as rows are in
// depth order), and `total` [] int64 (on the device) says how many pairs there were: the caller
// compares it with the capacity when it reads the device anyway. No host sync.
void bin_pairs(const at::Tensor& packed, const at::Tensor& emit, const at::Tensor& vradii, int64_t width,
               int64_t height, int64_t tile, cudaStream_t stream, at::Tensor& pair_ids, at::Tensor& tile_offsets,
               int64_t capacity, at::Tensor& total) {
  const int64_t V = packed.size(0);
  const int D = (int)packed.size(1);
  const int ntx = (int)((width + tile - 1) / tile), nty = (int)((height + tile - 1) / tile);
  const int64_t n_tiles = (int64_t)ntx * nty;
  auto counts = at::zeros({V}, vradii.options());
  stdr_cuda::count_tiles(packed.data_ptr<float>(), vradii.data_ptr<int32_t>(), V, D, (int)width, (int)height,
                         (int)tile, counts.data_ptr<int32_t>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  auto ends = at::cumsum(counts, 0, at::kLong);
  total = V > 0 ? ends.select(0, V - 1).clone() : at::zeros({}, ends.options());
  const int64_t P = capacity >= 0 ? capacity : total.item<int64_t>();
  auto offsets = ends - counts.to(at::kLong);
  auto keys = capacity >= 0 ? at::full({P}, (n_tiles << 32) | 0x7fffffffLL, packed.options().dtype(at::kLong))
                            : at::empty({P}, packed.options().dtype(at::kLong));
  stdr_cuda::emit_pairs(emit.data_ptr<float>(), vradii.data_ptr<int32_t>(), V, D, (int)width, (int)height,
                        (int)tile, counts.data_ptr<int32_t>(), offsets.data_ptr<int64_t>(),
                        keys.data_ptr<int64_t>(), P, stream);
  C10_CUDA_CHECK(cudaGetLastError());
  auto sorted = std::get<0>(at::sort(keys));  // (tile, depth rank): radix sort on the GPU
  pair_ids = at::bitwise_and(sorted, 0xffffffffLL).to(at::kInt);
  auto tiles = at::bitwise_right_shift(sorted, 32);
  auto bounds = at::arange(n_tiles + 1, tiles.options());
  tile_offsets = at::searchsorted(tiles, bounds);  // first pair of each tile; the last: end of the lists
}

// The rows of Gaussians order[v], packed one row each (packed [V, 6+F]); returns their radii [V].
at::Tensor pack(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac, const at::Tensor& feats,
                const at::Tensor& radii, const at::Tensor& order, cudaStream_t stream, at::Tensor& packed) {
  const int64_t V = order.size(0), F = feats.size(1);
  packed = at::empty({V, stdr::PACK_BASE + F}, means2d.options());
  auto vradii = at::empty({V}, radii.options());
  stdr_cuda::pack_rows(means2d.data_ptr<float>(), conics.data_ptr<float>(),
                       opac.data_ptr<float>(), feats.data_ptr<float>(),
                       radii.data_ptr<int32_t>(), order.data_ptr<int64_t>(), V, (int)F,
                       packed.data_ptr<float>(), vradii.data_ptr<int32_t>(), stream);
  C10_CUDA_CHECK(cudaGetLastError());
  return vradii;
}

// The visible Gaussians front to back, packed one row each (packed [V, 6+F], order [V]: packed row
// v is Gaussian order[v]), and their Gaussian-tile pairs (bin_pairs): what forward() and score()
// composite.
void pack_and_bin(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                  const at::Tensor& feats, const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                  int64_t height, int64_t tile, cudaStream_t stream, at::Tensor& packed, at::Tensor& order,
                  at::Tensor& pair_ids, at::Tensor& tile_offsets) {
  auto vis = at::nonzero(radii > 0).squeeze(1);
  order = vis.index_select(0, at::argsort(depths.index_select(0, vis), /*stable=*/true));
  auto vradii = pack(means2d, conics, opac, feats, radii, order, stream, packed);
  at::Tensor total;
  bin_pairs(packed, packed, vradii, width, height, tile, stream, pair_ids, tile_offsets, -1, total);
}

// The capture-safe form of pack_and_bin: no host sync. All N rows are packed, the visible ones
// first in the same order as pack_and_bin's (stable by depth; the invisible ones after them, by
// index, radius 0: no tile), so the visible rows keep their packed indices and every pair is the
// same; the pairs go into a buffer of `capacity` keys (bin_pairs), `total` [] int64 the count.
void pack_all_and_bin(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                      const at::Tensor& feats, const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                      int64_t height, int64_t tile, int64_t capacity, cudaStream_t stream, at::Tensor& packed,
                      at::Tensor& order, at::Tensor& pair_ids, at::Tensor& tile_offsets, at::Tensor& total) {
  auto key = at::where(radii > 0, depths, at::full({}, INFINITY, depths.options()));
  order = at::argsort(key, /*stable=*/true);
  auto vradii = pack(means2d, conics, opac, feats, radii, order, stream, packed);
  bin_pairs(packed, packed, vradii, width, height, tile, stream, pair_ids, tile_offsets, capacity, total);
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
  at::Tensor pair_ids, tile_offsets, total;
  bin_pairs(packed.contiguous(), emit.contiguous(), vradii.contiguous(), width, height, tile, stream, pair_ids,
            tile_offsets, -1, total);
  return {pair_ids, tile_offsets};
}

// The forward's input contract, checked in both forms (compiled.check_inputs checks the whole
// contract first, with the values in its messages; these checks keep literal messages: formatted
// ones crashed one toolchain). Makes the inputs contiguous.
void check_forward(at::Tensor& means2d, at::Tensor& conics, at::Tensor& opac, at::Tensor& feats,
                   at::Tensor& depths, at::Tensor& radii, int64_t tile) {
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
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  feats = feats.contiguous(); depths = depths.contiguous(); radii = radii.contiguous();
}

// Front-to-back compositing of the binned rows: (acc [H, W, F], T [H, W], last [H, W] int32).
std::vector<at::Tensor> composite(const at::Tensor& packed, int64_t F, const at::Tensor& pair_ids,
                                  const at::Tensor& tile_offsets, const at::Tensor& like, const at::Tensor& radii,
                                  int64_t width, int64_t height, int64_t tile, cudaStream_t stream) {
  auto acc = at::zeros({height, width, F}, like.options());
  auto T_img = at::ones({height, width}, like.options());
  auto last = at::zeros({height, width}, radii.options());
  stdr_cuda::forward(packed.data_ptr<float>(), (int)F, pair_ids.data_ptr<int32_t>(),
                     tile_offsets.data_ptr<int64_t>(), (int)width, (int)height, (int)tile,
                     acc.data_ptr<float>(), T_img.data_ptr<float>(), last.data_ptr<int32_t>(),
                     stream);
  C10_CUDA_CHECK(cudaGetLastError());
  return {acc, T_img, last};
}

std::vector<at::Tensor> forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac,
                                at::Tensor feats, at::Tensor depths, at::Tensor radii,
                                int64_t width, int64_t height, int64_t tile) {
  check_forward(means2d, conics, opac, feats, depths, radii, tile);
  const at::cuda::CUDAGuard guard(means2d.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  at::Tensor packed, order, pair_ids, tile_offsets;
  pack_and_bin(means2d, conics, opac, feats, depths, radii, width, height, tile, stream, packed, order, pair_ids,
               tile_offsets);
  auto img = composite(packed, feats.size(1), pair_ids, tile_offsets, means2d, radii, width, height, tile, stream);
  return {img[0], img[1], img[2], pair_ids, tile_offsets, packed, order};
}

// The capture-safe forward (pack_all_and_bin): no host sync, so a CUDA graph can hold it.
// Returns forward()'s seven tensors, with packed [N, 6+F] and order [N] (every row) and pair_ids
// [capacity], and an eighth, total [] int64 on the device: the pairs the image needed. With total <=
// capacity the image is forward()'s, bit for bit; above it the deepest rows' pairs are missing, and
// the caller must render again with a larger capacity.
std::vector<at::Tensor> forward_bounded(at::Tensor means2d, at::Tensor conics, at::Tensor opac,
                                        at::Tensor feats, at::Tensor depths, at::Tensor radii,
                                        int64_t width, int64_t height, int64_t tile, int64_t capacity) {
  check_forward(means2d, conics, opac, feats, depths, radii, tile);
  TORCH_CHECK(capacity >= 0, "stdr CUDA rasterizer: the capture-safe forward needs a capacity >= 0");
  const at::cuda::CUDAGuard guard(means2d.device());
  auto stream = c10::cuda::getCurrentCUDAStream().stream();
  at::Tensor packed, order, pair_ids, tile_offsets, total;
  pack_all_and_bin(means2d, conics, opac, feats, depths, radii, width, height, tile, capacity, stream, packed, order,
                   pair_ids, tile_offsets, total);
  auto img = composite(packed, feats.size(1), pair_ids, tile_offsets, means2d, radii, width, height, tile, stream);
  return {img[0], img[1], img[2], pair_ids, tile_offsets, packed, order, total};
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

}  // namespace
