// The rasterizer family of the CPU extension (ops_cpu.cpp binds it): tile-based forward and
// hand-written backward, the contribution score, the CUDA binning's two passes for the tests, and
// the projection with SH shading. Parallel over tiles with ATen's
// thread pool (built with -fopenmp, it shares torch's OpenMP runtime, so no second pool
// competes for the cores), vectorized across the pixels of a tile: float32 by explicit 16-lane
// vectors with the per-pixel state in registers (raster_simd.h), float64 (and compilers
// without vector extensions) by `#pragma omp simd` over raster_math.h's per-pixel functions.
//
// forward() sorts the visible Gaussians by depth, packs one row per Gaussian,
// [mx, my, a, b, c, o, f_0..f_{F-1}] (see raster_math.h), bins Gaussian-tile pairs and
// composites; backward() walks the same lists back to front and scatters the gradients to
// the inputs' rows.
#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cstring>
#include <type_traits>
#include <vector>

#include "../project_math.h"
#include "../raster_math.h"
#include "raster_simd.h"

#if defined(__GNUC__)
#define STDR_PREFETCH(p, rw) __builtin_prefetch(p, rw)
#else
#define STDR_PREFETCH(p, rw) ((void)0)
#endif

namespace {

using stdr::PACK_BASE;

struct Grid {
  int width, height, tile, ntx, nty, n_tiles, pt;
  Grid(int64_t w, int64_t h, int64_t t)
      : width((int)w), height((int)h), tile((int)t), ntx((int)((w + t - 1) / t)),
        nty((int)((h + t - 1) / t)), n_tiles(ntx * nty), pt((int)(t * t)) {}
};

// The slots of the two loops that sum over tiles (the backward's gradients, the score): a fixed
// number, whatever the thread count, so that every per-slot partial sum, and their sum in slot
// order, is bitwise the same on 1 core or 64 (the threads share the slots; beyond 16 threads these
// two loops leave the extra ones idle). The forward and the binning write each output once, so
// they split their work by the thread count.
constexpr int REDUCE_SLOTS = 16;

// Work split shared by every parallel loop: slot s of `slots` handles tiles s, s + slots, ...
// Interleaving balances dense and empty image regions; a fixed assignment keeps the backward's
// per-slot gradient sums (and so the result) deterministic, with REDUCE_SLOTS, on any thread count.
template <typename Fn> void for_each_slot(int slots, Fn fn) {
  at::parallel_for(0, slots, 1, [&](int64_t b, int64_t e) {
    for (int64_t s = b; s < e; ++s) fn((int)s);
  });
}

// Gaussian-tile pairs, sorted by tile then depth, by a two-pass counting sort: each slot finds
// the exact ellipse/tile overlaps of a contiguous depth range of Gaussians (kept in its own list,
// in depth order) and counts them per tile; then it writes its pair ids at its own offset inside
// each tile's list, so lists come out in depth order.
template <typename T>
void bin_pairs(const T* packed, const int32_t* radii, int64_t V, int64_t D, const Grid& gr,
               int slots, at::Tensor& pair_ids, at::Tensor& tile_offsets) {
  std::vector<int64_t> hist((size_t)slots * gr.n_tiles, 0);
  std::vector<std::vector<std::pair<int32_t, int32_t>>> found(slots);  // (Gaussian, tile)
  for_each_slot(slots, [&](int s) {
    int64_t* h = hist.data() + (size_t)s * gr.n_tiles;
    auto& mine = found[s];
    const int64_t v0 = V * s / slots, v1 = V * (s + 1) / slots;
    for (int64_t v = v0; v < v1; ++v) {
      const T* g = packed + v * D;
      int tx0, tx1, ty0, ty1;
      T cut;
      bool exact;
      if (!stdr::tile_range(g, radii[v], gr.width, gr.height, gr.tile, tx0, tx1, ty0, ty1, cut,
                            exact))
        continue;
      for (int ty = ty0; ty < ty1; ++ty)
        for (int tx = tx0; tx < tx1; ++tx)
          if (stdr::tile_overlaps(g, cut, exact, tx, ty, gr.tile, gr.width, gr.height)) {
            const int t = ty * gr.ntx + tx;
            ++h[t];
            mine.emplace_back((int32_t)v, t);
          }
    }
  });
  tile_offsets = at::empty({gr.n_tiles + 1}, at::kLong);
  int64_t* off = tile_offsets.data_ptr<int64_t>();
  int64_t run = 0;
  for (int t = 0; t < gr.n_tiles; ++t) {
    off[t] = run;
    for (int s = 0; s < slots; ++s) {
      int64_t c = hist[(size_t)s * gr.n_tiles + t];
      hist[(size_t)s * gr.n_tiles + t] = run;  // becomes the slot's write cursor
      run += c;
    }
  }
  off[gr.n_tiles] = run;
  pair_ids = at::empty({run}, at::kInt);
  int32_t* ids = pair_ids.data_ptr<int32_t>();
  for_each_slot(slots, [&](int s) {
    int64_t* cur = hist.data() + (size_t)s * gr.n_tiles;
    for (const auto& vt : found[s]) ids[cur[vt.second]++] = vt.first;
  });
}

// The pixels of one tile at a time, padded to S >= tile^2 entries (the SIMD path pads to whole
// 16-lane chunks) with outside pixels. The offsets inside a tile are computed once per thread
// (no integer division per pixel and tile).
template <typename T>
struct TileLayout {
  const Grid& gr;
  int S;                        // padded pixels per tile
  std::vector<int32_t> lx, ly;  // [S]: pixel p's column and row inside its tile
  std::vector<T> px, py;        // [S]: pixel centres of the current tile
  std::vector<int32_t> inside;  // [S]: 1 for pixels in the image
  int64_t base = 0;             // image index of the current tile's top-left pixel
  TileLayout(const Grid& g, int padded) : gr(g), S(padded), lx(S), ly(S), px(S), py(S), inside(S) {
    for (int p = 0; p < S; ++p) {
      lx[p] = p % g.tile;
      ly[p] = p / g.tile;
    }
  }
  void set(int t) {
    const int x0 = (t % gr.ntx) * gr.tile, y0 = (t / gr.ntx) * gr.tile;
    base = (int64_t)y0 * gr.width + x0;
    for (int p = 0; p < S; ++p) {
      const int x = x0 + lx[p], y = y0 + ly[p];
      px[p] = T(x) + T(0.5);
      py[p] = T(y) + T(0.5);
      inside[p] = (p < gr.pt && x < gr.width && y < gr.height) ? 1 : 0;
    }
  }
  int64_t pix(int p) const { return base + (int64_t)ly[p] * gr.width + lx[p]; }  // inside pixels
};

// A tile's forward results (pixel p's feature f at acc[f * stride + p]) into the images.
template <typename T, int F>
void store_tile(const TileLayout<T>& tl, const T* Tb, const int32_t* last, const T* acc, int stride,
                T* out_acc, T* out_T, int32_t* out_last) {
  for (int p = 0; p < tl.gr.pt; ++p) {
    if (!tl.inside[p]) continue;
    const int64_t pix = tl.pix(p);
    out_T[pix] = Tb[p];
    out_last[pix] = last[p];
    for (int f = 0; f < F; ++f) out_acc[pix * F + f] = acc[(size_t)f * stride + p];
  }
}

// A tile's backward state from the images, for its S padded pixels (outside ones: T = 1, no
// gradient, nothing composited): final T (also the walking T), dL/dT, last index, dL/d acc_f
// and the features behind (0). Returns the largest last index.
template <typename T, int F>
int load_tile(const TileLayout<T>& tl, const T* g_acc, const T* g_T, const T* Tfin_img,
              const int32_t* last_img, T* Tf, T* Tp, T* GT, int32_t* last, T* G, T* behind) {
  const int S = tl.S;
  int max_last = 0;
  for (int p = 0; p < S; ++p) {
    const bool in = tl.inside[p];
    const int64_t pix = in ? tl.pix(p) : 0;
    Tf[p] = in ? Tfin_img[pix] : T(1);
    Tp[p] = Tf[p];
    GT[p] = in ? g_T[pix] : T(0);
    last[p] = in ? last_img[pix] : 0;
    max_last = std::max(max_last, (int)last[p]);
    for (int f = 0; f < F; ++f) {
      G[(size_t)f * S + p] = in ? g_acc[pix * F + f] : T(0);
      behind[(size_t)f * S + p] = T(0);
    }
  }
  return max_last;
}

// A tile's per-pixel compositing state at the start (T = 1, nothing composited; pixels outside
// the image done from the start). Returns the number of pixels still compositing.
template <typename T>
int start_tile(const TileLayout<T>& tl, T* Tb, int32_t* done, int32_t* last) {
  int live = 0;
  for (int p = 0; p < tl.gr.pt; ++p) {
    Tb[p] = T(1);
    done[p] = tl.inside[p] ? 0 : 1;
    last[p] = 0;
    live += tl.inside[p];
  }
  return live;
}

template <typename T, int F>
void forward_tiles(const T* packed, int64_t D, const int32_t* ids, const int64_t* off,
                   const Grid& gr, int slots, T* out_acc, T* out_T, int32_t* out_last) {
  for_each_slot(slots, [&](int s) {
    const int Pt = gr.pt;
    TileLayout<T> tl(gr, Pt);
    std::vector<T> Tb(Pt), acc((size_t)F * Pt);
    std::vector<int32_t> done(Pt), last(Pt);
    for (int t = s; t < gr.n_tiles; t += slots) {
      tl.set(t);
      int live = start_tile(tl, Tb.data(), done.data(), last.data());
      std::fill(acc.begin(), acc.end(), T(0));
      T* A = acc.data();
      T* Tp = Tb.data();
      int32_t *dn = done.data(), *ls = last.data();
      const T *X = tl.px.data(), *Y = tl.py.data();
      for (int64_t k = off[t]; k < off[t + 1] && live > 0; ++k) {
        const T* g = packed + (int64_t)ids[k] * D;
        const int idx = (int)(k - off[t]);
        int stops = 0;
#pragma omp simd reduction(+ : stops)
        for (int p = 0; p < Pt; ++p)
          stops += stdr::forward_pixel<T, F>(g, X[p], Y[p], idx, Tp[p], dn[p], ls[p], A + p, Pt);
        live -= stops;
      }
      store_tile<T, F>(tl, Tb.data(), last.data(), acc.data(), Pt, out_acc, out_T, out_last);
    }
  });
}

template <typename T, int F>
void backward_tiles(const T* packed, int64_t D, const int32_t* ids, const int64_t* off,
                    const Grid& gr, int slots, const T* g_acc, const T* g_T, const T* Tfin_img,
                    const int32_t* last_img, T* grads /* [slots, V, D] */, int64_t V) {
  for_each_slot(slots, [&](int s) {
    const int Pt = gr.pt;
    TileLayout<T> tl(gr, Pt);
    std::vector<T> Tp(Pt), Tf(Pt), GT(Pt), G((size_t)F * Pt), behind((size_t)F * Pt),
        contrib((size_t)D * Pt);
    std::vector<int32_t> last(Pt);
    T* mine = grads + (int64_t)s * V * D;
    std::fill(mine, mine + V * D, T(0));
    for (int t = s; t < gr.n_tiles; t += slots) {
      if (off[t] == off[t + 1]) continue;
      tl.set(t);
      const int max_last = load_tile<T, F>(tl, g_acc, g_T, Tfin_img, last_img, Tf.data(), Tp.data(),
                                           GT.data(), last.data(), G.data(), behind.data());
      T *TP = Tp.data(), *B = behind.data(), *C = contrib.data();
      const T *X = tl.px.data(), *Y = tl.py.data(), *Gp = G.data(), *GTp = GT.data(), *TF = Tf.data();
      const int32_t* LS = last.data();
      for (int idx = max_last - 1; idx >= 0; --idx) {
        const int64_t v = ids[off[t] + idx];
        const T* g = packed + v * D;
#pragma omp simd
        for (int p = 0; p < Pt; ++p)
          stdr::backward_pixel<T, F>(g, X[p], Y[p], idx < LS[p], TP[p], B + p, Gp + p, GTp[p],
                                     TF[p], Pt, C + p);
        T* out = mine + v * D;
        for (int j = 0; j < PACK_BASE + F; ++j) {
          const T* cj = C + (size_t)j * Pt;
          T sum = T(0);
#pragma omp simd reduction(+ : sum)
          for (int p = 0; p < Pt; ++p) sum += cj[p];
          out[j] += sum;
        }
      }
    }
  });
}

#ifdef STDR_SIMD
// A tile layout padded to whole 16-lane chunks, with the view raster_simd.h reads.
struct SimdTiles : TileLayout<float> {
  int nch;  // chunks per tile
  stdr::simd::TilePixels tp;
  explicit SimdTiles(const Grid& g)
      : TileLayout<float>(g, (g.pt + stdr::simd::L - 1) / stdr::simd::L * stdr::simd::L),
        nch(S / stdr::simd::L), tp{nch, px.data(), py.data(), inside.data()} {}
};

// Prefetch the image rows of tile t that the backward's set-up reads next: each tile row is a
// separate cache line per image, a stride the hardware prefetcher does not follow. (The same
// for the forward's output rows measured no faster.)
inline void prefetch_tile_rows(const Grid& gr, int t, const float* g_acc, int F, const float* g_T,
                               const float* Tfin, const int32_t* last) {
  if (t >= gr.n_tiles) return;
  const int x0 = (t % gr.ntx) * gr.tile, y0 = (t / gr.ntx) * gr.tile;
  for (int y = y0; y < std::min(y0 + gr.tile, gr.height); ++y) {
    const int64_t i = (int64_t)y * gr.width + x0;
    STDR_PREFETCH(g_acc + i * F, 0);
    STDR_PREFETCH(g_acc + i * F + (int64_t)F * gr.tile - 1, 0);
    STDR_PREFETCH(g_T + i, 0);
    STDR_PREFETCH(Tfin + i, 0);
    STDR_PREFETCH(last + i, 0);
  }
}

template <int F>
void forward_tiles_simd(const float* packed, int64_t D, const int32_t* ids, const int64_t* off,
                        const Grid& gr, int slots, float* out_acc, float* out_T, int32_t* out_last) {
  for_each_slot(slots, [&](int s) {
    SimdTiles tl(gr);
    const int S = tl.S;
    std::vector<float> Tb(S), acc((size_t)F * S);
    std::vector<int32_t> last(S);
    for (int t = s; t < gr.n_tiles; t += slots) {
      tl.set(t);
      stdr::simd::forward_tile<F>(packed, D, ids, off[t], off[t + 1], tl.tp, Tb.data(), last.data(),
                                  acc.data(), S);
      store_tile<float, F>(tl, Tb.data(), last.data(), acc.data(), S, out_acc, out_T, out_last);
    }
  });
}

template <int F>
void backward_tiles_simd(const float* packed, int64_t D, const int32_t* ids, const int64_t* off,
                         const Grid& gr, int slots, const float* g_acc, const float* g_T,
                         const float* Tfin_img, const int32_t* last_img, float* grads, int64_t V) {
  for_each_slot(slots, [&](int s) {
    SimdTiles tl(gr);
    const int nch = tl.nch, S = tl.S;
    std::vector<float> Tp(S), Tf(S), GT(S), G((size_t)F * S), behind((size_t)F * S);
    std::vector<int32_t> last(S), chunk_last(nch);
    stdr::simd::TileGrad st{Tp.data(), Tf.data(), GT.data(), last.data(), chunk_last.data(),
                            G.data(), behind.data(), S};
    float* mine = grads + (int64_t)s * V * D;
    std::fill(mine, mine + V * D, 0.0f);
    for (int t = s; t < gr.n_tiles; t += slots) {
      if (off[t] == off[t + 1]) continue;
      tl.set(t);
      prefetch_tile_rows(gr, t + slots, g_acc, F, g_T, Tfin_img, last_img);
      const int max_last = load_tile<float, F>(tl, g_acc, g_T, Tfin_img, last_img, Tf.data(), Tp.data(),
                                               GT.data(), last.data(), G.data(), behind.data());
      for (int ch = 0; ch < nch; ++ch)
        chunk_last[ch] = *std::max_element(last.begin() + ch * stdr::simd::L,
                                           last.begin() + (ch + 1) * stdr::simd::L);
      stdr::simd::backward_tile<F>(packed, D, ids, off[t], max_last, tl.tp, st, mine);
    }
  });
}
#endif

// Visible Gaussians (radius > 0) front to back, ties in index order: an LSD radix sort on the
// depth's bits (visible depths are > near > 0, where IEEE order equals unsigned-integer order),
// stable like torch.argsort(stable=True).
template <typename T>
std::vector<int64_t> depth_order(const T* depths, const int32_t* radii, int64_t N) {
  using K = typename std::conditional<sizeof(T) == 4, uint32_t, uint64_t>::type;
  std::vector<int64_t> idx, tmp;
  std::vector<K> key, ktmp;
  for (int64_t i = 0; i < N; ++i)
    if (radii[i] > 0) {
      idx.push_back(i);
      K k;
      std::memcpy(&k, depths + i, sizeof(K));
      key.push_back(k);
    }
  const size_t V = idx.size();
  tmp.resize(V);
  ktmp.resize(V);
  for (unsigned shift = 0; shift < 8 * sizeof(K); shift += 8) {
    size_t count[257] = {0};
    for (size_t i = 0; i < V; ++i) ++count[((key[i] >> shift) & 255) + 1];
    if (count[((key.empty() ? 0 : (key[0] >> shift) & 255)) + 1] == V) continue;  // one bucket
    for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
    for (size_t i = 0; i < V; ++i) {
      const size_t dst = count[(key[i] >> shift) & 255]++;
      tmp[dst] = idx[i];
      ktmp[dst] = key[i];
    }
    idx.swap(tmp);
    key.swap(ktmp);
  }
  return idx;
}

void check_inputs(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                  const at::Tensor& feats, const at::Tensor& depths, const at::Tensor& radii,
                  int64_t width, int64_t height, int64_t tile) {
  const int64_t N = means2d.size(0);
  for (const at::Tensor* t : {&means2d, &conics, &opac, &feats, &depths, &radii})
    TORCH_CHECK(t->device().is_cpu(), "stdr CPU rasterizer: tensors must be on the CPU");
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "stdr rasterizer: means2d must be [N, 2]");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == N && conics.size(1) == 3,
              "stdr rasterizer: conics must be [N, 3]");
  TORCH_CHECK(opac.dim() == 1 && opac.size(0) == N, "stdr rasterizer: opacities must be [N]");
  TORCH_CHECK(depths.dim() == 1 && depths.size(0) == N, "stdr rasterizer: depths must be [N]");
  TORCH_CHECK(feats.dim() == 2 && feats.size(0) == N && feats.size(1) >= 1,
              "stdr rasterizer: features must be [N, F]");
  TORCH_CHECK(feats.size(1) <= stdr::MAX_CHANNELS,
              "stdr rasterizer: more feature channels than stdr::MAX_CHANNELS; use render.backend=reference");
  TORCH_CHECK(radii.dim() == 1 && radii.size(0) == N && radii.scalar_type() == at::kInt,
              "stdr rasterizer: radii must be int32 [N]");
  for (const at::Tensor* t : {&conics, &opac, &feats, &depths})
    TORCH_CHECK(t->scalar_type() == means2d.scalar_type(),
                "stdr rasterizer: all float inputs must share one dtype");
  TORCH_CHECK(width > 0 && height > 0, "stdr rasterizer: empty image");
  TORCH_CHECK(tile >= 1 && tile <= 32, "stdr CPU rasterizer: render.tile_size must be in [1, 32]");
}

