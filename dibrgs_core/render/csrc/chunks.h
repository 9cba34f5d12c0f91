// Many small tensors in one parallel loop: every tensor cut into chunks, all chunks of all
// tensors split over the threads (Adam's step, the finite checks). One loop per tensor would
// leave most of them too small to split, and each loop costs a fork and a join.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <utility>
#include <vector>

namespace dibrgs {

// Fewer elements than this in all run on the calling thread (the fork costs more than the split
// saves). A step's Adam (about 200,000 elements) once ran on one thread too, when a fork had to
// wake a sleeping worker; with the worker still spinning (common/openmp.py) it takes 0.30 ms on
// two threads against 0.39 on one, in the step (docs/benchmarks.md, session 39).
constexpr int64_t SERIAL_BELOW = int64_t(1) << 15;

// Calls fn(t, i0, i1) for the elements [i0, i1) of tensor t (lengths[t] elements), in chunks of
// at most `chunk` elements, from one at::parallel_for over all chunks (see SERIAL_BELOW).
template <typename F>
void parallel_chunks(const std::vector<int64_t>& lengths, int64_t chunk, F&& fn) {
  std::vector<std::pair<int64_t, int64_t>> work;  // (tensor, first element)
  for (size_t t = 0; t < lengths.size(); ++t)
    for (int64_t i = 0; i < lengths[t]; i += chunk) work.emplace_back(static_cast<int64_t>(t), i);
  int64_t total = 0;
  for (const int64_t l : lengths) total += l;
  const int64_t n = static_cast<int64_t>(work.size());
  at::parallel_for(0, n, total < SERIAL_BELOW ? std::max<int64_t>(n, 1) : 1, [&](int64_t w0, int64_t w1) {
    for (int64_t w = w0; w < w1; ++w) {
      const int64_t t = work[w].first, i0 = work[w].second;
      fn(t, i0, std::min(lengths[t], i0 + chunk));
    }
  });
}

}  // namespace dibrgs
