// Rows idx of an (N, D) tensor and the gradient of that gather (models/spawn.py take_rows): the
// model's per-anchor parameters of the visible anchors. torch's index_select is fine forward,
// but its backward is an index_add into a zeroed tensor that runs on one thread, about 0.1 ms a
// parameter of a 2,800-anchor model. With idx strictly increasing (a nonzero of the visibility
// mask), every row of the gradient is either one row of the upstream gradient or zero: one
// parallel pass of copies, no accumulation.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <cstring>

namespace dibrgs {
namespace rows {

// out[i] = src[idx[i]] for i < M, rows of D values.
template <typename T>
void gather(const T* src, const int64_t* idx, int64_t M, int64_t D, T* out) {
  at::parallel_for(0, M, 1024, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) std::memcpy(out + i * D, src + idx[i] * D, D * sizeof(T));
  });
}

inline bool strictly_increasing(const int64_t* idx, int64_t M) {
  for (int64_t i = 1; i < M; ++i)
    if (idx[i] <= idx[i - 1]) return false;
  return true;
}

// grad (N, D): row idx[i] = g[i], every other row 0; idx strictly increasing and in [0, N).
template <typename T>
void scatter(const T* g, const int64_t* idx, int64_t M, int64_t N, int64_t D, T* grad) {
  at::parallel_for(0, N, 1024, [&](int64_t b, int64_t e) {
    int64_t i = std::lower_bound(idx, idx + M, b) - idx;  // the first selected row at or after b
    for (int64_t r = b; r < e; ++r) {
      if (i < M && idx[i] == r) {
        std::memcpy(grad + r * D, g + i * D, D * sizeof(T));
        ++i;
      } else {
        std::fill(grad + r * D, grad + (r + 1) * D, T(0));
      }
    }
  });
}

}  // namespace rows
}  // namespace dibrgs
