// The nearest-neighbour family of the CPU extension (ops_cpu.cpp binds it; torch twin
// stdr.knn.knn_direct_torch): knn_direct, the k nearest of a set of points (of any dimension) for
// each query, as the per-step searches of SC-GS (Gaussians to control nodes, 11-D) and SP-GS (to
// superpoints, 3-D) need.
#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <tuple>
#include <vector>

#include "../knn_math.h"
#include "raster_simd.h"  // the vector type (stdr::simd::vf) and STDR_SIMD

namespace {

// One query's best-k list and its filter bound (reach; reach_f: the same in float, rounded up,
// +inf while the k-th best is a NaN so that any number can still displace it).
struct Nearest {
  double* bd;
  int64_t* bj;
  int n, k;
  double reach;
  float reach_f;
  void insert(double d, int64_t j, int64_t dims) {
    n = stdr::knn_insert(bd, bj, n, k, d, j);
    if (n < k) return;
    reach = stdr::knn_filter_bound(bd[k - 1], dims);
    reach_f = reach != reach ? std::numeric_limits<float>::infinity()
                             : std::nextafter(float(reach), std::numeric_limits<float>::infinity());
  }
};

#ifdef STDR_SIMD
// Bit t set where lane t of a comparison is true.
inline uint32_t lanes_set(stdr::simd::vi m) {
#if defined(__AVX512F__)
  return _mm512_cmplt_epi32_mask((__m512i)m, _mm512_setzero_si512());
#else
  int32_t v[stdr::simd::L];
  stdr::simd::storei(v, m);
  uint32_t bits = 0;
  for (int t = 0; t < stdr::simd::L; ++t) bits |= uint32_t(v[t] != 0) << t;
  return bits;
#endif
}
#endif

// Squared distances [Q, k] (float) and indices [Q, k] (int64) of the k nearest `points` [P, D] to
// each of `query` [Q, D], nearest first, ties to the lower index (knn_math.h). With exclude_self,
// query i is points[i] and is not its own neighbour. Deterministic: each query is one
// thread's, whatever the thread count.
std::tuple<at::Tensor, at::Tensor> knn_direct(const at::Tensor& query0, const at::Tensor& points0, int64_t k,
                                              bool exclude_self) {
  TORCH_CHECK(query0.device().is_cpu() && points0.device().is_cpu(), "stdr knn: query and points must be on the CPU");
  TORCH_CHECK(query0.scalar_type() == at::kFloat && points0.scalar_type() == at::kFloat,
              "stdr knn: query and points must be float32");
  TORCH_CHECK(query0.dim() == 2 && points0.dim() == 2 && query0.size(1) == points0.size(1) && query0.size(1) >= 1,
              "stdr knn: query and points must be [N, D] with one D");
  const int64_t Q = query0.size(0), P = points0.size(0), D = query0.size(1);
  static_assert(stdr::KNN_MAX_K == 16, "the message below names the bound");
  TORCH_CHECK(k >= 1 && k <= stdr::KNN_MAX_K, "stdr knn: k must be in 1..16");
  TORCH_CHECK(P - (exclude_self ? 1 : 0) >= k, "stdr knn: fewer points than k (plus the query itself with exclude_self)");
  TORCH_CHECK(!exclude_self || Q == P, "stdr knn: exclude_self needs the query to be the points");
  const at::Tensor query = query0.contiguous(), points = points0.contiguous();
  auto dist = at::empty({Q, k}, query.options());
  auto index = at::empty({Q, k}, query.options().dtype(at::kLong));
  const float* q = query.data_ptr<float>();
  const float* p = points.data_ptr<float>();
  float* out_d = dist.data_ptr<float>();
  int64_t* out_i = index.data_ptr<int64_t>();
  std::vector<float> pt(D * P);  // the points by coordinate: the distance loop runs along the points
  for (int64_t j = 0; j < P; ++j)
    for (int64_t c = 0; c < D; ++c) pt[c * P + j] = p[j * D + c];
  // Points in blocks of L (one vector register): their float32 distances in registers, a filter
  // only; the lanes within reach of the k-th best so far (few, once the list is full) get their
  // exact distance (knn_math.h) and may enter. The points after the last full block go one by one.
  at::parallel_for(0, Q, 256, [&](int64_t begin, int64_t end) {
    double bd[stdr::KNN_MAX_K];
    int64_t bj[stdr::KNN_MAX_K];
    for (int64_t i = begin; i < end; ++i) {
      const float* qi = q + i * D;
      Nearest best{bd, bj, 0, (int)k, std::numeric_limits<double>::infinity(),
                   std::numeric_limits<float>::infinity()};
      auto consider = [&](int64_t j, float rough) {  // a point that passed the filter
        if ((best.n == k && double(rough) > best.reach) || (exclude_self && j == i)) return;
        double exact = 0.0;
        for (int64_t c = 0; c < D; ++c) exact = stdr::knn_add(exact, qi[c], pt[c * P + j]);
        best.insert(exact, j, D);
      };
      int64_t j0 = 0;
#ifdef STDR_SIMD
      using stdr::simd::L;
      for (; j0 + L <= P; j0 += L) {
        stdr::simd::vf r = stdr::simd::splat(0.0f);
        for (int64_t c = 0; c < D; ++c) {
          const stdr::simd::vf d = stdr::simd::splat(qi[c]) - stdr::simd::loadf(pt.data() + c * P + j0);
          r += d * d;
        }
        uint32_t lanes = best.n < k ? 0xffffu : lanes_set(r <= stdr::simd::splat(best.reach_f));
        if (!lanes) continue;
        float rough[L];
        stdr::simd::storef(rough, r);
        for (; lanes; lanes &= lanes - 1) {
          const int t = __builtin_ctz(lanes);
          consider(j0 + t, rough[t]);
        }
      }
#endif
      for (; j0 < P; ++j0) {
        float rough = 0.0f;
        for (int64_t c = 0; c < D; ++c) {
          const float d = qi[c] - pt[c * P + j0];
          rough += d * d;
        }
        if (best.n < k || !(double(rough) > best.reach)) consider(j0, rough);
      }
      for (int64_t t = 0; t < k; ++t) {
        out_d[i * k + t] = (float)bd[t];
        out_i[i * k + t] = bj[t];
      }
    }
  });
  return {dist, index};
}

}  // namespace
