// Many small tensors in one parallel loop: all tensors' elements end to end, split over the threads
// (Adam's step, the finite checks). One loop per tensor would leave most of them too small to
// split, and each loop costs a fork and a join.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <vector>

namespace dibrgs {

// Fewer elements than this in all run on the calling thread (the fork costs more than the split
// saves). A step's Adam (about 200,000 elements) once ran on one thread too, when a fork had to
// wake a sleeping worker; with the worker still spinning (common/openmp.py) and equal shares
// (below) it takes 0.24 ms on two threads against 0.38 on one, in the step (docs/benchmarks.md,
// session 39).
constexpr int64_t SERIAL_BELOW = int64_t(1) << 15;

// Calls fn(t, i0, i1) for the elements [i0, i1) of tensor t (lengths[t] elements): all tensors end
// to end, cut into one equal run of elements a thread (at least `grain` elements each), from one
// at::parallel_for (see SERIAL_BELOW). Equal runs, not equal counts of pieces: the tensors' sizes
// differ a thousandfold, and halving a list of pieces gave one thread 2-8x the other's time.
template <typename F>
void parallel_chunks(const std::vector<int64_t>& lengths, int64_t grain, F&& fn) {
  int64_t total = 0;
  for (const int64_t l : lengths) total += l;
  const int64_t runs = total < SERIAL_BELOW ? 1
                                            : std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(),
                                                                                     total / std::max<int64_t>(grain, 1)));
  at::parallel_for(0, runs, 1, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      const int64_t a = total * r / runs, b = total * (r + 1) / runs;  // this run's elements
      int64_t start = 0;  // of tensor t, counted end to end
      for (size_t t = 0; t < lengths.size() && start < b; ++t) {
        const int64_t i0 = std::max<int64_t>(a - start, 0), i1 = std::min<int64_t>(b - start, lengths[t]);
        if (i0 < i1) fn(static_cast<int64_t>(t), i0, i1);
        start += lengths[t];
      }
    }
  });
}

// Runs worker(next) on `threads` of torch's intra-op threads (all by default), each pulling work
// indices from the shared counter next (dynamic scheduling: the compositing's tiles, the binning's
// blocks, dynamic_for's runs).
template <typename F>
void run_workers(F&& worker, int64_t threads = at::get_num_threads()) {
  std::atomic<int64_t> next(0);
  at::parallel_for(0, threads, 1, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) worker(next);
  });
}

// Calls fn(i0, i1) for consecutive runs [i0, i1) of [0, n), `chunk` elements each (the last may be
// shorter), the threads pulling runs from a shared counter; on the calling thread alone below four
// runs. For loops whose elements cost about the same but whose halves did not: on two cores the
// calling thread, which ran the Python between two calls, took 10-23 % longer over its half than
// the other thread over the same amount of work (spawning, projection; docs/benchmarks.md,
// session 40), and a static split waits for it.
template <typename F>
void dynamic_for(int64_t n, int64_t chunk, F&& fn) {
  const int64_t nc = (n + chunk - 1) / chunk;
  const int64_t T = std::min<int64_t>(at::get_num_threads(), nc);
  if (T < 2 || nc < 4 || at::in_parallel_region()) {
    if (n > 0) fn(int64_t(0), n);
    return;
  }
  run_workers(
      [&](std::atomic<int64_t>& next) {
        for (int64_t c = next++; c < nc; c = next++) fn(c * chunk, std::min(n, (c + 1) * chunk));
      },
      T);
}

}  // namespace dibrgs
