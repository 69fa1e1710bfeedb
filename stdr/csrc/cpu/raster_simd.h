// Explicit-SIMD float32 path of the CPU rasterizer (GCC/Clang vector extensions).
//
// The scalar per-pixel functions of raster_math.h (used by CUDA and by the CPU's float64 path)
// leave the per-pixel state in memory: each Gaussian of a tile list loads and stores every
// pixel's transmittance, flags and accumulators. Here the same math runs on 16-pixel vectors
// (`vf`, one AVX-512 register; two AVX2 or four SSE registers elsewhere) with the state held in
// registers:
//   * forward: one 16-pixel chunk of the tile at a time, walking the tile's whole list with the
//     chunk's T, last index and accumulators in registers; a chunk stops as soon as all its
//     pixels have stopped;
//   * backward: one Gaussian at a time (back to front), its chunks' contributions summed in
//     registers and reduced across lanes once per Gaussian and tile by a transposed tree
//     (`reduce_lanes`) instead of through a [values x pixels] buffer; chunks whose pixels all
//     ended in front of the Gaussian are skipped.
// Semantics are raster_math.h's, with two roundings moved: exp(-q/2) is reused for d alpha/d o
// (raster_math.h divides raw by o) and 1/(1 - alpha) is computed once. The parity tests pin the
// float32 path to the float64 reference (tests/test_compiled.py).
#pragma once

#include <cstdint>
#include <cstring>

#include "../raster_math.h"

