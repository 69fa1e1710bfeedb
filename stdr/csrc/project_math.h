// Per-Gaussian projection and SH shading, forward and backward, shared by the CPU (C++) and
// CUDA backends. The semantics are those of the torch twin (stdr/render/projection.py and
// stdr/render/sh.py, called by stdr.render.render), which the parity tests pin these to:
//
//   camera space  xc = R m + t;  in front: near < z < far (else z is replaced by 1, radius 0)
//   Jacobian      J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]], with (tx, ty) = z clamp(x/z, y/z)
//                 to 1.3x the field of view (3DGS / gsplat)
//   covariance    Sigma = R_q S S R_q^T (q normalized), cov2d = J R Sigma R^T J^T
//   low-pass      (a, b, c) = cov2d + eps2d I; conic = (c, -b, a) / (ac - b^2)
//   antialiased   opacity * sqrt(det(cov2d) / det(cov2d + eps2d I)) (Mip-Splatting)
//   radius        ceil(3 sqrt(lambda_max)), 0 when invalid or when the footprint misses the image
//   colour        max(SH(degree, dir) . coeffs + 0.5, 0), dir = normalize(m - camera centre),
//                 with the gradient through the view direction (as 3DGS)
//
// Gradients are those torch's autograd gives the twin, with one deliberate difference: with
// antialiasing, a 2D covariance of zero determinant gets no gradient through the compensation
// factor (torch's sqrt'(0) makes it inf/NaN there).
#pragma once

#include "raster_math.h"

