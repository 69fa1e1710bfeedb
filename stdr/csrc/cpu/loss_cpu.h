// The training-loss family of the CPU extension (ops_cpu.cpp binds it; torch twin
// stdr.metrics.image_loss):
//
// * image_loss_forward / image_loss_backward: the training's photometric loss,
//   (1 - lam) * L1 + lam * (1 - SSIM), in one pass over the image instead of ~35 ATen operators
//   forward and ~45 backward. SSIM as stdr.metrics.ssim (its torch twin): 11-tap Gaussian window
//   (sigma 1.5) applied as a vertical then a horizontal pass with zero padding ("same"),
//   C1 = 0.01^2, C2 = 0.03^2, mean over pixels and channels. The forward keeps the three partial
//   derivatives of each pixel's SSIM (by mu1, E[x^2], E[xy]) for the backward, which filters them
//   with the same window (the filter is symmetric and zero padded, so it is its own adjoint).
//   Deterministic: rows are independent work items, sums are per row and added in row order.
#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "../loss_math.h"

namespace stdr_loss {

constexpr int MAX_WINDOW = stdr::LOSS_MAX_WINDOW;

// The window rounded to T (stdr::loss_window computes it in double, as the twin does).
template <typename T>
void gauss1d(int size, double sigma, T* out) {
  double g[MAX_WINDOW];
  stdr::loss_window(size, sigma, g);
  for (int i = 0; i < size; ++i) out[i] = T(g[i]);
}

// Horizontal pass of one row of K maps: out[k][x*C + c] = sum_j g[j] * in[k][(x + j - R)*C + c],
// zero outside the row. `in` and `out` are K rows of RW = W*C values.
template <typename T, int K>
inline void hpass(const T* in, T* out, int64_t RW, int64_t C, const T* g, int R) {
  for (int k = 0; k < K; ++k) {
    const T* src = in + k * RW;
    T* dst = out + k * RW;
    for (int64_t i = 0; i < RW; ++i) dst[i] = T(0);
    for (int j = 0; j < 2 * R + 1; ++j) {
      const int64_t shift = (int64_t)(j - R) * C;  // dst[i] += g[j] * src[i + shift]
      const int64_t lo = shift < 0 ? -shift : 0, hi = shift > 0 ? RW - shift : RW;
      const T w = g[j];
#pragma omp simd
      for (int64_t i = lo; i < hi; ++i) dst[i] += w * src[i + shift];
    }
  }
}

// dst += w * src over n values (a function of its own: a pragma cannot sit in a macro's argument)
template <typename T>
inline void axpy(T w, const T* src, T* dst, int64_t n) {
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) dst[i] += w * src[i];
}

// The five filtered maps of row y (a, b, a^2, b^2, ab -> mu1, mu2, s11, s22, s12), into out[5][RW];
// vt is scratch of 5*RW.
template <typename T>
inline void filtered_row(const T* a, const T* b, int64_t H, int64_t RW, int64_t C, const T* g, int R, int64_t y,
                         T* vt, T* out) {
  for (int64_t i = 0; i < 5 * RW; ++i) vt[i] = T(0);
  for (int j = 0; j < 2 * R + 1; ++j) {
    const int64_t yy = y + j - R;
    if (yy < 0 || yy >= H) continue;
    const T w = g[j];
    const T* ar = a + yy * RW;
    const T* br = b + yy * RW;
#pragma omp simd
    for (int64_t i = 0; i < RW; ++i) {
      const T av = ar[i], bv = br[i];
      vt[i] += w * av;
      vt[RW + i] += w * bv;
      vt[2 * RW + i] += w * (av * av);
      vt[3 * RW + i] += w * (bv * bv);
      vt[4 * RW + i] += w * (av * bv);
    }
  }
  hpass<T, 5>(vt, out, RW, C, g, R);
}

