// CUDA kernels of every family: rasterizer, HexPlane, training loss, guard (their host sides:
// raster_cuda.h, hexplane_cuda.h, loss_cuda.h, guard_cuda.h). The per-Gaussian and per-pixel
// arithmetic is the shared header's (raster_math.h), the same functions the CPU backend runs and
// the CPU tests check.
#include "kernels.h"

#include <climits>
#include "../raster_math.h"
#include "../hexplane_math.h"
#include "../loss_math.h"

namespace stdr_cuda {
namespace {

constexpr int WARP = 32;

// This thread's pixel: block = tile, thread = pixel of the tile in row-major order.
struct TilePixel {
  int x, y;
  bool inside;
  float px, py;  // pixel centre
  int64_t pix;   // row-major image index (valid when inside)
  __device__ TilePixel(int width, int height, int tile) {
    const int ntx = (width + tile - 1) / tile;
    x = ((int)blockIdx.x % ntx) * tile + (int)threadIdx.x % tile;
    y = ((int)blockIdx.x / ntx) * tile + (int)threadIdx.x / tile;
    inside = x < width && y < height;
    px = x + 0.5f;
    py = y + 0.5f;
    pix = (int64_t)y * width + x;
  }
};

__global__ void pack_kernel(const float* __restrict__ means2d, const float* __restrict__ conics,
                            const float* __restrict__ opac, const float* __restrict__ feats,
                            const int32_t* __restrict__ radii, const int64_t* __restrict__ order,
                            int64_t V, int F, float* __restrict__ packed,
                            int32_t* __restrict__ vradii) {
  const int64_t v = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (v >= V) return;
  const int64_t g = order[v];
  const int D = stdr::PACK_BASE + F;
  float* row = packed + v * D;
  row[0] = means2d[2 * g];
  row[1] = means2d[2 * g + 1];
  row[2] = conics[3 * g];
  row[3] = conics[3 * g + 1];
  row[4] = conics[3 * g + 2];
  row[5] = opac[g];
  for (int j = 0; j < F; ++j) row[stdr::PACK_BASE + j] = feats[g * F + j];
  vradii[v] = radii[g];
}

// Both binning passes run this one kernel (keys == nullptr: count; else write), so the float
// test of raster_math.h's gaussian_tile_keys is the same compiled code in both. The write pass
// is memory-safe even if the two disagreed: it writes only Gaussian v's counted slots
// [offsets[v], offsets[v] + counts[v]) and fills any it did not reach with a key outside every
// tile (gaussian_tile_keys).
__global__ void tiles_kernel(const float* __restrict__ packed, const int32_t* __restrict__ vradii,
                             int64_t V, int D, int width, int height, int tile,
                             int32_t* __restrict__ counts_out, const int32_t* __restrict__ counts,
                             const int64_t* __restrict__ offsets, int64_t* __restrict__ keys,
                             int64_t capacity) {
  const int64_t v = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (v >= V) return;
  const float* g = packed + v * D;
  if (keys == nullptr) {
    counts_out[v] = stdr::gaussian_tile_keys(g, vradii[v], width, height, tile, v, nullptr, 0);
    return;
  }
  // the row's slots, cut at the key buffer's capacity (its first tiles are kept)
  const int64_t room = capacity - offsets[v];
  const int64_t cap = room < (int64_t)counts[v] ? room : (int64_t)counts[v];
  if (cap > 0) stdr::gaussian_tile_keys(g, vradii[v], width, height, tile, v, keys + offsets[v], cap);
}

template <int F>
__global__ void forward_kernel(const float* __restrict__ packed,
                               const int32_t* __restrict__ pair_ids,
                               const int64_t* __restrict__ tile_offsets, int width, int height,
                               int tile, float* __restrict__ out_acc, float* __restrict__ out_T,
                               int32_t* __restrict__ out_last) {
  constexpr int D = stdr::PACK_BASE + F;
  extern __shared__ float rows[];  // [block, D]
  const TilePixel me(width, height, tile);
  const bool inside = me.inside;
  const float px = me.px, py = me.py;
  const int block = blockDim.x;
  const int64_t start = tile_offsets[blockIdx.x], end = tile_offsets[blockIdx.x + 1];

  float Tp = 1.0f, acc[F];
#pragma unroll
  for (int f = 0; f < F; ++f) acc[f] = 0.0f;
  int done = inside ? 0 : 1, last = 0;
  for (int64_t base = start; base < end; base += block) {
    if (__syncthreads_count(done) == block) break;
    const int64_t k = base + threadIdx.x;
    if (k < end) {
      const float* src = packed + (int64_t)pair_ids[k] * D;
#pragma unroll
      for (int j = 0; j < D; ++j) rows[threadIdx.x * D + j] = src[j];
    }
    __syncthreads();
    const int n = (int)min((int64_t)block, end - base);
    for (int i = 0; i < n && !done; ++i)
      stdr::forward_pixel<float, F>(rows + i * D, px, py, (int)(base - start) + i, Tp, done,
                                    last, acc, 1);
  }
  if (inside) {
    const int64_t pix = me.pix;
    out_T[pix] = Tp;
    out_last[pix] = last;
#pragma unroll
    for (int f = 0; f < F; ++f) out_acc[pix * F + f] = acc[f];
  }
}

__device__ __forceinline__ float warp_sum(float v) {
#pragma unroll
  for (int o = WARP / 2; o > 0; o >>= 1) v += __shfl_down_sync(0xffffffffu, v, o);
  return v;
}

template <int F>
__global__ void backward_kernel(const float* __restrict__ packed,
                                const int32_t* __restrict__ pair_ids,
                                const int64_t* __restrict__ tile_offsets, int width, int height,
                                int tile, const float* __restrict__ g_acc,
                                const float* __restrict__ g_T, const float* __restrict__ T_img,
                                const int32_t* __restrict__ last_img,
                                float* __restrict__ grad_packed) {
  constexpr int D = stdr::PACK_BASE + F;
  extern __shared__ float smem[];
  float* rows = smem;                                   // [block, D]
  int32_t* ids = (int32_t*)(smem + blockDim.x * D);     // [block]
  __shared__ int max_last;
  const TilePixel me(width, height, tile);
  const bool inside = me.inside;
  const float px = me.px, py = me.py;
  const int block = blockDim.x;
  const int64_t start = tile_offsets[blockIdx.x];
  const int64_t pix = me.pix;

  float G[F], behind[F];
#pragma unroll
  for (int f = 0; f < F; ++f) {
    G[f] = inside ? g_acc[pix * F + f] : 0.0f;
    behind[f] = 0.0f;
  }
  const float Tfin = inside ? T_img[pix] : 1.0f;
  const float GT = inside ? g_T[pix] : 0.0f;
  const int last = inside ? last_img[pix] : 0;
  float Tp = Tfin;
  if (threadIdx.x == 0) max_last = 0;
  __syncthreads();
  atomicMax(&max_last, last);
  __syncthreads();
  const int count = max_last;  // entries [0, count) of this tile's list matter

  float out[D];
  for (int top = count; top > 0; top -= block) {  // batches, back to front
    const int lo = max(0, top - block);
    __syncthreads();
    const int i = lo + threadIdx.x;
    if (i < top) {
      const int32_t v = pair_ids[start + i];
      ids[threadIdx.x] = v;
      const float* src = packed + (int64_t)v * D;
#pragma unroll
      for (int j = 0; j < D; ++j) rows[threadIdx.x * D + j] = src[j];
    }
    __syncthreads();
    for (int idx = top - 1; idx >= lo; --idx) {  // every thread walks the same entries
      const int r = idx - lo;
      stdr::backward_pixel<float, F>(rows + r * D, px, py, idx < last, Tp, behind, G, GT, Tfin,
                                     1, out);
      float* dst = grad_packed + (int64_t)ids[r] * D;
#pragma unroll
      for (int j = 0; j < D; ++j) {
        const float s = warp_sum(out[j]);
        if ((threadIdx.x & (WARP - 1)) == 0 && s != 0.0f) atomicAdd(dst + j, s);
      }
    }
  }
}

// The contribution score pass: forward_kernel's compositing with one feature channel of ones
// (packed rows [.., 1]), so a pixel's "accumulated feature" from a Gaussian is its blending weight
// alpha * T; a warp sums its pixels' weights and one lane adds the sum to the Gaussian's score.
// Every thread walks the whole batch (a stopped pixel adds 0), so the warp sums see full warps.
// The atomic adds make the float sum order, and so the last bits, vary from run to run.
__global__ void score_kernel(const float* __restrict__ packed, const int32_t* __restrict__ pair_ids,
                             const int64_t* __restrict__ tile_offsets, int width, int height, int tile,
                             float* __restrict__ score) {
  constexpr int D = stdr::PACK_BASE + 1;
  extern __shared__ float smem[];
  float* rows = smem;                                // [block, D]
  int32_t* ids = (int32_t*)(smem + blockDim.x * D);  // [block]
  const TilePixel me(width, height, tile);
  const float px = me.px, py = me.py;
  const int block = blockDim.x;
  const int64_t start = tile_offsets[blockIdx.x], end = tile_offsets[blockIdx.x + 1];
  float Tp = 1.0f;
  int done = me.inside ? 0 : 1, last = 0;
  for (int64_t base = start; base < end; base += block) {
    if (__syncthreads_count(done) == block) break;
    const int64_t k = base + threadIdx.x;
    if (k < end) {
      const int32_t v = pair_ids[k];
      ids[threadIdx.x] = v;
      const float* src = packed + (int64_t)v * D;
#pragma unroll
      for (int j = 0; j < D; ++j) rows[threadIdx.x * D + j] = src[j];
    }
    __syncthreads();
    const int n = (int)min((int64_t)block, end - base);
    for (int i = 0; i < n; ++i) {
      float w = 0.0f;
      stdr::forward_pixel<float, 1>(rows + i * D, px, py, (int)(base - start) + i, Tp, done, last, &w, 1);
      const float s = warp_sum(w);
      if ((threadIdx.x & (WARP - 1)) == 0 && s != 0.0f) atomicAdd(score + ids[i], s);
    }
  }
}

template <int F> void launch_forward(const float* packed, const int32_t* pair_ids,
                                     const int64_t* tile_offsets, int width, int height,
                                     int tile, float* out_acc, float* out_T, int32_t* out_last,
                                     cudaStream_t stream) {
  const int ntiles = ((width + tile - 1) / tile) * ((height + tile - 1) / tile);
  const int block = tile * tile;
  const size_t shm = (size_t)block * (stdr::PACK_BASE + F) * sizeof(float);
  forward_kernel<F><<<ntiles, block, shm, stream>>>(packed, pair_ids, tile_offsets, width,
                                                    height, tile, out_acc, out_T, out_last);
}

template <int F> void launch_backward(const float* packed, const int32_t* pair_ids,
                                      const int64_t* tile_offsets, int width, int height,
                                      int tile, const float* g_acc, const float* g_T,
                                      const float* T_img, const int32_t* last_img,
                                      float* grad_packed, cudaStream_t stream) {
  const int ntiles = ((width + tile - 1) / tile) * ((height + tile - 1) / tile);
  const int block = tile * tile;
  const size_t shm = (size_t)block * ((stdr::PACK_BASE + F) * sizeof(float) + sizeof(int32_t));
  backward_kernel<F><<<ntiles, block, shm, stream>>>(packed, pair_ids, tile_offsets, width,
                                                     height, tile, g_acc, g_T, T_img, last_img,
                                                     grad_packed);
}

#define STDR_DISPATCH_F(F, CALL)          \
  switch (F) {                            \
    case 1: CALL(1); break;               \
    case 2: CALL(2); break;               \
    case 3: CALL(3); break;               \
    case 4: CALL(4); break;               \
    case 5: CALL(5); break;               \
    case 6: CALL(6); break;               \
    case 7: CALL(7); break;               \
    case 8: CALL(8); break;               \
    default: break;                       \
  }


// ---------------------------------------------------------------- the training loss
// img, gt [H, W, C] as rows of RW = W*C values; n = H*RW. Five launches in all (three forward,
// two backward); the sums are per block, added in block order by one block: deterministic.

constexpr int LOSS_THREADS = 256;

__global__ void loss_vpass5_kernel(const float* __restrict__ a, const float* __restrict__ b, int64_t H, int64_t RW,
                                   LossWindow w, float* __restrict__ vt) {
  const int64_t n = H * RW, idx = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (idx >= n) return;
  const int64_t y = idx / RW, i = idx % RW;
  float s0 = 0.f, s1 = 0.f, s2 = 0.f, s3 = 0.f, s4 = 0.f;
  for (int j = 0; j < 2 * w.R + 1; ++j) {
    const int64_t yy = y + j - w.R;
    if (yy < 0 || yy >= H) continue;
    const float g = w.g[j], av = a[yy * RW + i], bv = b[yy * RW + i];
    s0 += g * av;
    s1 += g * bv;
    s2 += g * (av * av);
    s3 += g * (bv * bv);
    s4 += g * (av * bv);
  }
  vt[idx] = s0;
  vt[n + idx] = s1;
  vt[2 * n + idx] = s2;
  vt[3 * n + idx] = s3;
  vt[4 * n + idx] = s4;
}

// The horizontal pass of K maps at element idx: out[k] = sum_j g[j] * vt[k][y][i + (j - R) C].
template <int K>
__device__ __forceinline__ void loss_hpass(const float* __restrict__ vt, int64_t n, int64_t RW, int64_t C,
                                           const LossWindow& w, int64_t idx, float* out) {
  const int64_t i = idx % RW, row = idx - i;
  for (int k = 0; k < K; ++k) out[k] = 0.f;
  for (int j = 0; j < 2 * w.R + 1; ++j) {
    const int64_t ii = i + (int64_t)(j - w.R) * C;
    if (ii < 0 || ii >= RW) continue;
    for (int k = 0; k < K; ++k) out[k] += w.g[j] * vt[k * n + row + ii];
  }
}

// Sum of v over the block into *out (a fixed tree: the same order every run).
__device__ __forceinline__ void loss_block_sum(double v, double* shared, double* out) {
  shared[threadIdx.x] = v;
  __syncthreads();
  for (int s = blockDim.x / 2; s > 0; s >>= 1) {
    if ((int)threadIdx.x < s) shared[threadIdx.x] += shared[threadIdx.x + s];
    __syncthreads();
  }
  if (threadIdx.x == 0) *out = shared[0];
  __syncthreads();
}

__global__ void loss_ssim_kernel(const float* __restrict__ vt, const float* __restrict__ a,
                                 const float* __restrict__ b, int64_t H, int64_t RW, int64_t C, LossWindow w,
                                 float* __restrict__ P, double* __restrict__ block_sums) {
  __shared__ double shared[LOSS_THREADS];
  const int64_t n = H * RW, idx = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  double ss = 0.0, sl = 0.0, sq = 0.0;
  if (idx < n) {
    float f[5];
    loss_hpass<5>(vt, n, RW, C, w, idx, f);
    float S;
    if (P) {
      float p0, p1, p2;
      S = stdr::ssim_pixel<float>(f[0], f[1], f[2], f[3], f[4], p0, p1, p2);
      P[idx] = p0;
      P[n + idx] = p1;
      P[2 * n + idx] = p2;
    } else {
      S = stdr::ssim_value<float>(f[0], f[1], f[2], f[3], f[4]);
    }
    const float d = a[idx] - b[idx];
    ss = S;
    sl = fabsf(d);
    sq = (double)d * d;
  }
  double* out = block_sums + 3 * (int64_t)blockIdx.x;
  loss_block_sum(ss, shared, out);
  loss_block_sum(sl, shared, out + 1);
  loss_block_sum(sq, shared, out + 2);
}

// One block: the blocks' sums in block order (each thread a fixed stride, then a fixed tree),
// then loss and stats (l1, 1 - ssim, psnr).
__global__ void loss_finish_kernel(const double* __restrict__ block_sums, int64_t blocks, int64_t n, double lam,
                                   float* __restrict__ loss, float* __restrict__ stats) {
  __shared__ double shared[LOSS_THREADS];
  __shared__ double tot[3];
  for (int k = 0; k < 3; ++k) {
    double v = 0.0;
    for (int64_t q = threadIdx.x; q < blocks; q += blockDim.x) v += block_sums[3 * q + k];
    loss_block_sum(v, shared, tot + k);
  }
  if (threadIdx.x == 0) {
    const double N = (double)n, l1 = tot[1] / N, dssim = 1.0 - tot[0] / N, mse = tot[2] / N;
    loss[0] = (float)((1.0 - lam) * l1 + lam * dssim);
    stats[0] = (float)l1;
    stats[1] = (float)dssim;
    stats[2] = (float)(10.0 * log10(1.0 / fmax(mse, 1e-20)));
  }
}

__global__ void loss_vpass3_kernel(const float* __restrict__ P, int64_t H, int64_t RW, LossWindow w,
                                   float* __restrict__ vt) {
  const int64_t n = H * RW, idx = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (idx >= n) return;
  const int64_t y = idx / RW, i = idx % RW;
  float s0 = 0.f, s1 = 0.f, s2 = 0.f;
  for (int j = 0; j < 2 * w.R + 1; ++j) {
    const int64_t yy = y + j - w.R;
    if (yy < 0 || yy >= H) continue;
    const float g = w.g[j];
    const int64_t o = yy * RW + i;
    s0 += g * P[o];
    s1 += g * P[n + o];
    s2 += g * P[2 * n + o];
  }
  vt[idx] = s0;
  vt[n + idx] = s1;
  vt[2 * n + idx] = s2;
}

// The image gradient; g_loss is read on the device (no host sync).
__global__ void loss_grad_kernel(const float* __restrict__ vt, const float* __restrict__ a,
                                 const float* __restrict__ b, int64_t H, int64_t RW, int64_t C, LossWindow w,
                                 double lam, const float* __restrict__ g_loss, float* __restrict__ out) {
  const int64_t n = H * RW, idx = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (idx >= n) return;
  const double g = (double)g_loss[0];
  const float ks = (float)(-lam * g / (double)n), kl = (float)((1.0 - lam) * g / (double)n);
  if (vt == nullptr) {
    out[idx] = kl * stdr::loss_sgn<float>(a[idx] - b[idx]);
    return;
  }
  float f[3];
  loss_hpass<3>(vt, n, RW, C, w, idx, f);
  out[idx] = stdr::loss_grad<float>(a[idx], b[idx], f[0], f[1], f[2], ks, kl);
}

// ---------------------------------------------------------------- the guard's check
// blockIdx.y: a tensor of the table; blockIdx.x: a stretch of its elements. A non-finite element
// (exponent bits all ones) lowers *first to the tensor's index (atomicMin: the result, the lowest
// index, does not depend on the order).
__global__ void guard_check_kernel(GuardTable t, int* __restrict__ first) {
  const int k = blockIdx.y;
  const int64_t n = t.numel[k];
  const uint32_t* p = reinterpret_cast<const uint32_t*>(t.ptr[k]);
  bool bad = false;
  for (int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x; i < n; i += (int64_t)gridDim.x * blockDim.x)
    bad |= (p[i] & 0x7f800000u) == 0x7f800000u;
  if (__syncthreads_or(bad) && threadIdx.x == 0) atomicMin(first, t.index[k]);
}

__global__ void guard_finish_kernel(const int* __restrict__ first, float* __restrict__ flag,
                                    int64_t* __restrict__ bad_step, int64_t* __restrict__ bad_index, int64_t step) {
  if (first[0] == INT_MAX) return;
  flag[0] = 1.0f;
  if (bad_step[0] < 0) {
    bad_step[0] = step;
    bad_index[0] = first[0];
  }
}

}  // namespace

void pack_rows(const float* means2d, const float* conics, const float* opac, const float* feats,
               const int32_t* radii, const int64_t* order, int64_t V, int F, float* packed,
               int32_t* vradii, cudaStream_t stream) {
  if (V == 0) return;
  pack_kernel<<<(unsigned)((V + 255) / 256), 256, 0, stream>>>(means2d, conics, opac, feats,
                                                               radii, order, V, F, packed, vradii);
}

void count_tiles(const float* packed, const int32_t* vradii, int64_t V, int D, int width,
                 int height, int tile, int32_t* counts, cudaStream_t stream) {
  if (V == 0) return;
  tiles_kernel<<<(unsigned)((V + 255) / 256), 256, 0, stream>>>(
      packed, vradii, V, D, width, height, tile, counts, nullptr, nullptr, nullptr, 0);
}

void emit_pairs(const float* packed, const int32_t* vradii, int64_t V, int D, int width,
                int height, int tile, const int32_t* counts, const int64_t* offsets, int64_t* keys,
                int64_t capacity, cudaStream_t stream) {
  if (V == 0) return;
  tiles_kernel<<<(unsigned)((V + 255) / 256), 256, 0, stream>>>(
      packed, vradii, V, D, width, height, tile, nullptr, counts, offsets, keys, capacity);
}

void forward(const float* packed, int F, const int32_t* pair_ids, const int64_t* tile_offsets,
             int width, int height, int tile, float* out_acc, float* out_T, int32_t* out_last,
             cudaStream_t stream) {
#define STDR_CALL(n) launch_forward<n>(packed, pair_ids, tile_offsets, width, height, tile, \
                                       out_acc, out_T, out_last, stream)
  STDR_DISPATCH_F(F, STDR_CALL)
#undef STDR_CALL
}