template <typename Fn> void dispatch_channels(int64_t F, Fn fn) {
  switch (F) {
#define STDR_CASE(n) \
  case n: fn(std::integral_constant<int, n>{}); break;
    STDR_CASE(1) STDR_CASE(2) STDR_CASE(3) STDR_CASE(4)
    STDR_CASE(5) STDR_CASE(6) STDR_CASE(7) STDR_CASE(8)
#undef STDR_CASE
    default: TORCH_CHECK(false, "stdr rasterizer: unsupported channel count");
  }
}

// The visible Gaussians (radius > 0) sorted front to back, packed one row each (packed [V, 6+F],
// order [V] int64: packed row v is Gaussian order[v]) and their Gaussian-tile pairs (pair_ids [P]
// int32 by tile then depth, tile_offsets [n_tiles + 1]): what forward() and score() composite.
template <typename scalar_t>
void pack_rows(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
               const at::Tensor& feats, const at::Tensor& radii, const std::vector<int64_t>& ord,
               at::Tensor& packed, at::Tensor& order, at::Tensor& vradii) {
  const int64_t V = (int64_t)ord.size(), F = feats.size(1), D = PACK_BASE + F;
  order = at::empty({V}, at::kLong);
  std::copy(ord.begin(), ord.end(), order.data_ptr<int64_t>());
  packed = at::empty({V, D}, means2d.options());
  vradii = at::empty({V}, at::kInt);
  const scalar_t *m = means2d.data_ptr<scalar_t>(), *c = conics.data_ptr<scalar_t>(),
                 *o = opac.data_ptr<scalar_t>(), *f = feats.data_ptr<scalar_t>();
  const int32_t* r = radii.data_ptr<int32_t>();
  scalar_t* P = packed.data_ptr<scalar_t>();
  int32_t* vr = vradii.data_ptr<int32_t>();
  at::parallel_for(0, V, 4096, [&](int64_t b, int64_t e) {
    for (int64_t v = b; v < e; ++v) {
      const int64_t g = ord[v];
      scalar_t* row = P + v * D;
      row[0] = m[2 * g]; row[1] = m[2 * g + 1];
      row[2] = c[3 * g]; row[3] = c[3 * g + 1]; row[4] = c[3 * g + 2];
      row[5] = o[g];
      for (int64_t j = 0; j < F; ++j) row[PACK_BASE + j] = f[g * F + j];
      vr[v] = r[g];
    }
  });
}