// One row of the forward: from the five filtered maps f [5][RW] (mu1, mu2, s11, s22, s12) and the
// images' rows, the sums of SSIM, |a - b| and (a - b)^2 over the row and, where P0 is given, the
// partials dS/dmu1, dS/ds11, dS/ds12 of each element. A function of its own with restrict
// pointers, so that the loop vectorizes.
template <typename T>
void ssim_row(const T* __restrict f, const T* __restrict ar, const T* __restrict br, int64_t RW, T* __restrict P0,
              T* __restrict P1, T* __restrict P2, double* ss_out, double* sl_out, double* sq_out) {
  const T *mu1 = f, *mu2 = f + RW, *s11 = f + 2 * RW, *s22 = f + 3 * RW, *s12 = f + 4 * RW;
  double ss = 0.0, sl = 0.0, sq = 0.0;
  if (P0 != nullptr) {
#pragma omp simd reduction(+ : ss, sl, sq)
    for (int64_t i = 0; i < RW; ++i) {
      T p0, p1, p2;
      ss += (double)stdr::ssim_pixel<T>(mu1[i], mu2[i], s11[i], s22[i], s12[i], p0, p1, p2);
      P0[i] = p0;
      P1[i] = p1;
      P2[i] = p2;
      const T d = ar[i] - br[i];
      sl += (double)std::abs(d);
      sq += (double)(d * d);
    }
  } else {
#pragma omp simd reduction(+ : ss, sl, sq)
    for (int64_t i = 0; i < RW; ++i) {
      ss += (double)stdr::ssim_value<T>(mu1[i], mu2[i], s11[i], s22[i], s12[i]);
      const T d = ar[i] - br[i];
      sl += (double)std::abs(d);
      sq += (double)(d * d);
    }
  }
  *ss_out = ss;
  *sl_out = sl;
  *sq_out = sq;
}

// One row of the backward: ks * (F1 + 2 a F2 + b F3) + kl * sgn(a - b), where F [3][RW] are the
// filtered partials (none: the L1 term alone).
template <typename T>
void grad_row(const T* __restrict F, const T* __restrict ar, const T* __restrict br, int64_t RW, T ks, T kl,
              T* __restrict out) {
  if (F == nullptr) {
#pragma omp simd
    for (int64_t i = 0; i < RW; ++i) out[i] = kl * stdr::loss_sgn<T>(ar[i] - br[i]);
    return;
  }
  const T *f1 = F, *f2 = F + RW, *f3 = F + 2 * RW;
#pragma omp simd
  for (int64_t i = 0; i < RW; ++i) out[i] = stdr::loss_grad<T>(ar[i], br[i], f1[i], f2[i], f3[i], ks, kl);
}

inline void check_images(const at::Tensor& img, const at::Tensor& gt) {
  TORCH_CHECK(img.dim() == 3 && img.sizes() == gt.sizes() && img.device().is_cpu() && gt.device().is_cpu() &&
                  img.scalar_type() == gt.scalar_type(),
              "stdr image_loss: img and gt must be [H, W, C] CPU tensors of one shape and dtype");
}

}  // namespace stdr_loss

// img, gt [H, W, C] (contiguous, one floating dtype, CPU). Returns {loss (0-d), stats [3] =
// (l1, 1 - ssim, psnr in dB), partials [3, H, W, C] (dS/dmu1, dS/ds11, dS/ds12; empty when
// lam == 0: the backward then needs none)}.
std::vector<at::Tensor> image_loss_forward(at::Tensor img, at::Tensor gt, double lam, int64_t window, double sigma) {
  stdr_loss::check_images(img, gt);
  TORCH_CHECK(window % 2 == 1 && window >= 1 && window <= stdr_loss::MAX_WINDOW,
              "stdr image_loss: window must be odd, 1..31");
  img = img.contiguous();
  gt = gt.contiguous();
  const int64_t H = img.size(0), W = img.size(1), C = img.size(2), RW = W * C, n = H * RW;
  const int R = (int)(window / 2);
  const bool grad = lam != 0.0;
  auto loss = at::empty({}, img.options());
  auto stats = at::empty({3}, img.options());
  auto partials = grad ? at::empty({3, H, W, C}, img.options()) : at::empty({0}, img.options());
  std::vector<double> row_ssim(H), row_l1(H), row_sq(H);
  AT_DISPATCH_FLOATING_TYPES(img.scalar_type(), "stdr_image_loss_forward", [&] {
    using T = scalar_t;
    T g[stdr_loss::MAX_WINDOW];
    stdr_loss::gauss1d<T>((int)window, sigma, g);
    const T* a = img.data_ptr<T>();
    const T* b = gt.data_ptr<T>();
    T* P = grad ? partials.data_ptr<T>() : nullptr;
    at::parallel_for(0, H, 4, [&](int64_t y0, int64_t y1) {
      std::vector<T> vt(5 * RW), f(5 * RW);
      for (int64_t y = y0; y < y1; ++y) {
        stdr_loss::filtered_row<T>(a, b, H, RW, C, g, R, y, vt.data(), f.data());
        const int64_t o = y * RW;
        stdr_loss::ssim_row<T>(f.data(), a + o, b + o, RW, P ? P + o : nullptr, P ? P + n + o : nullptr,
                               P ? P + 2 * n + o : nullptr, &row_ssim[y], &row_l1[y], &row_sq[y]);
      }
    });
    double ss = 0.0, sl = 0.0, sq = 0.0;
    for (int64_t y = 0; y < H; ++y) {  // in row order: the result does not depend on the threads
      ss += row_ssim[y];
      sl += row_l1[y];
      sq += row_sq[y];
    }
    const double N = (double)n, l1 = sl / N, dssim = 1.0 - ss / N, mse = sq / N;
    *loss.data_ptr<T>() = T((1.0 - lam) * l1 + lam * dssim);  // written, not filled: no ATen operator
    T* st = stats.data_ptr<T>();
    st[0] = T(l1);
    st[1] = T(dssim);
    st[2] = T(10.0 * std::log10(1.0 / std::max(mse, 1e-20)));
  });
  return {loss, stats, partials};
}

