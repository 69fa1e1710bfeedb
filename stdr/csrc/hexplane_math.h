// HexPlane sampling math shared by the CPU (C++) and CUDA backends (4DGaussians' feature field,
// stdr/baselines/fourdgs.py, whose torch code is the twin the parity tests pin these to).
//
// A plane is [C, H, W] (row-major, channel first); a point samples it at (u, v) in [-1, 1]
// with u along W and v along H, bilinearly, -1 and 1 being the centres of the corner cells
// (grid_sample's align_corners=True) and zero outside (padding_mode="zeros"). A HexPlane
// feature at scale m is the product over the scale's six planes of the samples, channel by
// channel; the six planes pair the four coordinates (x, y, z, t) as HEX_PAIRS.
#pragma once

#include "hd.h"

#include <cmath>
#include <cstdint>

namespace stdr {

constexpr int HEX_PLANES = 6;
// plane p samples at (coord[hex_u(p)], coord[hex_v(p)]): (0,1) (0,2) (0,3) (1,2) (1,3) (2,3)
// (functions, not arrays: a namespace-scope array is not readable from CUDA device code)
STDR_HD int hex_u(int p) { return p < 3 ? 0 : (p < 5 ? 1 : 2); }
STDR_HD int hex_v(int p) { return p == 0 ? 1 : ((p == 1 || p == 3) ? 2 : 3); }

// The four bilinear corners of (u, v) on an H x W plane: offsets y * W + x into one channel and
// weights; a corner outside the plane gets offset 0 and weight 0 (so it reads a valid cell and adds
// nothing). Corner order: (x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1).
template <typename T>
STDR_HD void hex_corners(T u, T v, int H, int W, int64_t off[4], T w[4]) {
  const T x = (u + T(1)) * (T(0.5) * T(W - 1));
  const T y = (v + T(1)) * (T(0.5) * T(H - 1));
  const T xf = floor(x), yf = floor(y);
  const T fx = x - xf, fy = y - yf;
  // a far-away or non-finite coordinate is outside before any integer conversion
  const T lim = T(1 << 30);
  const int x0 = (xf >= -lim && xf <= lim) ? (int)xf : -2;
  const int y0 = (yf >= -lim && yf <= lim) ? (int)yf : -2;
  const T wk[4] = {(T(1) - fx) * (T(1) - fy), fx * (T(1) - fy), (T(1) - fx) * fy, fx * fy};
#pragma unroll
  for (int k = 0; k < 4; ++k) {
    const int xi = x0 + (k & 1), yi = y0 + (k >> 1);
    const bool ok = xi >= 0 && xi < W && yi >= 0 && yi < H;
    off[k] = ok ? (int64_t)yi * W + xi : 0;
    w[k] = ok ? wk[k] : T(0);
  }
}

template <typename T>
STDR_HD T hex_sample(const T* channel, const int64_t off[4], const T w[4]) {
  return w[0] * channel[off[0]] + w[1] * channel[off[1]] + w[2] * channel[off[2]] + w[3] * channel[off[3]];
}

}  // namespace stdr