void backward(const float* packed, int F, const int32_t* pair_ids, const int64_t* tile_offsets,
              int width, int height, int tile, const float* g_acc, const float* g_T,
              const float* T_img, const int32_t* last_img, float* grad_packed,
              cudaStream_t stream) {
#define STDR_CALL(n) launch_backward<n>(packed, pair_ids, tile_offsets, width, height, tile, \
                                        g_acc, g_T, T_img, last_img, grad_packed, stream)
  STDR_DISPATCH_F(F, STDR_CALL)
#undef STDR_CALL
}

void score(const float* packed, const int32_t* pair_ids, const int64_t* tile_offsets, int width, int height,
           int tile, float* score_out, cudaStream_t stream) {
  const int ntiles = ((width + tile - 1) / tile) * ((height + tile - 1) / tile);
  const int block = tile * tile;
  const size_t shm = (size_t)block * ((stdr::PACK_BASE + 1) * sizeof(float) + sizeof(int32_t));
  score_kernel<<<ntiles, block, shm, stream>>>(packed, pair_ids, tile_offsets, width, height, tile, score_out);
}

// ---------------------------------------------------------------- projection and SH

__global__ void project_forward_kernel(stdr::ProjCam<float> cam, int64_t N, const float* __restrict__ means,
                                       const float* __restrict__ quats, const float* __restrict__ scales,
                                       const float* __restrict__ opac, const float* __restrict__ sh,
                                       float* means2d, float* depths, float* conics, float* opac_out,
                                       int32_t* radii, float* colors) {
  const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  stdr::project_forward_one<float>(cam, means + 3 * i, quats + 4 * i, scales + 3 * i, opac[i],
                                   sh + (int64_t)cam.K * 3 * i, means2d + 2 * i, depths + i, conics + 3 * i,
                                   opac_out + i, radii + i, colors + 3 * i);
}