template <typename scalar_t>
void pack_and_bin(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                  const at::Tensor& feats, const at::Tensor& depths, const at::Tensor& radii,
                  const Grid& gr, int slots, at::Tensor& packed, at::Tensor& order,
                  at::Tensor& pair_ids, at::Tensor& tile_offsets) {
  at::Tensor vradii;
  pack_rows<scalar_t>(means2d, conics, opac, feats, radii,
                      depth_order(depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), means2d.size(0)),
                      packed, order, vradii);
  bin_pairs<scalar_t>(packed.data_ptr<scalar_t>(), vradii.data_ptr<int32_t>(), packed.size(0), packed.size(1), gr,
                      slots, pair_ids, tile_offsets);
}

// Front-to-back compositing of the binned rows into acc [H, W, F], T [H, W], last [H, W] (every
// pixel written): the SIMD path for float32 where built, the scalar loops otherwise.
template <typename scalar_t>
void composite(const scalar_t* P, int64_t D, int64_t F, const at::Tensor& pair_ids, const at::Tensor& tile_offsets,
               const Grid& gr, int slots, at::Tensor& acc, at::Tensor& T_img, at::Tensor& last) {
  dispatch_channels(F, [&](auto fc) {
    constexpr int FC = decltype(fc)::value;
#ifdef STDR_SIMD
    if constexpr (std::is_same<scalar_t, float>::value) {
      forward_tiles_simd<FC>(P, D, pair_ids.data_ptr<int32_t>(), tile_offsets.data_ptr<int64_t>(),
                             gr, slots, acc.data_ptr<float>(), T_img.data_ptr<float>(),
                             last.data_ptr<int32_t>());
      return;
    }
#endif
    forward_tiles<scalar_t, FC>(
        P, D, pair_ids.data_ptr<int32_t>(), tile_offsets.data_ptr<int64_t>(), gr, slots,
        acc.data_ptr<scalar_t>(), T_img.data_ptr<scalar_t>(), last.data_ptr<int32_t>());
  });
}

