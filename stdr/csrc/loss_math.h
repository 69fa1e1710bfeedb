// Per-element math of the training loss, shared by the CPU (C++) and CUDA backends. The torch
// twin is stdr.metrics.image_loss (SSIM as stdr.metrics._ssim_map), which the parity tests pin
// these to.
#pragma once

#include "hd.h"

#include <cmath>
#include <cstdint>

namespace stdr {

constexpr int LOSS_MAX_WINDOW = 31;

// The normalized 1D Gaussian window of `size` taps, computed in double as stdr.metrics._gauss1d.
inline void loss_window(int size, double sigma, double* out) {
  double s = 0.0;
  for (int i = 0; i < size; ++i) {
    const double x = double(i - size / 2);
    out[i] = std::exp(-x * x / (2.0 * sigma * sigma));
    s += out[i];
  }
  for (int i = 0; i < size; ++i) out[i] /= s;
}

// One pixel's SSIM from its five filtered values (mu1, mu2, E[a^2], E[b^2], E[ab]) and its
// partials dS/dmu1, dS/ds11, dS/ds12 (mu2 and s22 fixed: b is a target).
template <typename T>
STDR_HD T ssim_pixel(T m1, T m2, T s11, T s22, T s12, T& d_m1, T& d_s11, T& d_s12) {
  const T C1 = T(0.01 * 0.01), C2 = T(0.03 * 0.03);
  const T m12 = m1 * m2;  // the twin's expression, term for term
  const T A1 = T(2) * m12 + C1, A2 = T(2) * (s12 - m12) + C2;
  const T B1 = m1 * m1 + m2 * m2 + C1, B2 = s11 - m1 * m1 + s22 - m2 * m2 + C2;
  const T D = B1 * B2, S = (A1 * A2) / D;
  d_m1 = (T(2) * m2 * A2 - T(2) * m2 * A1) / D - S * (T(2) * m1 / B1 - T(2) * m1 / B2);
  d_s11 = -S / B2;
  d_s12 = T(2) * A1 / D;
  return S;
}

// The SSIM alone (no partials: a loss without its D-SSIM term, lam = 0).
template <typename T>
STDR_HD T ssim_value(T m1, T m2, T s11, T s22, T s12) {
  const T C1 = T(0.01 * 0.01), C2 = T(0.03 * 0.03);
  const T m12 = m1 * m2;
  return ((T(2) * m12 + C1) * (T(2) * (s12 - m12) + C2)) /
         ((m1 * m1 + m2 * m2 + C1) * (s11 - m1 * m1 + s22 - m2 * m2 + C2));
}

template <typename T>
STDR_HD T loss_sgn(T v) { return T((v > T(0)) - (v < T(0))); }

// One element's image gradient: ks * (F1 + 2 a F2 + b F3) + kl * sgn(a - b), where F1..F3 are the
// filtered partials, ks = -lam g / n and kl = (1 - lam) g / n.
template <typename T>
STDR_HD T loss_grad(T a, T b, T f1, T f2, T f3, T ks, T kl) {
  return ks * (f1 + T(2) * a * f2 + b * f3) + kl * loss_sgn<T>(a - b);
}

}  // namespace stdr