__global__ void project_backward_kernel(stdr::ProjCam<float> cam, int64_t N, const float* __restrict__ means,
                                        const float* __restrict__ quats, const float* __restrict__ scales,
                                        const float* __restrict__ opac, const float* __restrict__ sh,
                                        const float* __restrict__ g_m2d, const float* __restrict__ g_depth,
                                        const float* __restrict__ g_conic, const float* __restrict__ g_opac,
                                        const float* __restrict__ g_color, float* g_means, float* g_quats,
                                        float* g_scales, float* g_opac_in, float* g_sh) {
  const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  const int64_t k3 = (int64_t)cam.K * 3 * i;
  stdr::project_backward_one<float>(cam, means + 3 * i, quats + 4 * i, scales + 3 * i, opac[i], sh + k3,
                                    g_m2d + 2 * i, g_depth[i], g_conic + 3 * i, g_opac[i], g_color + 3 * i,
                                    g_means + 3 * i, g_quats + 4 * i, g_scales + 3 * i, g_opac_in + i, g_sh + k3);
}

__global__ void hexplane_forward_kernel(HexPlanes pl, int64_t N, const float* __restrict__ coords,
                                        float* __restrict__ feats, float* __restrict__ others) {
  const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;  // (n, m, c), c fastest
  const int64_t MC = (int64_t)pl.M * pl.C;
  if (i >= N * MC) return;
  const int64_t n = i / MC;
  const int m = (int)((i % MC) / pl.C), c = (int)(i % pl.C);
  const float* cn = coords + 4 * n;
  float s[stdr::HEX_PLANES];
  for (int p = 0; p < stdr::HEX_PLANES; ++p) {
    const int q = m * stdr::HEX_PLANES + p;
    int64_t off[4];
    float w[4];
    stdr::hex_corners<float>(cn[stdr::hex_u(p)], cn[stdr::hex_v(p)], pl.H[q], pl.W[q], off, w);
    s[p] = stdr::hex_sample<float>(pl.ptr[q] + (int64_t)c * pl.H[q] * pl.W[q], off, w);
  }
  float pre = 1.0f, suf[stdr::HEX_PLANES + 1];
  suf[stdr::HEX_PLANES] = 1.0f;
  for (int p = stdr::HEX_PLANES - 1; p >= 0; --p) suf[p] = s[p] * suf[p + 1];
  float* orow = others + ((n * pl.M + m) * stdr::HEX_PLANES) * pl.C + c;
  for (int p = 0; p < stdr::HEX_PLANES; ++p) {
    orow[(int64_t)p * pl.C] = pre * suf[p + 1];
    pre = pre * s[p];
  }
  feats[i] = pre;
}