// Returns (acc [H, W, F], T [H, W], last [H, W] int32, pair_ids [P] int32, tile_offsets [n+1],
// packed [V, 6+F], order [V] int64): the last four are what the backward needs.
std::vector<at::Tensor> forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac,
                                at::Tensor feats, at::Tensor depths, at::Tensor radii,
                                int64_t width, int64_t height, int64_t tile) {
  check_inputs(means2d, conics, opac, feats, depths, radii, width, height, tile);
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  feats = feats.contiguous(); depths = depths.contiguous(); radii = radii.contiguous();
  const Grid gr(width, height, tile);
  const int64_t F = feats.size(1), D = PACK_BASE + F;
  const int slots = std::max(1, at::get_num_threads());
  // every pixel is written by the tile loops (tiles with empty lists too): no fill needed
  auto acc = at::empty({height, width, F}, means2d.options());
  auto T_img = at::empty({height, width}, means2d.options());
  auto last = at::empty({height, width}, means2d.options().dtype(at::kInt));
  at::Tensor pair_ids, tile_offsets, packed, order;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "stdr_forward", [&] {
    pack_and_bin<scalar_t>(means2d, conics, opac, feats, depths, radii, gr, slots, packed, order, pair_ids,
                           tile_offsets);
    composite<scalar_t>(packed.data_ptr<scalar_t>(), D, F, pair_ids, tile_offsets, gr, slots, acc, T_img, last);
  });
  return {acc, T_img, last, pair_ids, tile_offsets, packed, order};
}

