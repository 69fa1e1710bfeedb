// Per-Gaussian and per-pixel rasterization math shared by the CPU (C++) and CUDA backends.
//
// Every function is a small inline `__host__ __device__` function on scalars, free of torch and
// of branches in the per-pixel paths (ternaries only), so the CPU loops vectorize across pixels
// and the CUDA kernels run the very same arithmetic. The CPU parity tests therefore check the
// math that both backends execute.
//
// Semantics (identical to stdr/render/reference.py):
//   q      = d^T Q d, d = pixel centre - mean, Q = [[a, b], [b, c]] (the conic)
//   alpha  = min(0.99, o exp(-q/2)) where q <= 9 (3-sigma) and o exp(-q/2) >= 1/255, else 0
//   front to back: T_{i+1} = T_i (1 - alpha_i); compositing stops *before* the first Gaussian
//   that would bring T below 1e-4.
//
// Packed Gaussian layout (one row per visible Gaussian, in depth order):
//   [mx, my, a, b, c, o, f_0 .. f_{F-1}]   (PACK_BASE + F values)
#pragma once

#include "hd.h"

#include <cmath>
#include <cstdint>

namespace stdr {

constexpr int PACK_BASE = 6;  // mx, my, a, b, c, o
constexpr float ALPHA_MAX = 0.99f;
constexpr float ALPHA_MIN = 1.0f / 255.0f;
constexpr float T_MIN = 1e-4f;
constexpr float Q_MAX = 9.0f;  // (3 sigma)^2
constexpr int MAX_CHANNELS = 8;

template <typename T> STDR_HD T tmin(T a, T b) { return a < b ? a : b; }
template <typename T> STDR_HD T tmax(T a, T b) { return a > b ? a : b; }

// exp(x - n ln2) for the integer n nearest x / ln2, so |x - n ln2| <= ln2/2: ln2 split in two
// for an exact reduction, then a degree-6 Taylor/Horner polynomial (truncation < 2e-8). V is
// float or the CPU's 16-lane float vector (csrc/cpu/raster_simd.h): only * and + with floats.
template <typename V> STDR_HD V exp_reduced(V x, V n) {
  V r = x - n * 0.693145751953125f;
  r = r - n * 1.428606765330187045e-06f;
  V p = r * (1.0f / 720.0f) + 1.0f / 120.0f;
  p = p * r + 1.0f / 24.0f;
  p = p * r + 1.0f / 6.0f;
  p = p * r + 0.5f;
  p = p * r + 1.0f;
  p = p * r + 1.0f;
  return p;
}

// exp(x) for x <= 0 as needed by alpha (arguments below -80 return ~0). On the host this is a
// branch-free polynomial the compiler vectorizes (relative error < 2e-7 in float); double uses
// the library exp so float64 parity tests are exact to rounding.
STDR_HD float exp_neg(float x) {
#ifdef __CUDA_ARCH__
  return expf(x);
#else
  x = tmax(x, -80.0f);
  const float inv_ln2 = 1.44269504088896341f;
  const float n = std::nearbyint(x * inv_ln2);
  const float p = exp_reduced(x, n);
  // scale by 2^n through the exponent bits (n in [-116, 0])
  int32_t e = (int32_t)n + 127;
  union { int32_t i; float f; } u;
  u.i = e << 23;
  return p * u.f;
#endif
}
STDR_HD double exp_neg(double x) { return exp(x); }

// A product and a sum that no compiler fuses into an FMA (CUDA: __fmul_rn / __fadd_rn; nvcc and
// ptxas otherwise contract a * b + c wherever they like, differently in two compilations of one
// expression). The binning's float tests use them, so that its count and write passes round alike.
template <typename T> STDR_HD T mul_rn(T a, T b) {
#ifdef __CUDA_ARCH__
  if constexpr (sizeof(T) == sizeof(float)) return __fmul_rn(a, b);
  else return __dmul_rn(a, b);
#else
  return a * b;
#endif
}
template <typename T> STDR_HD T add_rn(T a, T b) {
#ifdef __CUDA_ARCH__
  if constexpr (sizeof(T) == sizeof(float)) return __fadd_rn(a, b);
  else return __dadd_rn(a, b);
#else
  return a + b;
#endif
}

// q = d^T Q d for d = (dx, dy)
template <typename T> STDR_HD T conic_q(T a, T b, T c, T dx, T dy) {
  return a * dx * dx + T(2) * b * dx * dy + c * dy * dy;
}

// Squared Mahalanobis radius beyond which a Gaussian of opacity o contributes nothing:
// min(9, 2 ln(255 o)). Negative when o < 1/255 (the Gaussian is invisible everywhere).
// Explicitly rounded (mul_rn): the binning evaluates it twice on CUDA.
template <typename T> STDR_HD T cutoff_q(T o) {
  return o > T(0) ? tmin(T(Q_MAX), mul_rn(T(2), T(log(mul_rn(T(255), o))))) : T(-1);
}

// conic_q with explicit rounding (mul_rn / add_rn), for the binning's tests
template <typename T> STDR_HD T conic_q_rn(T a, T b, T c, T dx, T dy) {
  const T xx = mul_rn(mul_rn(a, dx), dx), xy = mul_rn(mul_rn(mul_rn(T(2), b), dx), dy);
  const T yy = mul_rn(mul_rn(c, dy), dy);
  return add_rn(add_rn(xx, xy), yy);
}

// alpha at squared distance q (0 outside the footprint); `raw` = o exp(-q/2) before the clamp.
template <typename T> STDR_HD T pair_alpha(T o, T q, T& raw) {
  raw = o * exp_neg(T(-0.5) * q);
  T alpha = tmin(raw, T(ALPHA_MAX));
  return (q <= T(Q_MAX) && raw >= T(ALPHA_MIN)) ? alpha : T(0);
}

// Minimum of q over the box [x0, x1] x [y0, y1] (pixel centres), for a positive definite conic.
// 0 when the mean is inside; otherwise the minimum over the four edges (exact: q is convex).
// Explicitly rounded (conic_q_rn, mul_rn): the binning evaluates it twice on CUDA.
template <typename T>
STDR_HD T box_min_q(T a, T b, T c, T mx, T my, T x0, T x1, T y0, T y1) {
  if (mx >= x0 && mx <= x1 && my >= y0 && my <= y1) return T(0);
  T best = T(1e30);
  // vertical edges x = xe: q(dy) minimal at dy = -b dx / c
  T xs[2] = {x0, x1};
  for (int k = 0; k < 2; ++k) {
    T dx = xs[k] - mx;
    T dy = tmin(tmax(-mul_rn(b, dx) / c, y0 - my), y1 - my);
    best = tmin(best, conic_q_rn(a, b, c, dx, dy));
  }
  T ys[2] = {y0, y1};
  for (int k = 0; k < 2; ++k) {
    T dy = ys[k] - my;
    T dx = tmin(tmax(-mul_rn(b, dy) / a, x0 - mx), x1 - mx);
    best = tmin(best, conic_q_rn(a, b, c, dx, dy));
  }
  return best;
}

// The tiles a Gaussian may touch: the bounding box of its cut-off ellipse over the pixel
// centres of a width x height image, as a tile range [tx0, tx1) x [ty0, ty1). Returns the
// cut-off (with a small safety margin) through `cut`; false when nothing can be touched.
// `radius` is the projection's 3-sigma radius (0 = culled); when the conic is not positive
// definite the radius square is used without the exact test (`exact` = false).
template <typename T>
STDR_HD bool tile_range(const T* g, int radius, int width, int height, int tile, int& tx0,
                        int& tx1, int& ty0, int& ty1, T& cut, bool& exact) {
  if (radius <= 0) return false;
  const T mx = g[0], my = g[1], a = g[2], b = g[3], c = g[4], o = g[5];
  cut = cutoff_q(o);
  if (!(cut >= T(0))) return false;
  // explicitly rounded where a compiler could fuse a product into a sum (mul_rn, add_rn): the
  // binning evaluates this twice on CUDA (gaussian_tile_keys)
  cut = add_rn(mul_rn(cut, T(1.0001)), T(1e-4));  // never cull a pixel the per-pixel test would keep
  const T det = add_rn(mul_rn(a, c), -mul_rn(b, b));
  exact = a > T(0) && c > T(0) && det > T(0);
  T ex, ey;
  if (exact) {
    ex = sqrt(mul_rn(cut, c) / det) + T(1e-3);
    ey = sqrt(mul_rn(cut, a) / det) + T(1e-3);
    ex = tmin(ex, T(radius));
    ey = tmin(ey, T(radius));
  } else {
    ex = ey = T(radius);
  }
  // pixel i has its centre at i + 0.5: pixels with centres inside [m - e, m + e]
  T px0 = ceil(mx - ex - T(0.5)), px1 = floor(mx + ex - T(0.5));
  T py0 = ceil(my - ey - T(0.5)), py1 = floor(my + ey - T(0.5));
  px0 = tmax(px0, T(0)); py0 = tmax(py0, T(0));
  px1 = tmin(px1, T(width - 1)); py1 = tmin(py1, T(height - 1));
  if (px0 > px1 || py0 > py1) return false;
  tx0 = (int)px0 / tile; tx1 = (int)px1 / tile + 1;
  ty0 = (int)py0 / tile; ty1 = (int)py1 / tile + 1;
  return true;
}

// Whether the Gaussian's footprint reaches any in-image pixel centre of tile (tx, ty).
template <typename T>
STDR_HD bool tile_overlaps(const T* g, T cut, bool exact, int tx, int ty, int tile, int width,
                           int height) {
  if (!exact) return true;
  const T x0 = T(tx * tile) + T(0.5), y0 = T(ty * tile) + T(0.5);
  const T x1 = T(tmin((tx + 1) * tile, width) - 1) + T(0.5);
  const T y1 = T(tmin((ty + 1) * tile, height) - 1) + T(0.5);
  return box_min_q(g[2], g[3], g[4], g[0], g[1], x0, x1, y0, y1) <= cut;
}

// The Gaussian-tile keys of packed row v: ((tile << 32) | v, tile = ty * ntx + tx) for every tile
// its footprint reaches, in tile order. Returns how many tiles that is. With keys == nullptr it
// only counts; otherwise it writes to keys[0, cap) and never beyond, and fills the slots it did
// not reach with `(n_tiles << 32) | v`, a key that sorts after every tile's and so lies in no
// tile's list. A two-pass binner (count, then write into slots sized by the count) calls this
// twice on the same row; compiled twice (nvcc --use_fast_math contracts a * b + c into an FMA in
// one instantiation and not in the other) the float test can disagree by one tile, and the write
// pass must then stay inside the counted slots and leave none of them unwritten.
template <typename T>
STDR_HD int gaussian_tile_keys(const T* g, int radius, int width, int height, int tile, int64_t v,
                               int64_t* keys, int64_t cap) {
  int tx0, tx1, ty0, ty1;
  T cut;
  bool exact;
  const int ntx = (width + tile - 1) / tile;
  const int64_t n_tiles = (int64_t)ntx * ((height + tile - 1) / tile);
  int n = 0;
  int64_t at = 0;
  if (tile_range(g, radius, width, height, tile, tx0, tx1, ty0, ty1, cut, exact)) {
    for (int ty = ty0; ty < ty1; ++ty)
      for (int tx = tx0; tx < tx1; ++tx)
        if (tile_overlaps(g, cut, exact, tx, ty, tile, width, height)) {
          if (keys && at < cap) keys[at++] = ((int64_t)(ty * ntx + tx) << 32) | v;
          ++n;
        }
  }
  if (keys)
    for (; at < cap; ++at) keys[at] = (n_tiles << 32) | v;
  return n;
}

// ---- per pixel, front to back ------------------------------------------------------------
// One Gaussian g (packed row) at pixel centre (px, py). State: transmittance Tp, `done` flag,
// `last` = 1 + index of the last composited Gaussian, accumulated features acc[f * stride].
// Returns 1 when this Gaussian stops the pixel (it is then not composited).
template <typename T, int F>
STDR_HD int forward_pixel(const T* g, T px, T py, int idx, T& Tp, int& done, int& last, T* acc,
                          int stride) {
  T raw;
  const T q = conic_q(g[2], g[3], g[4], px - g[0], py - g[1]);
  const T alpha = pair_alpha(g[5], q, raw);
  const T test = Tp * (T(1) - alpha);
  const bool live = !done && alpha > T(0);
  const bool stop = live && test < T(T_MIN);
  const bool take = live && !stop;
  const T w = take ? alpha * Tp : T(0);
#pragma unroll
  for (int f = 0; f < F; ++f) acc[f * stride] += w * g[PACK_BASE + f];
  // State updates written as unconditional arithmetic (not `x = c ? new : x`), so compilers emit
  // plain vector stores instead of masked stores guarded by data-dependent branches.
  Tp = Tp * (take ? T(1) - alpha : T(1));  // == test where taken, bit for bit
  last = last > (take ? idx + 1 : 0) ? last : (take ? idx + 1 : 0);
  done = done | (stop ? 1 : 0);
  return stop ? 1 : 0;
}

// ---- per pixel, back to front ------------------------------------------------------------
// Gradient of the loss with respect to one Gaussian's packed row from one pixel, walking the
// pixel's list back to front. G[f * stride] = dL/d(accumulated feature f), GT = dL/dT_final,
// Tfin = final transmittance. State: Tp (transmittance *after* this Gaussian, updated to before
// it), behind[f * stride] (features composited behind, normalized). `active` = this Gaussian
// was among the pixel's composited ones (idx < last). Writes PACK_BASE + F contributions to
// out[j * stride].
template <typename T, int F>
STDR_HD void backward_pixel(const T* g, T px, T py, bool active, T& Tp, T* behind,
                            const T* G, T GT, T Tfin, int stride, T* out) {
  T raw;
  const T dx = px - g[0], dy = py - g[1];
  const T a = g[2], b = g[3], c = g[4], o = g[5];
  const T q = conic_q(a, b, c, dx, dy);
  const T alpha0 = pair_alpha(o, q, raw);
  const bool use = active && alpha0 > T(0);
  const T alpha = use ? alpha0 : T(0);
  const T one_m = T(1) - alpha;
  const T Ti = Tp / one_m;  // transmittance in front of this Gaussian
  T feat[F];
#pragma unroll
  for (int f = 0; f < F; ++f) feat[f] = g[PACK_BASE + f];  // unconditional loads
  T g_alpha = T(0);
#pragma unroll
  for (int f = 0; f < F; ++f) {
    const T Gf = G[f * stride];
    const T bf = behind[f * stride];
    g_alpha += Gf * (feat[f] - bf);
    out[(PACK_BASE + f) * stride] = alpha * Ti * Gf;  // alpha = 0 where unused
    behind[f * stride] = use ? alpha * feat[f] + one_m * bf : bf;
  }
  g_alpha = Ti * g_alpha - GT * Tfin / one_m;
  // alpha = min(0.99, o e^{-q/2}): no gradient where clamped
  const bool lin = use && raw <= T(ALPHA_MAX);
  const T e = raw / o;  // e^{-q/2}, o > 0 wherever use
  const T g_o = lin ? g_alpha * e : T(0);
  const T g_q = lin ? T(-0.5) * g_alpha * raw : T(0);
  // q = a dx^2 + 2 b dx dy + c dy^2, dx = px - mx
  out[0 * stride] = -g_q * (T(2) * a * dx + T(2) * b * dy);
  out[1 * stride] = -g_q * (T(2) * b * dx + T(2) * c * dy);
  out[2 * stride] = g_q * dx * dx;
  out[3 * stride] = g_q * T(2) * dx * dy;
  out[4 * stride] = g_q * dy * dy;
  out[5 * stride] = g_o;
  Tp = use ? Ti : Tp;
}

}  // namespace stdr