__global__ void hexplane_backward_kernel(HexPlanes pl, int64_t N, const float* __restrict__ coords,
                                         const float* __restrict__ others, const float* __restrict__ g_feats) {
  const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  const int64_t MC = (int64_t)pl.M * pl.C;
  if (i >= N * MC) return;
  const int64_t n = i / MC;
  const int m = (int)((i % MC) / pl.C), c = (int)(i % pl.C);
  const float g = g_feats[i];
  const float* cn = coords + 4 * n;
  const float* orow = others + ((n * pl.M + m) * stdr::HEX_PLANES) * pl.C + c;
  for (int p = 0; p < stdr::HEX_PLANES; ++p) {
    const int q = m * stdr::HEX_PLANES + p;
    int64_t off[4];
    float w[4];
    stdr::hex_corners<float>(cn[stdr::hex_u(p)], cn[stdr::hex_v(p)], pl.H[q], pl.W[q], off, w);
    const float gv = g * orow[(int64_t)p * pl.C];
    float* out = pl.grad[q] + (int64_t)c * pl.H[q] * pl.W[q];
    for (int k = 0; k < 4; ++k)
      if (w[k] != 0.0f) atomicAdd(out + off[k], gv * w[k]);
  }
}

void hexplane_forward(const HexPlanes& planes, int64_t N, const float* coords, float* feats, float* others,
                      cudaStream_t stream) {
  const int64_t total = N * planes.M * planes.C;
  if (total == 0) return;
  hexplane_forward_kernel<<<(unsigned)((total + 255) / 256), 256, 0, stream>>>(planes, N, coords, feats, others);
}