// The gradient of g_loss * loss with respect to img. g_loss: 0-d (read here, on the CPU).
at::Tensor image_loss_backward(at::Tensor g_loss, at::Tensor img, at::Tensor gt, at::Tensor partials, double lam,
                               int64_t window, double sigma) {
  stdr_loss::check_images(img, gt);
  img = img.contiguous();
  gt = gt.contiguous();
  const int64_t H = img.size(0), W = img.size(1), C = img.size(2), RW = W * C, n = H * RW;
  const int R = (int)(window / 2);
  const bool grad = lam != 0.0;
  TORCH_CHECK(g_loss.numel() == 1 && g_loss.scalar_type() == img.scalar_type() && g_loss.device().is_cpu(),
              "stdr image_loss: the loss gradient must be a CPU scalar of the image's dtype");
  TORCH_CHECK(!grad || (partials.dim() == 4 && partials.size(0) == 3 && partials.numel() == 3 * n),
              "stdr image_loss: partials do not match the image");
  auto out = at::empty_like(img);
  AT_DISPATCH_FLOATING_TYPES(img.scalar_type(), "stdr_image_loss_backward", [&] {
    using T = scalar_t;
    T g[stdr_loss::MAX_WINDOW];
    stdr_loss::gauss1d<T>((int)window, sigma, g);
    const double gl = (double)*g_loss.data_ptr<T>();  // a CPU scalar: no device to wait for
    const T ks = T(-lam * gl / (double)n), kl = T((1.0 - lam) * gl / (double)n);
    const T* a = img.data_ptr<T>();
    const T* b = gt.data_ptr<T>();
    const T* P = grad ? partials.data_ptr<T>() : nullptr;
    T* o = out.data_ptr<T>();
    at::parallel_for(0, H, 4, [&](int64_t y0, int64_t y1) {
      std::vector<T> vt(grad ? 3 * RW : 0), f(grad ? 3 * RW : 0);
      for (int64_t y = y0; y < y1; ++y) {
        const T* ar = a + y * RW;
        const T* br = b + y * RW;
        T* orow = o + y * RW;
        if (!grad) {
          stdr_loss::grad_row<T>(nullptr, ar, br, RW, ks, kl, orow);
          continue;
        }
        for (int64_t i = 0; i < 3 * RW; ++i) vt[i] = T(0);
        for (int j = 0; j < 2 * R + 1; ++j) {
          const int64_t yy = y + j - R;
          if (yy < 0 || yy >= H) continue;
          const T w = g[j];
          for (int k = 0; k < 3; ++k) stdr_loss::axpy<T>(w, P + k * n + yy * RW, vt.data() + k * RW, RW);
        }
        stdr_loss::hpass<T, 3>(vt.data(), f.data(), RW, C, g, R);
        stdr_loss::grad_row<T>(f.data(), ar, br, RW, ks, kl, orow);
      }
    });
  });
  return out;
}