// The contribution score pass: the forward's compositing (same lists, same per-pixel arithmetic,
// raster_math.h's forward_pixel with one feature channel of ones, so the "accumulated feature" of
// a Gaussian at a pixel is its blending weight alpha * T) summed over the pixels of each Gaussian.
// Each slot sums into its own row of `sums` [slots, V]; the rows are added in slot order, so the
// result is the same on any thread count (REDUCE_SLOTS).
template <typename T>
void score_tiles(const T* packed, const int32_t* ids, const int64_t* off, const Grid& gr, int slots,
                 T* sums, int64_t V) {
  constexpr int64_t D = PACK_BASE + 1;
  for_each_slot(slots, [&](int s) {
    const int Pt = gr.pt;
    TileLayout<T> tl(gr, Pt);
    std::vector<T> Tb(Pt), w(Pt);
    std::vector<int32_t> done(Pt), last(Pt);
    T* mine = sums + (int64_t)s * V;
    std::fill(mine, mine + V, T(0));
    for (int t = s; t < gr.n_tiles; t += slots) {
      if (off[t] == off[t + 1]) continue;
      tl.set(t);
      int live = start_tile(tl, Tb.data(), done.data(), last.data());
      T *W = w.data(), *Tp = Tb.data();
      int32_t *dn = done.data(), *ls = last.data();
      const T *X = tl.px.data(), *Y = tl.py.data();
      for (int64_t k = off[t]; k < off[t + 1] && live > 0; ++k) {
        const int32_t v = ids[k];
        const T* g = packed + (int64_t)v * D;
        const int idx = (int)(k - off[t]);
        int stops = 0;
        T sum = T(0);
#pragma omp simd reduction(+ : stops)
        for (int p = 0; p < Pt; ++p) {
          W[p] = T(0);
          stops += stdr::forward_pixel<T, 1>(g, X[p], Y[p], idx, Tp[p], dn[p], ls[p], W + p, Pt);
        }
#pragma omp simd reduction(+ : sum)
        for (int p = 0; p < Pt; ++p) sum += W[p];
        mine[v] += sum;
        live -= stops;
      }
    }
  });
}

// score [N]: each Gaussian's blending weight alpha * T summed over the image's pixels (0 for the
// ones not rendered), what compositing gives it in this view: LightGaussian's global significance
// for one view, the contribution pruning ranks by (stdr/scene/prune.py).
at::Tensor score(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor depths, at::Tensor radii,
                 int64_t width, int64_t height, int64_t tile) {
  auto ones = at::ones({means2d.size(0), 1}, means2d.options());
  check_inputs(means2d, conics, opac, ones, depths, radii, width, height, tile);
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  depths = depths.contiguous(); radii = radii.contiguous();
  const Grid gr(width, height, tile);
  const int64_t N = means2d.size(0);
  const int slots = std::max(1, at::get_num_threads()), reduce_slots = REDUCE_SLOTS;
  auto out = at::zeros({N}, means2d.options());
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "stdr_score", [&] {
    at::Tensor pair_ids, tile_offsets, packed, order;
    pack_and_bin<scalar_t>(means2d, conics, opac, ones, depths, radii, gr, slots, packed, order, pair_ids,
                           tile_offsets);
    const int64_t V = packed.size(0);
    std::vector<scalar_t> sums((size_t)reduce_slots * V);
    score_tiles<scalar_t>(packed.data_ptr<scalar_t>(), pair_ids.data_ptr<int32_t>(),
                          tile_offsets.data_ptr<int64_t>(), gr, reduce_slots, sums.data(), V);
    // the slots' sums in slot order (deterministic), scattered to input order, as backward() does
    const int64_t* ord = order.data_ptr<int64_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    at::parallel_for(0, V, 4096, [&](int64_t b, int64_t e) {
      for (int64_t v = b; v < e; ++v) {
        scalar_t total = 0;
        for (int s = 0; s < reduce_slots; ++s) total += sums[(size_t)s * V + v];
        o[ord[v]] = total;
      }
    });
  });
  return out;
}