void hexplane_backward(const HexPlanes& planes, int64_t N, const float* coords, const float* others,
                       const float* g_feats, cudaStream_t stream) {
  const int64_t total = N * planes.M * planes.C;
  if (total == 0) return;
  hexplane_backward_kernel<<<(unsigned)((total + 255) / 256), 256, 0, stream>>>(planes, N, coords, others, g_feats);
}

void project_forward(const stdr::ProjCam<float>& cam, int64_t N, const float* means, const float* quats,
                     const float* scales, const float* opac, const float* sh, float* means2d, float* depths,
                     float* conics, float* opac_out, int32_t* radii, float* colors, cudaStream_t stream) {
  if (N == 0) return;
  project_forward_kernel<<<(unsigned)((N + 255) / 256), 256, 0, stream>>>(
      cam, N, means, quats, scales, opac, sh, means2d, depths, conics, opac_out, radii, colors);
}

void project_backward(const stdr::ProjCam<float>& cam, int64_t N, const float* means, const float* quats,
                      const float* scales, const float* opac, const float* sh, const float* g_m2d,
                      const float* g_depth, const float* g_conic, const float* g_opac, const float* g_color,
                      float* g_means, float* g_quats, float* g_scales, float* g_opac_in, float* g_sh,
                      cudaStream_t stream) {
  if (N == 0) return;
  project_backward_kernel<<<(unsigned)((N + 255) / 256), 256, 0, stream>>>(
      cam, N, means, quats, scales, opac, sh, g_m2d, g_depth, g_conic, g_opac, g_color, g_means, g_quats,
      g_scales, g_opac_in, g_sh);
}