#if defined(__GNUC__) && !defined(__CUDACC__) && !defined(STDR_NO_SIMD)
#define STDR_SIMD 1
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace stdr {
namespace simd {

constexpr int L = 16;  // lanes
typedef float vf __attribute__((vector_size(64)));
typedef int32_t vi __attribute__((vector_size(64)));

inline vf splat(float x) { return vf{} + x; }
inline vi splati(int32_t x) { return vi{} + x; }
inline vf vmin(vf a, vf b) { return a < b ? a : b; }
inline vf vmax(vf a, vf b) { return a > b ? a : b; }
inline vf loadf(const float* p) { vf v; std::memcpy(&v, p, sizeof v); return v; }
inline vi loadi(const int32_t* p) { vi v; std::memcpy(&v, p, sizeof v); return v; }
inline void storef(float* p, vf v) { std::memcpy(p, &v, sizeof v); }
inline void storei(int32_t* p, vi v) { std::memcpy(p, &v, sizeof v); }

// Lanes of a comparison result are 0 or -1: true when every lane is set.
inline bool all_set(vi m) {
#if defined(__AVX512F__)
  return _mm512_cmpeq_epi32_mask((__m512i)m, _mm512_setzero_si512()) == 0;
#else
  int32_t r = -1;
  for (int l = 0; l < L; ++l) r &= m[l];
  return r != 0;
#endif
}

// exp(x) for x <= 0: raster_math.h's exp_neg on 16 lanes (the same reduction and polynomial;
// the integer n comes from the 1.5 * 2^23 shifter instead of nearbyint).
inline vf exp_neg(vf x) {
  x = vmax(x, splat(-80.0f));
  const float inv_ln2 = 1.44269504088896341f, shifter = 12582912.0f;
  const vf n = (x * inv_ln2 + shifter) - shifter;
  const vf p = exp_reduced(x, n);
  const vi e = (__builtin_convertvector(n, vi) + 127) << 23;
  return p * (vf)e;
}

#if defined(__clang__)
#define STDR_SHUF2(a, b, ...) __builtin_shufflevector(a, b, __VA_ARGS__)
#else
#define STDR_SHUF2(a, b, ...) __builtin_shuffle(a, b, vi{__VA_ARGS__})
#endif

// One level of the transposed reduction: a holds k-lane groups of partial sums of some values,
// b likewise; the result holds k/2-lane groups of both, a's values first.
template <int K> inline vf fold(vf a, vf b);
template <> inline vf fold<16>(vf a, vf b) {
  return STDR_SHUF2(a, b, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23) +
         STDR_SHUF2(a, b, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31);
}
template <> inline vf fold<8>(vf a, vf b) {
  return STDR_SHUF2(a, b, 0, 1, 2, 3, 8, 9, 10, 11, 16, 17, 18, 19, 24, 25, 26, 27) +
         STDR_SHUF2(a, b, 4, 5, 6, 7, 12, 13, 14, 15, 20, 21, 22, 23, 28, 29, 30, 31);
}
template <> inline vf fold<4>(vf a, vf b) {
  return STDR_SHUF2(a, b, 0, 1, 4, 5, 8, 9, 12, 13, 16, 17, 20, 21, 24, 25, 28, 29) +
         STDR_SHUF2(a, b, 2, 3, 6, 7, 10, 11, 14, 15, 18, 19, 22, 23, 26, 27, 30, 31);
}
template <> inline vf fold<2>(vf a, vf b) {
  return STDR_SHUF2(a, b, 0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30) +
         STDR_SHUF2(a, b, 1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
}
#undef STDR_SHUF2

template <int K, int M> inline void fold_level(vf* s) {  // M vectors -> ceil(M/2), in place
  for (int i = 0; i < (M + 1) / 2; ++i) s[i] = fold<K>(s[2 * i], 2 * i + 1 < M ? s[2 * i + 1] : vf{});
}

// The lane sums of M <= 16 vectors: out[j] = sum over lanes of s[j]. s is overwritten.
template <int M> inline void reduce_lanes(vf* s, float* out) {
  static_assert(M >= 1 && M <= 16, "reduce_lanes: at most 16 values");
  constexpr int M1 = (M + 1) / 2, M2 = (M1 + 1) / 2, M3 = (M2 + 1) / 2;
  fold_level<16, M>(s);
  fold_level<8, M1>(s);
  fold_level<4, M2>(s);
  fold_level<2, M3>(s);
  float r[L];
  storef(r, s[0]);
  for (int j = 0; j < M; ++j) out[j] = r[j];
}

// Pixel centres and in-image flags of tile t, padded with outside lanes to whole chunks.
struct TilePixels {
  int nch;                  // 16-pixel chunks
  float *x, *y;             // [nch * L]
  int32_t* inside;          // [nch * L], 1 inside the image
};

// Forward over one tile's list [k0, k1): per 16-pixel chunk, T (init 1), last (init 0) and the
// accumulators (init 0) in registers; results into Tb[p], last[p], acc[f * stride + p].
// (Two chunks at once, for more independent work per iteration, measured no faster.)
template <int F>
inline void forward_tile(const float* packed, int64_t D, const int32_t* ids, int64_t k0, int64_t k1,
                         const TilePixels& tp, float* Tb, int32_t* last, float* acc, int stride) {
  for (int ch = 0; ch < tp.nch; ++ch) {
    const int p0 = ch * L;
    const vf X = loadf(tp.x + p0), Y = loadf(tp.y + p0);
    vf Tp = splat(1.0f), A[F];
    for (int f = 0; f < F; ++f) A[f] = vf{};
    vi done = loadi(tp.inside + p0) == 0, ls = vi{};
    for (int64_t k = k0; k < k1 && !all_set(done); ++k) {
      const float* g = packed + (int64_t)ids[k] * D;
      if (k + 1 < k1) __builtin_prefetch(packed + (int64_t)ids[k + 1] * D);  // rows are scattered
      const float mx = g[0], my = g[1], a = g[2], b = g[3], c = g[4], o = g[5];
      const vf dx = X - mx, dy = Y - my;
      const vf q = a * dx * dx + 2.0f * b * dx * dy + c * dy * dy;
      const vf raw = o * exp_neg(-0.5f * q);
      const vf alpha = (q <= Q_MAX) & (raw >= ALPHA_MIN) ? vmin(raw, splat(ALPHA_MAX)) : vf{};
      const vf test = Tp * (1.0f - alpha);
      const vi live = ~done & (alpha > 0.0f);
      const vi stop = live & (test < T_MIN);
      const vi take = live & ~stop;
      const vf w = take ? alpha * Tp : vf{};
      for (int f = 0; f < F; ++f) A[f] += w * g[PACK_BASE + f];
      Tp = Tp * (take ? 1.0f - alpha : splat(1.0f));
      ls = take ? splati((int32_t)(k - k0) + 1) : ls;
      done |= stop;
    }
    storef(Tb + p0, Tp);
    storei(last + p0, ls);
    for (int f = 0; f < F; ++f) storef(acc + (size_t)f * stride + p0, A[f]);
  }
}

// Backward state of one tile, padded like TilePixels: per pixel the transmittance (final, then
// walked back), the final T, dL/dT_final, the last index, dL/d acc_f and the features behind.
struct TileGrad {
  float *Tp, *Tf, *GT;      // [nch * L]
  int32_t* last;            // [nch * L]
  int32_t* chunk_last;      // [nch]: the largest last index of each chunk
  float *G, *behind;        // [F][nch * L]
  int stride;               // nch * L
};

// Backward over one tile's list, back to front from the tile's largest last index; adds each
// Gaussian's PACK_BASE + F gradient values to grads[v * D + j].
template <int F>
inline void backward_tile(const float* packed, int64_t D, const int32_t* ids, int64_t k0, int max_last,
                          const TilePixels& tp, TileGrad& st, float* grads) {
  constexpr int M = PACK_BASE + F;
  const int S = st.stride;
  for (int idx = max_last - 1; idx >= 0; --idx) {
    const int64_t v = ids[k0 + idx];
    const float* g = packed + v * D;
    if (idx > 0) {  // the next Gaussian's rows: packed (read) and gradient (read-modify-write)
      const int64_t vn = ids[k0 + idx - 1];
      __builtin_prefetch(packed + vn * D);
      __builtin_prefetch(grads + vn * D, 1);
    }
    const float mx = g[0], my = g[1], a = g[2], b = g[3], c = g[4], o = g[5];
    float feat[F];
    for (int f = 0; f < F; ++f) feat[f] = g[PACK_BASE + f];
    vf sum[M];
    for (int j = 0; j < M; ++j) sum[j] = vf{};
    bool any = false;
    for (int ch = 0; ch < tp.nch; ++ch) {
      if (idx >= st.chunk_last[ch]) continue;  // every pixel of the chunk ended in front of it
      any = true;
      const int p0 = ch * L;
      const vf X = loadf(tp.x + p0), Y = loadf(tp.y + p0);
      const vf dx = X - mx, dy = Y - my;
      const vf q = a * dx * dx + 2.0f * b * dx * dy + c * dy * dy;
      const vf ex = exp_neg(-0.5f * q);
      const vf raw = o * ex;
      const vf alpha0 = (q <= Q_MAX) & (raw >= ALPHA_MIN) ? vmin(raw, splat(ALPHA_MAX)) : vf{};
      const vi use = (splati(idx) < loadi(st.last + p0)) & (alpha0 > 0.0f);
      const vf alpha = use ? alpha0 : vf{};
      const vf one_m = 1.0f - alpha;
      const vf inv = 1.0f / one_m;
      const vf Tp = loadf(st.Tp + p0);
      const vf Ti = Tp * inv;  // transmittance in front of this Gaussian
      vf g_alpha = vf{};
      for (int f = 0; f < F; ++f) {
        const vf Gf = loadf(st.G + (size_t)f * S + p0);
        const vf bf = loadf(st.behind + (size_t)f * S + p0);
        g_alpha += Gf * (feat[f] - bf);
        sum[PACK_BASE + f] += alpha * Ti * Gf;
        storef(st.behind + (size_t)f * S + p0, use ? alpha * feat[f] + one_m * bf : bf);
      }
      g_alpha = Ti * g_alpha - loadf(st.GT + p0) * loadf(st.Tf + p0) * inv;
      const vi lin = use & (raw <= ALPHA_MAX);  // no gradient where alpha is clamped at 0.99
      const vf g_o = lin ? g_alpha * ex : vf{};
      const vf g_q = lin ? -0.5f * g_alpha * raw : vf{};
      sum[0] -= g_q * (2.0f * a * dx + 2.0f * b * dy);
      sum[1] -= g_q * (2.0f * b * dx + 2.0f * c * dy);
      sum[2] += g_q * dx * dx;
      sum[3] += g_q * 2.0f * dx * dy;
      sum[4] += g_q * dy * dy;
      sum[5] += g_o;
      storef(st.Tp + p0, use ? Ti : Tp);
    }
    if (!any) continue;
    float r[M];
    reduce_lanes<M>(sum, r);
    float* out = grads + v * D;
    for (int j = 0; j < M; ++j) out[j] += r[j];
  }
}

}  // namespace simd
}  // namespace stdr
#endif