namespace stdr {

template <typename T> struct ProjCam {
  T R[9];       // world-to-camera rotation, row-major
  T t[3];       // world-to-camera translation
  T center[3];  // camera centre in world space
  T fx, fy, cx, cy;
  T lim_xp, lim_xn, lim_yp, lim_yn;  // Jacobian clamp: -lim_xn <= x/z <= lim_xp
  T near_z, far_z, eps2d;
  int width, height;
  int antialiased;
  int degree;  // SH degree evaluated (0..3)
  int K;       // SH coefficients stored per Gaussian (>= (degree + 1)^2)
};

// The camera as the Python side passes it: 26 doubles, R (9, row-major), t (3), centre (3),
// fx, fy, cx, cy, lim_xp, lim_xn, lim_yp, lim_yn, near, far, eps2d (stdr/render/compiled.py).
constexpr int PROJ_CAM_VALUES = 26;

template <typename T>
inline ProjCam<T> make_proj_cam(const double* c, int width, int height, bool antialiased, int degree, int K) {
  ProjCam<T> cam;
  for (int i = 0; i < 9; ++i) cam.R[i] = (T)c[i];
  for (int i = 0; i < 3; ++i) cam.t[i] = (T)c[9 + i];
  for (int i = 0; i < 3; ++i) cam.center[i] = (T)c[12 + i];
  cam.fx = (T)c[15]; cam.fy = (T)c[16]; cam.cx = (T)c[17]; cam.cy = (T)c[18];
  cam.lim_xp = (T)c[19]; cam.lim_xn = (T)c[20]; cam.lim_yp = (T)c[21]; cam.lim_yn = (T)c[22];
  cam.near_z = (T)c[23]; cam.far_z = (T)c[24]; cam.eps2d = (T)c[25];
  cam.width = width; cam.height = height;
  cam.antialiased = antialiased ? 1 : 0;
  cam.degree = degree;
  cam.K = K;
  return cam;
}

template <typename T> STDR_HD T tsqrt(T x) { return sqrt(x); }

// Real SH basis values Y[0..15] (3DGS's constants and sign convention) at unit direction d.
template <typename T> STDR_HD void sh_basis(int degree, T x, T y, T z, T* Y) {
  Y[0] = T(0.28209479177387814);
  if (degree < 1) return;
  const T C1 = T(0.4886025119029199);
  Y[1] = -C1 * y;
  Y[2] = C1 * z;
  Y[3] = -C1 * x;
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  Y[4] = T(1.0925484305920792) * xy;
  Y[5] = T(-1.0925484305920792) * yz;
  Y[6] = T(0.31539156525252005) * (T(2) * zz - xx - yy);
  Y[7] = T(-1.0925484305920792) * xz;
  Y[8] = T(0.5462742152960396) * (xx - yy);
  if (degree < 3) return;
  Y[9] = T(-0.5900435899266435) * y * (T(3) * xx - yy);
  Y[10] = T(2.890611442640554) * xy * z;
  Y[11] = T(-0.4570457994644658) * y * (T(4) * zz - xx - yy);
  Y[12] = T(0.3731763325901154) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  Y[13] = T(-0.4570457994644658) * x * (T(4) * zz - xx - yy);
  Y[14] = T(1.445305721320277) * z * (xx - yy);
  Y[15] = T(-0.5900435899266435) * x * (xx - T(3) * yy);
}

// g += sum_k w[k] grad Y_k(d) for k >= 1 (the gradient of sum_k w_k Y_k with respect to d).
template <typename T> STDR_HD void sh_basis_vjp(int degree, T x, T y, T z, const T* w, T* g) {
  if (degree < 1) return;
  const T C1 = T(0.4886025119029199);
  g[1] += -C1 * w[1];
  g[2] += C1 * w[2];
  g[0] += -C1 * w[3];
  if (degree < 2) return;
  const T A = T(1.0925484305920792), B = T(-1.0925484305920792), Cc = T(0.31539156525252005),
          D = T(-1.0925484305920792), E = T(0.5462742152960396);
  g[0] += A * y * w[4] + Cc * (T(-2) * x) * w[6] + D * z * w[7] + E * (T(2) * x) * w[8];
  g[1] += A * x * w[4] + B * z * w[5] + Cc * (T(-2) * y) * w[6] + E * (T(-2) * y) * w[8];
  g[2] += B * y * w[5] + Cc * (T(4) * z) * w[6] + D * x * w[7];
  if (degree < 3) return;
  const T K0 = T(-0.5900435899266435), K1 = T(2.890611442640554), K2 = T(-0.4570457994644658),
          K3 = T(0.3731763325901154), K4 = T(-0.4570457994644658), K5 = T(1.445305721320277),
          K6 = T(-0.5900435899266435);
  const T xx = x * x, yy = y * y, zz = z * z;
  // Y9 = K0 (3 x^2 y - y^3)
  g[0] += K0 * (T(6) * x * y) * w[9];
  g[1] += K0 * (T(3) * xx - T(3) * yy) * w[9];
  // Y10 = K1 x y z
  g[0] += K1 * y * z * w[10];
  g[1] += K1 * x * z * w[10];
  g[2] += K1 * x * y * w[10];
  // Y11 = K2 (4 y z^2 - x^2 y - y^3)
  g[0] += K2 * (T(-2) * x * y) * w[11];
  g[1] += K2 * (T(4) * zz - xx - T(3) * yy) * w[11];
  g[2] += K2 * (T(8) * y * z) * w[11];
  // Y12 = K3 (2 z^3 - 3 x^2 z - 3 y^2 z)
  g[0] += K3 * (T(-6) * x * z) * w[12];
  g[1] += K3 * (T(-6) * y * z) * w[12];
  g[2] += K3 * (T(6) * zz - T(3) * xx - T(3) * yy) * w[12];
  // Y13 = K4 (4 x z^2 - x^3 - x y^2)
  g[0] += K4 * (T(4) * zz - T(3) * xx - yy) * w[13];
  g[1] += K4 * (T(-2) * x * y) * w[13];
  g[2] += K4 * (T(8) * x * z) * w[13];
  // Y14 = K5 (x^2 z - y^2 z)
  g[0] += K5 * (T(2) * x * z) * w[14];
  g[1] += K5 * (T(-2) * y * z) * w[14];
  g[2] += K5 * (xx - yy) * w[14];
  // Y15 = K6 (x^3 - 3 x y^2)
  g[0] += K6 * (T(3) * xx - T(3) * yy) * w[15];
  g[1] += K6 * (T(-6) * x * y) * w[15];
}

// Everything the forward computes for one Gaussian, kept for the backward (which recomputes it).
template <typename T> struct ProjState {
  T x, y, z, zs, rx, ry, cxr, cyr, tx, ty;
  bool in_depth, valid;
  T J00, J02, J11, J12;
  T qn[4], qnorm, Rq[9];
  T Sc[6];  // camera-space covariance: xx, xy, xz, yy, yz, zz
  T a0, b0, c0, a, b, c, det, det_s;
  T dir[3], dnorm, d[3];
};

// R^T-free symmetric helpers: S = [s0 s1 s2; s1 s3 s4; s2 s4 s5]
template <typename T> STDR_HD T sym(const T* S, int i, int j) {
  const int idx[3][3] = {{0, 1, 2}, {1, 3, 4}, {2, 4, 5}};
  return S[idx[i][j]];
}

template <typename T>
STDR_HD void project_state(const ProjCam<T>& cam, const T* m, const T* q, const T* s, ProjState<T>& st) {
  const T* R = cam.R;
  st.x = R[0] * m[0] + R[1] * m[1] + R[2] * m[2] + cam.t[0];
  st.y = R[3] * m[0] + R[4] * m[1] + R[5] * m[2] + cam.t[1];
  st.z = R[6] * m[0] + R[7] * m[1] + R[8] * m[2] + cam.t[2];
  st.in_depth = st.z > cam.near_z && st.z < cam.far_z;
  st.zs = st.in_depth ? st.z : T(1);
  st.rx = st.x / st.zs;
  st.ry = st.y / st.zs;
  st.cxr = tmin(tmax(st.rx, -cam.lim_xn), cam.lim_xp);
  st.cyr = tmin(tmax(st.ry, -cam.lim_yn), cam.lim_yp);
  st.tx = st.zs * st.cxr;
  st.ty = st.zs * st.cyr;
  const T z2 = st.zs * st.zs;
  st.J00 = cam.fx / st.zs;
  st.J02 = -cam.fx * st.tx / z2;
  st.J11 = cam.fy / st.zs;
  st.J12 = -cam.fy * st.ty / z2;
  // rotation of the normalized quaternion (w, x, y, z)
  st.qnorm = tsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const T qn = tmax(st.qnorm, T(1e-12));
  for (int k = 0; k < 4; ++k) st.qn[k] = q[k] / qn;
  const T w = st.qn[0], x = st.qn[1], y = st.qn[2], z = st.qn[3];
  T* Q = st.Rq;
  Q[0] = T(1) - T(2) * (y * y + z * z); Q[1] = T(2) * (x * y - w * z); Q[2] = T(2) * (x * z + w * y);
  Q[3] = T(2) * (x * y + w * z); Q[4] = T(1) - T(2) * (x * x + z * z); Q[5] = T(2) * (y * z - w * x);
  Q[6] = T(2) * (x * z - w * y); Q[7] = T(2) * (y * z + w * x); Q[8] = T(1) - T(2) * (x * x + y * y);
  // A = R Rq diag(s): camera-space covariance Sc = A A^T
  T A[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      A[i * 3 + j] = (R[i * 3 + 0] * Q[0 * 3 + j] + R[i * 3 + 1] * Q[1 * 3 + j] + R[i * 3 + 2] * Q[2 * 3 + j]) * s[j];
  int k = 0;
  for (int i = 0; i < 3; ++i)
    for (int j = i; j < 3; ++j)
      st.Sc[k++] = A[i * 3 + 0] * A[j * 3 + 0] + A[i * 3 + 1] * A[j * 3 + 1] + A[i * 3 + 2] * A[j * 3 + 2];
  const T* S = st.Sc;
  // cov2d = J Sc J^T, J rows (J00, 0, J02) and (0, J11, J12)
  st.a0 = st.J00 * st.J00 * S[0] + T(2) * st.J00 * st.J02 * S[2] + st.J02 * st.J02 * S[5];
  st.b0 = st.J00 * st.J11 * S[1] + st.J00 * st.J12 * S[2] + st.J02 * st.J11 * S[4] + st.J02 * st.J12 * S[5];
  st.c0 = st.J11 * st.J11 * S[3] + T(2) * st.J11 * st.J12 * S[4] + st.J12 * st.J12 * S[5];
  st.a = st.a0 + cam.eps2d;
  st.b = st.b0;
  st.c = st.c0 + cam.eps2d;
  st.det = st.a * st.c - st.b * st.b;
  st.valid = st.in_depth && st.det > T(0);
  st.det_s = st.valid ? st.det : T(1);
  for (int i = 0; i < 3; ++i) st.dir[i] = m[i] - cam.center[i];
  st.dnorm = tsqrt(st.dir[0] * st.dir[0] + st.dir[1] * st.dir[1] + st.dir[2] * st.dir[2]);
  const T dn = tmax(st.dnorm, T(1e-12));
  for (int i = 0; i < 3; ++i) st.d[i] = st.dir[i] / dn;
}

// One Gaussian forward. sh points at its K x 3 coefficients.
template <typename T>
STDR_HD void project_forward_one(const ProjCam<T>& cam, const T* m, const T* q, const T* s, T o, const T* sh,
                                 T* means2d, T* depth, T* conic, T* opac, int32_t* radius, T* color) {
  ProjState<T> st;
  project_state(cam, m, q, s, st);
  conic[0] = st.c / st.det_s;
  conic[1] = -st.b / st.det_s;
  conic[2] = st.a / st.det_s;
  T o_out = o;
  if (cam.antialiased) {
    const T det0 = tmax(st.a0 * st.c0 - st.b0 * st.b0, T(0));
    o_out = o * tsqrt(det0 / st.det_s);
  }
  *opac = o_out;
  const T mid = T(0.5) * (st.a + st.c);
  const T lam = mid + tsqrt(tmax(mid * mid - st.det, T(0.1)));
  int32_t r = st.valid ? (int32_t)ceil(T(3) * tsqrt(lam)) : 0;
  const T u = cam.fx * st.x / st.zs + cam.cx, v = cam.fy * st.y / st.zs + cam.cy;
  const T rf = (T)r;
  if (u + rf <= T(0) || u - rf >= (T)cam.width || v + rf <= T(0) || v - rf >= (T)cam.height) r = 0;
  means2d[0] = u;
  means2d[1] = v;
  *depth = st.z;
  *radius = r;
  T Y[16];
  sh_basis(cam.degree, st.d[0], st.d[1], st.d[2], Y);
  const int nb = (cam.degree + 1) * (cam.degree + 1);
  for (int ch = 0; ch < 3; ++ch) {
    T acc = T(0);
    for (int k = 0; k < nb; ++k) acc += Y[k] * sh[k * 3 + ch];
    color[ch] = tmax(acc + T(0.5), T(0));
  }
}

// One Gaussian backward: gradients of (means2d, depth, conic, opac, color) -> (means, quats,
// scales, opacity, sh). g_sh points at K x 3 values, all written.
template <typename T>
STDR_HD void project_backward_one(const ProjCam<T>& cam, const T* m, const T* q, const T* s, T o, const T* sh,
                                  const T* g_m2d, T g_depth, const T* g_conic, T g_opac_out, const T* g_color,
                                  T* g_means, T* g_quats, T* g_scales, T* g_opac, T* g_sh) {
  ProjState<T> st;
  project_state(cam, m, q, s, st);
  // ---- colour: SH and the view direction
  T Y[16];
  sh_basis(cam.degree, st.d[0], st.d[1], st.d[2], Y);
  const int nb = (cam.degree + 1) * (cam.degree + 1);
  T g_raw[3];
  for (int ch = 0; ch < 3; ++ch) {
    T acc = T(0);
    for (int k = 0; k < nb; ++k) acc += Y[k] * sh[k * 3 + ch];
    g_raw[ch] = acc + T(0.5) >= T(0) ? g_color[ch] : T(0);
  }
  T wk[16];
  for (int k = 0; k < cam.K; ++k)
    for (int ch = 0; ch < 3; ++ch) g_sh[k * 3 + ch] = k < nb ? g_raw[ch] * Y[k] : T(0);
  for (int k = 0; k < nb; ++k) wk[k] = g_raw[0] * sh[k * 3] + g_raw[1] * sh[k * 3 + 1] + g_raw[2] * sh[k * 3 + 2];
  T g_d[3] = {T(0), T(0), T(0)};
  sh_basis_vjp(cam.degree, st.d[0], st.d[1], st.d[2], wk, g_d);
  T gm[3];
  if (st.dnorm >= T(1e-12)) {
    const T dot = st.d[0] * g_d[0] + st.d[1] * g_d[1] + st.d[2] * g_d[2];
    for (int i = 0; i < 3; ++i) gm[i] = (g_d[i] - st.d[i] * dot) / st.dnorm;
  } else {
    for (int i = 0; i < 3; ++i) gm[i] = g_d[i] / T(1e-12);
  }
  // ---- means2d and depth
  const T zs = st.zs, z2 = zs * zs;
  T g_x = g_m2d[0] * cam.fx / zs, g_y = g_m2d[1] * cam.fy / zs;
  T g_zs = -(g_m2d[0] * cam.fx * st.x + g_m2d[1] * cam.fy * st.y) / z2;
  T g_z = g_depth;
  // ---- conic -> (a, b, c)
  T g_a, g_b, g_c;
  if (st.valid) {
    const T D = st.det;
    const T gD = -(g_conic[0] * st.c - g_conic[1] * st.b + g_conic[2] * st.a) / (D * D);
    g_a = g_conic[2] / D + gD * st.c;
    g_c = g_conic[0] / D + gD * st.a;
    g_b = -g_conic[1] / D - T(2) * st.b * gD;
  } else {
    g_a = g_conic[2];
    g_c = g_conic[0];
    g_b = -g_conic[1];
  }
  T g_a0 = T(0), g_b0 = T(0), g_c0 = T(0);
  // ---- opacity (and Mip-Splatting's compensation)
  T g_o = g_opac_out;
  if (cam.antialiased) {
    const T det0raw = st.a0 * st.c0 - st.b0 * st.b0;
    const T det0 = tmax(det0raw, T(0));
    const T ratio = det0 / st.det_s;
    const T sq = tsqrt(ratio);
    g_o = g_opac_out * sq;
    if (ratio > T(0)) {
      const T g_ratio = g_opac_out * o / (T(2) * sq);
      const T g_det0 = det0raw >= T(0) ? g_ratio / st.det_s : T(0);
      if (st.valid) {
        const T g_det_s = -g_ratio * det0 / (st.det_s * st.det_s);
        g_a += g_det_s * st.c;
        g_c += g_det_s * st.a;
        g_b += g_det_s * (T(-2) * st.b);
      }
      g_a0 += g_det0 * st.c0;
      g_c0 += g_det0 * st.a0;
      g_b0 += g_det0 * (T(-2) * st.b0);
    }
  }
  g_a0 += g_a;
  g_b0 += g_b;
  g_c0 += g_c;
  // ---- cov2d = J Sc J^T: symmetric upstream G = [[g_a0, g_b0/2], [g_b0/2, g_c0]]
  const T G00 = g_a0, G01 = T(0.5) * g_b0, G11 = g_c0;
  const T J[2][3] = {{st.J00, T(0), st.J02}, {T(0), st.J11, st.J12}};
  // JS = J Sc [2x3]
  T JS[2][3];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      JS[i][j] = J[i][0] * sym(st.Sc, 0, j) + J[i][1] * sym(st.Sc, 1, j) + J[i][2] * sym(st.Sc, 2, j);
  // g_J = 2 G J Sc
  const T gJ00 = T(2) * (G00 * JS[0][0] + G01 * JS[1][0]);
  const T gJ02 = T(2) * (G00 * JS[0][2] + G01 * JS[1][2]);
  const T gJ11 = T(2) * (G01 * JS[0][1] + G11 * JS[1][1]);
  const T gJ12 = T(2) * (G01 * JS[0][2] + G11 * JS[1][2]);
  g_zs += -cam.fx / z2 * gJ00 - cam.fy / z2 * gJ11 + T(2) * cam.fx * st.tx / (z2 * zs) * gJ02 +
          T(2) * cam.fy * st.ty / (z2 * zs) * gJ12;
  const T g_tx = -cam.fx / z2 * gJ02, g_ty = -cam.fy / z2 * gJ12;
  // (tx, ty) = zs clamp(x / zs, ...): torch's clamp passes the gradient where inside (bounds included)
  const bool in_x = st.rx >= -cam.lim_xn && st.rx <= cam.lim_xp;
  const bool in_y = st.ry >= -cam.lim_yn && st.ry <= cam.lim_yp;
  g_zs += g_tx * (st.cxr - (in_x ? st.rx : T(0))) + g_ty * (st.cyr - (in_y ? st.ry : T(0)));
  if (in_x) g_x += g_tx;
  if (in_y) g_y += g_ty;
  if (st.in_depth) g_z += g_zs;
  // g_Sc = J^T G J (symmetric 3x3)
  T GJ[2][3];  // G J
  for (int j = 0; j < 3; ++j) {
    GJ[0][j] = G00 * J[0][j] + G01 * J[1][j];
    GJ[1][j] = G01 * J[0][j] + G11 * J[1][j];
  }
  T gSc[3][3];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) gSc[i][j] = J[0][i] * GJ[0][j] + J[1][i] * GJ[1][j];
  // world covariance: Sc = R Sw R^T -> g_Sw = R^T g_Sc R
  const T* R = cam.R;
  T tmp[3][3], gSw[3][3];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      tmp[i][j] = gSc[i][0] * R[0 * 3 + j] + gSc[i][1] * R[1 * 3 + j] + gSc[i][2] * R[2 * 3 + j];  // g_Sc R
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      gSw[i][j] = R[0 * 3 + i] * tmp[0][j] + R[1 * 3 + i] * tmp[1][j] + R[2 * 3 + i] * tmp[2][j];
  // Sw = M M^T, M = Rq diag(s): g_M = 2 g_Sw M
  const T* Q = st.Rq;
  T gQ[9];
  for (int j = 0; j < 3; ++j) g_scales[j] = T(0);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      const T gM = T(2) * (gSw[i][0] * Q[0 * 3 + j] * s[j] + gSw[i][1] * Q[1 * 3 + j] * s[j] +
                           gSw[i][2] * Q[2 * 3 + j] * s[j]);
      gQ[i * 3 + j] = gM * s[j];
      g_scales[j] += gM * Q[i * 3 + j];
    }
  const T w = st.qn[0], x = st.qn[1], y = st.qn[2], z = st.qn[3];
  T gq[4];
  gq[0] = T(2) * (-z * gQ[1] + y * gQ[2] + z * gQ[3] - x * gQ[5] - y * gQ[6] + x * gQ[7]);
  gq[1] = T(2) * (y * gQ[1] + z * gQ[2] + y * gQ[3] - T(2) * x * gQ[4] - w * gQ[5] + z * gQ[6] + w * gQ[7] -
                  T(2) * x * gQ[8]);
  gq[2] = T(2) * (T(-2) * y * gQ[0] + x * gQ[1] + w * gQ[2] + x * gQ[3] + z * gQ[5] - w * gQ[6] + z * gQ[7] -
                  T(2) * y * gQ[8]);
  gq[3] = T(2) * (T(-2) * z * gQ[0] - w * gQ[1] + x * gQ[2] + w * gQ[3] - T(2) * z * gQ[4] + y * gQ[5] +
                  x * gQ[6] + y * gQ[7]);
  if (st.qnorm >= T(1e-12)) {
    const T dot = gq[0] * st.qn[0] + gq[1] * st.qn[1] + gq[2] * st.qn[2] + gq[3] * st.qn[3];
    for (int k = 0; k < 4; ++k) g_quats[k] = (gq[k] - st.qn[k] * dot) / st.qnorm;
  } else {
    for (int k = 0; k < 4; ++k) g_quats[k] = gq[k] / T(1e-12);
  }
  // camera space -> world: g_m += R^T (g_x, g_y, g_z)
  for (int i = 0; i < 3; ++i) g_means[i] = gm[i] + R[0 * 3 + i] * g_x + R[1 * 3 + i] * g_y + R[2 * 3 + i] * g_z;
  *g_opac = g_o;
}

}  // namespace stdr