LossWindow loss_window_f(int64_t window, double sigma) {
  LossWindow w;
  double g[stdr::LOSS_MAX_WINDOW];
  stdr::loss_window((int)window, sigma, g);
  for (int i = 0; i < (int)window; ++i) w.g[i] = (float)g[i];
  w.R = (int)(window / 2);
  return w;
}

int64_t loss_blocks(int64_t n) { return (n + LOSS_THREADS - 1) / LOSS_THREADS; }

void image_loss_forward(const float* a, const float* b, int64_t H, int64_t W, int64_t C, const LossWindow& w,
                        double lam, float* vt, float* P, double* block_sums, float* loss, float* stats,
                        cudaStream_t stream) {
  const int64_t RW = W * C, n = H * RW, blocks = loss_blocks(n);
  loss_vpass5_kernel<<<(unsigned)blocks, LOSS_THREADS, 0, stream>>>(a, b, H, RW, w, vt);
  loss_ssim_kernel<<<(unsigned)blocks, LOSS_THREADS, 0, stream>>>(vt, a, b, H, RW, C, w, P, block_sums);
  loss_finish_kernel<<<1, LOSS_THREADS, 0, stream>>>(block_sums, blocks, n, lam, loss, stats);
}

void image_loss_backward(const float* a, const float* b, const float* P, int64_t H, int64_t W, int64_t C,
                         const LossWindow& w, double lam, const float* g_loss, float* vt, float* out,
                         cudaStream_t stream) {
  const int64_t RW = W * C, n = H * RW, blocks = loss_blocks(n);
  if (P) loss_vpass3_kernel<<<(unsigned)blocks, LOSS_THREADS, 0, stream>>>(P, H, RW, w, vt);
  loss_grad_kernel<<<(unsigned)blocks, LOSS_THREADS, 0, stream>>>(P ? vt : nullptr, a, b, H, RW, C, w, lam, g_loss,
                                                                 out);
}

void guard_check(const GuardTable& table, int count, int64_t max_numel, int* first, cudaStream_t stream) {
  if (count == 0) return;
  const int64_t want = (max_numel + 4 * LOSS_THREADS - 1) / (4 * LOSS_THREADS);  // ~4 elements a thread
  const unsigned gx = (unsigned)(want < 1 ? 1 : (want > 1024 ? 1024 : want));
  guard_check_kernel<<<dim3(gx, (unsigned)count), LOSS_THREADS, 0, stream>>>(table, first);
}

void guard_finish(const int* first, float* flag, int64_t* bad_step, int64_t* bad_index, int64_t step,
                  cudaStream_t stream) {
  guard_finish_kernel<<<1, 1, 0, stream>>>(first, flag, bad_step, bad_index, step);
}

}  // namespace stdr_cuda
