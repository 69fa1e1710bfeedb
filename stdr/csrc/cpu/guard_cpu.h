// The guard family of the CPU extension (ops_cpu.cpp binds it; torch twin
// stdr.train.guard.nonfinite_flags and Guard.flag_step's update):
// nonfinite_flags / guard_update, the training guard's finiteness check of a list of tensors as
// one call. The test is on the exponent bits, so no compiler flag can fold it away.
#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cstdint>
#include <vector>

namespace stdr_guard {

// Whether a tensor has a NaN or an infinity: an exponent field of all ones. The largest masked
// exponent over a chunk (a max reduction, which vectorizes) equals the mask exactly then.
template <typename U>
U max_masked(const U* __restrict p, int64_t n, U mask) {
  U m = 0;
#pragma omp simd reduction(max : m)
  for (int64_t i = 0; i < n; ++i) {
    const U v = p[i] & mask;
    m = v > m ? v : m;
  }
  return m;
}

template <typename U>
bool any_nonfinite_bits(const U* p, int64_t n, U mask) {
  return at::parallel_reduce(
      0, n, 1 << 18, false,
      [p, mask](int64_t b, int64_t e, bool acc) {  // by value: the loop then vectorizes
        if (acc) return true;
        return max_masked(p + b, e - b, mask) == mask;
      },
      [](bool x, bool y) { return x || y; });
}

inline bool any_nonfinite(const at::Tensor& t0) {
  if (!t0.defined() || t0.numel() == 0 || !t0.is_floating_point()) return false;
  const at::Tensor t = t0.contiguous();
  const int64_t n = t.numel();
  switch (t.scalar_type()) {
    case at::kFloat:
      return any_nonfinite_bits<uint32_t>(reinterpret_cast<const uint32_t*>(t.data_ptr()), n, 0x7f800000u);
    case at::kDouble:
      return any_nonfinite_bits<uint64_t>(reinterpret_cast<const uint64_t*>(t.data_ptr()), n, 0x7ff0000000000000ull);
    case at::kHalf:
      return any_nonfinite_bits<uint16_t>(reinterpret_cast<const uint16_t*>(t.data_ptr()), n, (uint16_t)0x7c00u);
    case at::kBFloat16:
      return any_nonfinite_bits<uint16_t>(reinterpret_cast<const uint16_t*>(t.data_ptr()), n, (uint16_t)0x7f80u);
    default:
      return !at::isfinite(t).all().item<bool>();
  }
}

inline void check_cpu(const std::vector<at::Tensor>& ts) {
  for (size_t i = 0; i < ts.size(); ++i)
    TORCH_CHECK(!ts[i].defined() || ts[i].device().is_cpu(), "stdr guard: every tensor must be on the CPU");
}

}  // namespace stdr_guard

// One bool per tensor: whether it has a non-finite element (undefined / empty / integer: false).
at::Tensor nonfinite_flags(std::vector<at::Tensor> ts) {
  stdr_guard::check_cpu(ts);
  auto out = at::empty({(int64_t)ts.size()}, at::TensorOptions().dtype(at::kBool));
  bool* o = out.data_ptr<bool>();
  for (size_t i = 0; i < ts.size(); ++i) o[i] = stdr_guard::any_nonfinite(ts[i]);
  return out;
}

// The sync-free guard's per-step update, in place (stdr.train.guard.Guard.flag_step's torch form):
// if any tensor is non-finite, flag = 1 (float 0-d) and, where bad_step < 0 (int64 0-d), bad_step =
// step and bad_index = the first such tensor's index. The tensors are checked in order and the
// check stops at the first non-finite one.
void guard_update(std::vector<at::Tensor> ts, at::Tensor flag, at::Tensor bad_step, at::Tensor bad_index,
                  int64_t step) {
  stdr_guard::check_cpu(ts);
  TORCH_CHECK(flag.device().is_cpu() && flag.numel() == 1 && flag.scalar_type() == at::kFloat,
              "stdr guard: flag must be a float32 CPU scalar");
  TORCH_CHECK(bad_step.numel() == 1 && bad_step.scalar_type() == at::kLong && bad_index.numel() == 1 &&
                  bad_index.scalar_type() == at::kLong,
              "stdr guard: bad_step and bad_index must be int64 scalars");
  int64_t first = -1;
  for (size_t i = 0; i < ts.size() && first < 0; ++i)
    if (stdr_guard::any_nonfinite(ts[i])) first = (int64_t)i;
  if (first < 0) return;
  flag.fill_(1.0);
  int64_t* bs = bad_step.data_ptr<int64_t>();
  if (*bs < 0) {
    *bs = step;
    *bad_index.data_ptr<int64_t>() = first;
  }
}