// The CUDA backend's two-pass binning (../cuda/raster_cuda.h's bin_pairs: count, scan, write, sort), run
// serially with the same shared function (raster_math.h's gaussian_tile_keys): the count pass reads
// `P`, the write pass `E` (rows of the same shape). capacity < 0: keys sized by the total;
// capacity >= 0 (the capture-safe form): that many keys, a row's keys past it dropped, the others
// filled with a key that sorts after every tile's. total: the pairs counted.
template <typename T>
void bin_pairs_two_pass(const T* P, const T* E, const int32_t* r, int64_t V, int64_t D, const Grid& gr,
                        int64_t capacity, at::Tensor& pair_ids, at::Tensor& tile_offsets, int64_t& total) {
  auto counts = at::zeros({V}, at::kInt);
  int32_t* c = counts.data_ptr<int32_t>();
  for (int64_t v = 0; v < V; ++v)
    c[v] = stdr::gaussian_tile_keys(P + v * D, r[v], gr.width, gr.height, gr.tile, v, (int64_t*)nullptr, 0);
  auto ends = at::cumsum(counts, 0, at::kLong);
  total = V > 0 ? ends[-1].item<int64_t>() : 0;
  const int64_t size = capacity >= 0 ? capacity : total;
  const int64_t* end = ends.data_ptr<int64_t>();
  auto keys = at::full({size}, ((int64_t)gr.n_tiles << 32) | 0x7fffffffLL, at::kLong);
  int64_t* k = keys.data_ptr<int64_t>();
  for (int64_t v = 0; v < V; ++v) {
    const int64_t first = end[v] - c[v], cap = std::min<int64_t>(c[v], size - first);
    if (cap > 0) stdr::gaussian_tile_keys(E + v * D, r[v], gr.width, gr.height, gr.tile, v, k + first, cap);
  }
  auto sorted = std::get<0>(at::sort(keys));
  pair_ids = at::bitwise_and(sorted, 0xffffffffLL).to(at::kInt);
  auto tiles = at::bitwise_right_shift(sorted, 32);
  tile_offsets = at::searchsorted(tiles, at::arange((int64_t)gr.n_tiles + 1, tiles.options()));
}

// bin_pairs_two_pass for the tests, as the CUDA binding's bin_pairs_split: returns (pair_ids [P]
// int32, tile_offsets [n_tiles + 1]). This CPU backend's own binning is single-pass (bin_pairs above).
std::vector<at::Tensor> bin_pairs_split(at::Tensor packed, at::Tensor emit, at::Tensor vradii, int64_t width,
                                        int64_t height, int64_t tile) {
  TORCH_CHECK(packed.device().is_cpu() && emit.device().is_cpu() && vradii.device().is_cpu(),
              "stdr CPU bin_pairs_split: every input must be a CPU tensor");
  TORCH_CHECK(packed.dim() == 2 && packed.sizes() == emit.sizes() && packed.scalar_type() == emit.scalar_type() &&
                  packed.size(1) > PACK_BASE && vradii.scalar_type() == at::kInt &&
                  vradii.numel() == packed.size(0),
              "stdr CPU bin_pairs_split: packed and emit [V, D] of one dtype, vradii int32 [V]");
  TORCH_CHECK(width > 0 && height > 0 && tile >= 1 && tile <= 32, "stdr CPU bin_pairs_split: bad image or tile size");
  packed = packed.contiguous(); emit = emit.contiguous(); vradii = vradii.contiguous();
  const Grid gr(width, height, tile);
  at::Tensor pair_ids, tile_offsets;
  int64_t total = 0;
  AT_DISPATCH_FLOATING_TYPES(packed.scalar_type(), "stdr_bin_pairs_split", [&] {
    bin_pairs_two_pass<scalar_t>(packed.data_ptr<scalar_t>(), emit.data_ptr<scalar_t>(), vradii.data_ptr<int32_t>(),
                                 packed.size(0), packed.size(1), gr, -1, pair_ids, tile_offsets, total);
  });
  return {pair_ids, tile_offsets};
}

