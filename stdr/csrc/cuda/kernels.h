// Launchers for the CUDA kernels of every family (rasterizer, HexPlane, training loss, guard).
// Plain C++ on raw device pointers: no torch headers, so kernels.cu compiles with nvcc alone in seconds (tests do `nvcc -c` on it), and the
// torch binding (ops_cuda.cpp and the family headers) does allocation, sorting and scans with ATen.
#pragma once

#include <cstdint>
#include <cuda_runtime.h>

#include "../loss_math.h"
#include "../project_math.h"

namespace stdr_cuda {

// the planes of a HexPlane field (6 per scale, at most HEX_MAX_PLANES), passed by value to the kernels
constexpr int HEX_MAX_PLANES = 48;
struct HexPlanes {
  const float* ptr[HEX_MAX_PLANES];
  float* grad[HEX_MAX_PLANES];
  int H[HEX_MAX_PLANES], W[HEX_MAX_PLANES];
  int M, C;
};

// the training loss's window, in float, passed by value to the kernels
struct LossWindow {
  float g[stdr::LOSS_MAX_WINDOW];
  int R;  // radius: the window has 2R + 1 taps
};

// up to GUARD_MAX float32 tensors for one launch of the guard's check, passed by value; index is
// each tensor's position in the caller's list
constexpr int GUARD_MAX = 64;
struct GuardTable {
  const void* ptr[GUARD_MAX];
  int64_t numel[GUARD_MAX];
  int index[GUARD_MAX];
};

// packed[v] = [mx, my, a, b, c, o, f_0..f_{F-1}] of Gaussian order[v]; vradii[v] = radii[order[v]]
void pack_rows(const float* means2d, const float* conics, const float* opac, const float* feats,
               const int32_t* radii, const int64_t* order, int64_t V, int F, float* packed,
               int32_t* vradii, cudaStream_t stream);

// counts[v] = number of tiles whose in-image pixel centres the Gaussian's footprint reaches
void count_tiles(const float* packed, const int32_t* vradii, int64_t V, int D, int width,
                 int height, int tile, int32_t* counts, cudaStream_t stream);

// keys[offsets[v] + k] = (tile << 32) | v for the k-th touched tile (offsets: exclusive scan of
// counts), never beyond counts[v] slots nor beyond keys[capacity - 1] (the binning that sizes keys
// by the total passes it; the capture-safe one a fixed capacity); slots it does not reach get
// (n_tiles << 32) | v
void emit_pairs(const float* packed, const int32_t* vradii, int64_t V, int D, int width,
                int height, int tile, const int32_t* counts, const int64_t* offsets, int64_t* keys,
                int64_t capacity, cudaStream_t stream);

// One block per tile (tile x tile threads): front-to-back compositing.
void forward(const float* packed, int F, const int32_t* pair_ids, const int64_t* tile_offsets,
             int width, int height, int tile, float* out_acc, float* out_T, int32_t* out_last,
             cudaStream_t stream);

// One block per tile: back-to-front gradients, accumulated into grad_packed [V, 6 + F].
void backward(const float* packed, int F, const int32_t* pair_ids, const int64_t* tile_offsets,
              int width, int height, int tile, const float* g_acc, const float* g_T,
              const float* T_img, const int32_t* last_img, float* grad_packed,
              cudaStream_t stream);

// One block per tile: the forward's compositing with packed rows [V, 7] whose feature is 1;
// score_out[v] += the blending weight alpha * T of packed row v summed over the tile's pixels
// (score_out zeroed by the caller).
void score(const float* packed, const int32_t* pair_ids, const int64_t* tile_offsets, int width, int height,
           int tile, float* score_out, cudaStream_t stream);

// One thread per Gaussian: projection and SH shading (project_math.h), forward.
void project_forward(const stdr::ProjCam<float>& cam, int64_t N, const float* means, const float* quats,
                     const float* scales, const float* opac, const float* sh, float* means2d, float* depths,
                     float* conics, float* opac_out, int32_t* radii, float* colors, cudaStream_t stream);

// One thread per Gaussian: projection and SH shading, backward (every output row written).
void project_backward(const stdr::ProjCam<float>& cam, int64_t N, const float* means, const float* quats,
                      const float* scales, const float* opac, const float* sh, const float* g_m2d,
                      const float* g_depth, const float* g_conic, const float* g_opac, const float* g_color,
                      float* g_means, float* g_quats, float* g_scales, float* g_opac_in, float* g_sh,
                      cudaStream_t stream);

// One thread per (point, scale, channel): the HexPlane features feats [N, M*C] and, for each
// plane, the product of the five other samples, others [N, M, 6, C] (hexplane_math.h).
void hexplane_forward(const HexPlanes& planes, int64_t N, const float* coords, float* feats, float* others,
                      cudaStream_t stream);

// One thread per (point, scale, channel): the planes' gradients (planes.grad, zeroed by the
// caller) of sum(g_feats * feats), by atomic adds.
void hexplane_backward(const HexPlanes& planes, int64_t N, const float* coords, const float* others,
                       const float* g_feats, cudaStream_t stream);

// The training loss (stdr.render.compiled.image_loss_compiled): the window as floats, and the
// number of blocks whose sums block_sums [3 * loss_blocks(n)] holds (n = H * W * C).
LossWindow loss_window_f(int64_t window, double sigma);
int64_t loss_blocks(int64_t n);

// img a, gt b [H, W, C]; vt scratch [5 n]; P [3 n] the partials (null: lam = 0, none kept); loss
// [1] and stats [3] = (l1, 1 - ssim, psnr) written on the device.
void image_loss_forward(const float* a, const float* b, int64_t H, int64_t W, int64_t C, const LossWindow& w,
                        double lam, float* vt, float* P, double* block_sums, float* loss, float* stats,
                        cudaStream_t stream);

// out [n] = the gradient of g_loss[0] * loss by img; vt scratch [3 n] (unused when P is null).
void image_loss_backward(const float* a, const float* b, const float* P, int64_t H, int64_t W, int64_t C,
                         const LossWindow& w, double lam, const float* g_loss, float* vt, float* out,
                         cudaStream_t stream);

// *first = min(*first, index of each table tensor with a NaN or an infinity) (*first starts at INT_MAX)
void guard_check(const GuardTable& table, int count, int64_t max_numel, int* first, cudaStream_t stream);

// where *first < INT_MAX: flag = 1 and, if bad_step < 0, bad_step = step, bad_index = *first
void guard_finish(const int* first, float* flag, int64_t* bad_step, int64_t* bad_index, int64_t step,
                  cudaStream_t stream);

}  // namespace stdr_cuda
