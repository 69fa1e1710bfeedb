// The HexPlane family of the CPU extension (ops_cpu.cpp binds it): 4DGaussians' six-plane
// feature sampling (math in ../hexplane_math.h, torch twin stdr/baselines/fourdgs.py) and the planes'
// gradients, deterministic on any thread count.
#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <vector>

#include "../hexplane_math.h"

namespace {

// ---------------------------------------------------------------- HexPlane sampling (hexplane_math.h)

void check_hexplane_inputs(const at::Tensor& coords, const std::vector<at::Tensor>& planes) {
  TORCH_CHECK(coords.dim() == 2 && coords.size(1) == 4, "stdr hexplane: coords must be [N, 4]");
  TORCH_CHECK(!planes.empty() && planes.size() % stdr::HEX_PLANES == 0,
              "stdr hexplane: planes must be 6 per scale");
  TORCH_CHECK(coords.device().is_cpu() && coords.is_contiguous(), "stdr CPU hexplane: coords must be a contiguous CPU tensor");
  const int64_t C = planes[0].size(0);
  for (const auto& pl : planes) {
    TORCH_CHECK(pl.dim() == 3 && pl.size(0) == C, "stdr hexplane: every plane must be [C, H, W] with one C");
    TORCH_CHECK(pl.size(1) >= 1 && pl.size(2) >= 1, "stdr hexplane: empty plane");
    TORCH_CHECK(pl.device().is_cpu() && pl.is_contiguous() && pl.scalar_type() == coords.scalar_type(),
                "stdr CPU hexplane: planes must be contiguous CPU tensors of the coords' dtype");
  }
}

// feats [N, M*C]: per scale m the product over its six planes of the bilinear samples; others
// [N, M, 6, C]: for each plane, the product of the five other samples (what the backward needs).
std::vector<at::Tensor> hexplane_forward(at::Tensor coords, std::vector<at::Tensor> planes) {
  check_hexplane_inputs(coords, planes);
  const int64_t N = coords.size(0), P = (int64_t)planes.size(), M = P / stdr::HEX_PLANES, C = planes[0].size(0);
  auto feats = at::empty({N, M * C}, coords.options());
  auto others = at::empty({N, M, stdr::HEX_PLANES, C}, coords.options());
  AT_DISPATCH_FLOATING_TYPES(coords.scalar_type(), "stdr_hexplane_forward", [&] {
    std::vector<const scalar_t*> ptr(P);
    std::vector<int> H(P), W(P);
    for (int64_t q = 0; q < P; ++q) {
      ptr[q] = planes[q].data_ptr<scalar_t>();
      H[q] = (int)planes[q].size(1);
      W[q] = (int)planes[q].size(2);
    }
    const scalar_t* xy = coords.data_ptr<scalar_t>();
    scalar_t *f = feats.data_ptr<scalar_t>(), *o = others.data_ptr<scalar_t>();
    at::parallel_for(0, N, 256, [&](int64_t b, int64_t e) {
      int64_t off[stdr::HEX_PLANES][4];
      scalar_t w[stdr::HEX_PLANES][4];
      for (int64_t n = b; n < e; ++n) {
        const scalar_t* cn = xy + 4 * n;
        for (int64_t m = 0; m < M; ++m) {
          for (int p = 0; p < stdr::HEX_PLANES; ++p) {
            const int64_t q = m * stdr::HEX_PLANES + p;
            stdr::hex_corners<scalar_t>(cn[stdr::hex_u(p)], cn[stdr::hex_v(p)], H[q], W[q], off[p], w[p]);
          }
          scalar_t* orow = o + (n * M + m) * stdr::HEX_PLANES * C;
          for (int64_t c = 0; c < C; ++c) {
            scalar_t s[stdr::HEX_PLANES], pre[stdr::HEX_PLANES + 1], suf[stdr::HEX_PLANES + 1];
            for (int p = 0; p < stdr::HEX_PLANES; ++p) {
              const int64_t q = m * stdr::HEX_PLANES + p;
              s[p] = stdr::hex_sample<scalar_t>(ptr[q] + c * (int64_t)H[q] * W[q], off[p], w[p]);
            }
            pre[0] = scalar_t(1);
            suf[stdr::HEX_PLANES] = scalar_t(1);
            for (int p = 0; p < stdr::HEX_PLANES; ++p) pre[p + 1] = pre[p] * s[p];
            for (int p = stdr::HEX_PLANES - 1; p >= 0; --p) suf[p] = s[p] * suf[p + 1];
            f[n * M * C + m * C + c] = pre[stdr::HEX_PLANES];
            for (int p = 0; p < stdr::HEX_PLANES; ++p) orow[p * C + c] = pre[p] * suf[p + 1];
          }
        }
      }
    });
  });
  return {feats, others};
}

// The planes' gradients of sum(g_feats * feats). Deterministic: each (plane, channel block) is
// one work item that walks the points in order, so no two threads write one cell.
std::vector<at::Tensor> hexplane_backward(at::Tensor coords, std::vector<at::Tensor> planes, at::Tensor others,
                                          at::Tensor g_feats) {
  check_hexplane_inputs(coords, planes);
  const int64_t N = coords.size(0), P = (int64_t)planes.size(), M = P / stdr::HEX_PLANES, C = planes[0].size(0);
  TORCH_CHECK(others.is_contiguous() && others.numel() == N * M * stdr::HEX_PLANES * C &&
              others.scalar_type() == coords.scalar_type(), "stdr hexplane backward: others must be the forward's");
  TORCH_CHECK(g_feats.device().is_cpu() && g_feats.is_contiguous() && g_feats.scalar_type() == coords.scalar_type() &&
              g_feats.dim() == 2 && g_feats.size(0) == N && g_feats.size(1) == M * C,
              "stdr hexplane backward: g_feats must be a contiguous [N, M*C] tensor of the coords' dtype");
  std::vector<at::Tensor> grads;
  for (const auto& pl : planes) grads.push_back(at::zeros_like(pl));
  constexpr int64_t CB = 8;  // channels per work item
  const int64_t blocks = (C + CB - 1) / CB;
  AT_DISPATCH_FLOATING_TYPES(coords.scalar_type(), "stdr_hexplane_backward", [&] {
    const scalar_t *xy = coords.data_ptr<scalar_t>(), *o = others.data_ptr<scalar_t>(), *g = g_feats.data_ptr<scalar_t>();
    std::vector<scalar_t*> gp(P);
    for (int64_t q = 0; q < P; ++q) gp[q] = grads[q].data_ptr<scalar_t>();
    at::parallel_for(0, P * blocks, 1, [&](int64_t b, int64_t e) {
      for (int64_t item = b; item < e; ++item) {
        const int64_t q = item / blocks, c0 = (item % blocks) * CB, c1 = std::min(C, c0 + CB);
        const int64_t m = q / stdr::HEX_PLANES;
        const int p = (int)(q % stdr::HEX_PLANES);
        const int H = (int)planes[q].size(1), W = (int)planes[q].size(2);
        const int64_t HW = (int64_t)H * W;
        scalar_t* out = gp[q];
        int64_t off[4];
        scalar_t w[4];
        for (int64_t n = 0; n < N; ++n) {
          const scalar_t* cn = xy + 4 * n;
          stdr::hex_corners<scalar_t>(cn[stdr::hex_u(p)], cn[stdr::hex_v(p)], H, W, off, w);
          const scalar_t* gn = g + n * M * C + m * C;
          const scalar_t* on = o + ((n * M + m) * stdr::HEX_PLANES + p) * C;
          for (int64_t c = c0; c < c1; ++c) {
            const scalar_t gv = gn[c] * on[c];
            scalar_t* oc = out + c * HW;
            for (int k = 0; k < 4; ++k) oc[off[k]] += gv * w[k];
          }
        }
      }
    });
  });
  return grads;
}

}  // namespace