// The CUDA backend's capture-safe forward (../cuda/raster_cuda.h's forward_bounded) on the CPU, for
// the tests: every row packed, the visible ones first in forward()'s order and the others after
// them by index (radius 0: no tile), binned by bin_pairs_two_pass into `capacity` keys, then
// composited as forward() does. Returns forward()'s seven tensors (packed [N, 6+F], order [N],
// pair_ids [capacity]) and total [] int64.
std::vector<at::Tensor> forward_bounded(at::Tensor means2d, at::Tensor conics, at::Tensor opac,
                                        at::Tensor feats, at::Tensor depths, at::Tensor radii,
                                        int64_t width, int64_t height, int64_t tile, int64_t capacity) {
  check_inputs(means2d, conics, opac, feats, depths, radii, width, height, tile);
  TORCH_CHECK(capacity >= 0, "stdr CPU rasterizer: the capture-safe forward needs a capacity >= 0");
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  feats = feats.contiguous(); depths = depths.contiguous(); radii = radii.contiguous();
  const Grid gr(width, height, tile);
  const int64_t N = means2d.size(0), F = feats.size(1), D = PACK_BASE + F;
  const int slots = std::max(1, at::get_num_threads());
  auto acc = at::empty({height, width, F}, means2d.options());
  auto T_img = at::empty({height, width}, means2d.options());
  auto last = at::empty({height, width}, means2d.options().dtype(at::kInt));
  at::Tensor packed, order, vradii, pair_ids, tile_offsets;
  int64_t total = 0;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "stdr_forward_bounded", [&] {
    const int32_t* r = radii.data_ptr<int32_t>();
    std::vector<int64_t> ord = depth_order(depths.data_ptr<scalar_t>(), r, N);
    for (int64_t i = 0; i < N; ++i)
      if (r[i] <= 0) ord.push_back(i);
    pack_rows<scalar_t>(means2d, conics, opac, feats, radii, ord, packed, order, vradii);
    const scalar_t* P = packed.data_ptr<scalar_t>();
    bin_pairs_two_pass<scalar_t>(P, P, vradii.data_ptr<int32_t>(), N, D, gr, capacity, pair_ids, tile_offsets, total);
    composite<scalar_t>(P, D, F, pair_ids, tile_offsets, gr, slots, acc, T_img, last);
  });
  return {acc, T_img, last, pair_ids, tile_offsets, packed, order, at::scalar_tensor(total, at::kLong)};
}

// Gradients for (means2d [N, 2], conics [N, 3], opacities [N], features [N, F]); rows of
// Gaussians that were not rendered are zero.
std::vector<at::Tensor> backward(at::Tensor packed, at::Tensor order, int64_t N,
                                 at::Tensor pair_ids, at::Tensor tile_offsets, at::Tensor T_img,
                                 at::Tensor last, at::Tensor g_acc, at::Tensor g_T,
                                 int64_t width, int64_t height, int64_t tile) {
  g_acc = g_acc.contiguous();
  g_T = g_T.contiguous();
  const Grid gr(width, height, tile);
  const int64_t V = packed.size(0), D = packed.size(1), F = D - PACK_BASE;
  TORCH_CHECK(g_acc.size(0) == height && g_acc.size(1) == width && g_acc.size(2) == F,
              "stdr rasterizer backward: gradient shape mismatch");
  const int slots = REDUCE_SLOTS;
  // [slots, V, D] partial sums; each slot zeroes its own part in its thread (backward_tiles*)
  auto grads = at::empty({slots, V, D}, packed.options());
  auto opt = packed.options();
  auto g_m = at::zeros({N, 2}, opt), g_c = at::zeros({N, 3}, opt), g_o = at::zeros({N}, opt),
       g_f = at::zeros({N, F}, opt);
  AT_DISPATCH_FLOATING_TYPES(packed.scalar_type(), "stdr_backward", [&] {
    dispatch_channels(F, [&](auto fc) {
      constexpr int FC = decltype(fc)::value;
#ifdef STDR_SIMD
      if constexpr (std::is_same<scalar_t, float>::value) {
        backward_tiles_simd<FC>(packed.data_ptr<float>(), D, pair_ids.data_ptr<int32_t>(),
                                tile_offsets.data_ptr<int64_t>(), gr, slots, g_acc.data_ptr<float>(),
                                g_T.data_ptr<float>(), T_img.data_ptr<float>(), last.data_ptr<int32_t>(),
                                grads.data_ptr<float>(), V);
        return;
      }
#endif
      backward_tiles<scalar_t, FC>(
          packed.data_ptr<scalar_t>(), D, pair_ids.data_ptr<int32_t>(),
          tile_offsets.data_ptr<int64_t>(), gr, slots, g_acc.data_ptr<scalar_t>(),
          g_T.data_ptr<scalar_t>(), T_img.data_ptr<scalar_t>(), last.data_ptr<int32_t>(),
          grads.data_ptr<scalar_t>(), V);
    });
    // sum the slots' partial gradients (fixed order: deterministic) and scatter to the inputs
    const scalar_t* G = grads.data_ptr<scalar_t>();
    const int64_t* ord = order.data_ptr<int64_t>();
    scalar_t *gm = g_m.data_ptr<scalar_t>(), *gc = g_c.data_ptr<scalar_t>(),
             *go = g_o.data_ptr<scalar_t>(), *gf = g_f.data_ptr<scalar_t>();
    at::parallel_for(0, V, 4096, [&](int64_t b, int64_t e) {
      scalar_t row[PACK_BASE + stdr::MAX_CHANNELS];
      for (int64_t v = b; v < e; ++v) {
        if (v + 8 < e) {  // the output rows are scattered (depth order -> input order)
          const int64_t gn = ord[v + 8];
          STDR_PREFETCH(gm + 2 * gn, 1);
          STDR_PREFETCH(gc + 3 * gn, 1);
          STDR_PREFETCH(go + gn, 1);
          STDR_PREFETCH(gf + gn * F, 1);
        }
        for (int64_t j = 0; j < D; ++j) {
          scalar_t sum = 0;
          for (int s = 0; s < slots; ++s) sum += G[((int64_t)s * V + v) * D + j];
          row[j] = sum;
        }
        const int64_t g = ord[v];
        gm[2 * g] = row[0]; gm[2 * g + 1] = row[1];
        gc[3 * g] = row[2]; gc[3 * g + 1] = row[3]; gc[3 * g + 2] = row[4];
        go[g] = row[5];
        for (int64_t j = 0; j < F; ++j) gf[g * F + j] = row[PACK_BASE + j];
      }
    });
  });
  return {g_m, g_c, g_o, g_f};
}


// ---------------------------------------------------------------- projection and SH (project_math.h)

