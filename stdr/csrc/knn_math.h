// The nearest-neighbour search's per-pair math and its selection, shared by the CPU (C++) and
// CUDA backends. The torch twin is stdr.knn.knn_direct, which the parity tests pin these to.
//
// A distance is the squared length of the coordinate differences: each difference in float (one
// subtraction, nothing to fuse), its square and the sum in double, coordinate by coordinate in
// order, where a float's square is exact and a fused multiply-add gives the bits of a multiply
// and an add. So every backend and
// the twin get the same value, whatever the compiler contracts. The k nearest are the k smallest
// (distance, index) pairs: a tie goes to the lower index, a NaN comes last.
#pragma once

#include "hd.h"

#include <cstdint>

namespace stdr {

constexpr int KNN_MAX_K = 16;

// One coordinate's term added to a running squared distance: the float difference, squared and
// added in double. A distance is ((0 + d_0²) + d_1²) + ... over the coordinates in order.
STDR_HD double knn_add(double acc, float q, float p) {
  const double d = double(q - p);
  return acc + d * d;
}

// A bound on how far a float32 sum of D float squares (any order, fused or not) can lie from the
// exact sum: rel * exact + abs (the float rounding of each of its steps, and a square flushed near
// zero). A point whose float distance exceeds the bound of the k-th best's exact distance cannot
// be nearer than it, so only the others need their exact distance.
constexpr double KNN_FLOAT_REL = 6.0e-8;   // > 2^-24 per step, for up to 2 D steps
STDR_HD double knn_filter_bound(double exact, int64_t d) {
  return exact * (1.0 + 2.0 * double(d) * KNN_FLOAT_REL) + double(d) * 1.0e-37;
}

// The order of distances: ascending, a NaN after every number (as torch.sort puts it).
STDR_HD bool knn_less(double a, double b) { return a < b || (b != b && a == a); }

// Insert (d, j) into the sorted best-`k` list (bd, bj) holding n entries; j arrives in increasing
// order, so an equal distance stays behind the earlier index. Returns the new count.
STDR_HD int knn_insert(double* bd, int64_t* bj, int n, int k, double d, int64_t j) {
  if (n == k && !knn_less(d, bd[k - 1])) return n;
  int s = n < k ? n++ : k - 1;
  while (s > 0 && knn_less(d, bd[s - 1])) {
    bd[s] = bd[s - 1];
    bj[s] = bj[s - 1];
    --s;
  }
  bd[s] = d;
  bj[s] = j;
  return n;
}

}  // namespace stdr