void check_project_inputs(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                          const at::Tensor& opac, const at::Tensor& sh, const std::vector<double>& cam,
                          int64_t degree) {
  const int64_t N = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "stdr projection: means must be [N, 3]");
  TORCH_CHECK(quats.dim() == 2 && quats.size(0) == N && quats.size(1) == 4, "stdr projection: quats must be [N, 4]");
  TORCH_CHECK(scales.dim() == 2 && scales.size(0) == N && scales.size(1) == 3, "stdr projection: scales must be [N, 3]");
  TORCH_CHECK(opac.dim() == 1 && opac.size(0) == N, "stdr projection: opacities must be [N]");
  TORCH_CHECK(sh.dim() == 3 && sh.size(0) == N && sh.size(2) == 3, "stdr projection: sh must be [N, K, 3]");
  TORCH_CHECK(degree >= 0 && degree <= 3 && sh.size(1) >= (degree + 1) * (degree + 1) && sh.size(1) <= 16,
              "stdr projection: SH degree must be in [0, 3] with (degree + 1)^2 <= K <= 16");
  TORCH_CHECK((int)cam.size() == stdr::PROJ_CAM_VALUES, "stdr projection: the camera must be 26 values");
  for (const at::Tensor* t : {&means, &quats, &scales, &opac, &sh}) {
    TORCH_CHECK(t->device().is_cpu(), "stdr CPU projection: tensors must be on the CPU");
    TORCH_CHECK(t->scalar_type() == means.scalar_type(), "stdr projection: all inputs must share one dtype");
    TORCH_CHECK(t->is_contiguous(), "stdr projection: inputs must be contiguous");
  }
}

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opac,
                                        at::Tensor sh, std::vector<double> cam, int64_t width, int64_t height,
                                        bool antialiased, int64_t degree) {
  check_project_inputs(means, quats, scales, opac, sh, cam, degree);
  const int64_t N = means.size(0), K = sh.size(1);
  auto o = means.options();
  auto means2d = at::empty({N, 2}, o), depths = at::empty({N}, o), conics = at::empty({N, 3}, o);
  auto opac_out = at::empty({N}, o), colors = at::empty({N, 3}, o);
  auto radii = at::empty({N}, o.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "stdr_project_forward", [&] {
    const auto c = stdr::make_proj_cam<scalar_t>(cam.data(), (int)width, (int)height, antialiased, (int)degree, (int)K);
    const scalar_t *m = means.data_ptr<scalar_t>(), *q = quats.data_ptr<scalar_t>(),
                   *s = scales.data_ptr<scalar_t>(), *op = opac.data_ptr<scalar_t>(), *h = sh.data_ptr<scalar_t>();
    scalar_t *m2 = means2d.data_ptr<scalar_t>(), *dp = depths.data_ptr<scalar_t>(),
             *cn = conics.data_ptr<scalar_t>(), *oo = opac_out.data_ptr<scalar_t>(), *cl = colors.data_ptr<scalar_t>();
    int32_t* r = radii.data_ptr<int32_t>();
    at::parallel_for(0, N, 2048, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        stdr::project_forward_one<scalar_t>(c, m + 3 * i, q + 4 * i, s + 3 * i, op[i], h + K * 3 * i, m2 + 2 * i,
                                            dp + i, cn + 3 * i, oo + i, r + i, cl + 3 * i);
    });
  });
  return {means2d, depths, conics, opac_out, radii, colors};
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opac,
                                         at::Tensor sh, at::Tensor g_m2d, at::Tensor g_depth, at::Tensor g_conic,
                                         at::Tensor g_opac, at::Tensor g_color, std::vector<double> cam,
                                         int64_t width, int64_t height, bool antialiased, int64_t degree) {
  check_project_inputs(means, quats, scales, opac, sh, cam, degree);
  const int64_t N = means.size(0), K = sh.size(1);
  for (const at::Tensor* t : {&g_m2d, &g_depth, &g_conic, &g_opac, &g_color}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == means.scalar_type(),
                "stdr projection backward: gradients must be contiguous CPU tensors of the inputs' dtype");
    TORCH_CHECK(t->size(0) == N, "stdr projection backward: one gradient row per Gaussian");
  }
  auto gm = at::empty_like(means), gq = at::empty_like(quats), gs = at::empty_like(scales);
  auto go = at::empty_like(opac), gh = at::empty_like(sh);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "stdr_project_backward", [&] {
    const auto c = stdr::make_proj_cam<scalar_t>(cam.data(), (int)width, (int)height, antialiased, (int)degree, (int)K);
    const scalar_t *m = means.data_ptr<scalar_t>(), *q = quats.data_ptr<scalar_t>(),
                   *s = scales.data_ptr<scalar_t>(), *op = opac.data_ptr<scalar_t>(), *h = sh.data_ptr<scalar_t>();
    const scalar_t *a2 = g_m2d.data_ptr<scalar_t>(), *ad = g_depth.data_ptr<scalar_t>(),
                   *ac = g_conic.data_ptr<scalar_t>(), *ao = g_opac.data_ptr<scalar_t>(), *acl = g_color.data_ptr<scalar_t>();
    scalar_t *pm = gm.data_ptr<scalar_t>(), *pq = gq.data_ptr<scalar_t>(), *ps = gs.data_ptr<scalar_t>(),
             *po = go.data_ptr<scalar_t>(), *ph = gh.data_ptr<scalar_t>();
    at::parallel_for(0, N, 2048, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        stdr::project_backward_one<scalar_t>(c, m + 3 * i, q + 4 * i, s + 3 * i, op[i], h + K * 3 * i, a2 + 2 * i,
                                             ad[i], ac + 3 * i, ao[i], acl + 3 * i, pm + 3 * i, pq + 4 * i,
                                             ps + 3 * i, po + i, ph + K * 3 * i);
    });
  });
  return {gm, gq, gs, go, gh};
}

}  // namespace
