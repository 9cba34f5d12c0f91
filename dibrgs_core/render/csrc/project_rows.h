// The IBR projection P applied to the anchors' rows (models/ibr/projection.py project_rows), forward
// and the gradient of its weights, for the rows a mask selects (the anchors a view sees):
//   out[i, c] = sum_k x_i[k] Wt[k, c],   x_i = rows[idx[i]]  (K = D + 1 values: the levels' raw
//   features side by side, then the "seen" column, whose weight row is the levels' biases summed)
//   G[k, c] = sum_i x_i[k] g[i, c]      (every level's weight gradient side by side, the biases' last)
// In torch this was a boolean gather, the weight matrix assembled from the levels (a cat, a stack,
// a sum), a product and, backward, a product and per-level slices: about ten operators and three
// autograd nodes a step on the calling thread, about 1 ms of a 256x256 step's serial part (issue 17).
// A row's sum runs over k in order, so its value does not depend on which rows are computed with it
// (training's recorded forward and evaluation's cached one agree bit for bit); the gradient sums
// fixed blocks of rows, then the blocks in order: the same on any thread count.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <vector>

#include "chunks.h"     // dynamic_for
#include "composite.h"  // the build's vector type, Vec<T>::V
#include "ssim.h"       // ssim::load / ssim::store: unaligned vector loads and stores

namespace dibrgs {
namespace prows {

constexpr int64_t BLOCK = 256;  // rows a partial sum of the gradient

// Sums of R rows (or R k's) in flight at once: one chain of fused multiply-adds is bound by their
// latency, not their throughput (four cycles each); R independent chains fill the pipeline.
constexpr int64_t R = 8;

// out (M, C) from rows (., K), idx (M,) and Wt (K, C). Each output vector (L columns of a row) is a
// chain over k in order, whichever rows share the pass, so a row's value does not depend on the
// others; the columns past the last whole vector are summed the same way one at a time.
template <typename T>
void forward(const T* rows, const int64_t* idx, int64_t M, int64_t K, const T* Wt, int64_t C, T* out) {
  typedef typename Vec<T>::V V;
  constexpr int64_t L = sizeof(V) / sizeof(T);
  at::parallel_for(0, M, BLOCK, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; i += R) {
      const int64_t n = std::min(R, e - i);
      const T* x[R];
      for (int64_t r = 0; r < R; ++r) x[r] = rows + idx[i + std::min(r, n - 1)] * K;
      int64_t c0 = 0;
      for (; c0 + L <= C; c0 += L) {
        V acc[R] = {};
        for (int64_t k = 0; k < K; ++k) {
          const V w = ssim::load<V>(Wt + k * C + c0);
          for (int64_t r = 0; r < R; ++r) acc[r] += x[r][k] * w;
        }
        for (int64_t r = 0; r < n; ++r) ssim::store(out + (i + r) * C + c0, acc[r]);
      }
      for (int64_t c = c0; c < C; ++c)
        for (int64_t r = 0; r < n; ++r) {
          T acc = 0;
          for (int64_t k = 0; k < K; ++k) acc += x[r][k] * Wt[k * C + c];
          out[(i + r) * C + c] = acc;
        }
    }
  });
}

// G (K, C) from g (M, C), rows (., K) and idx (M,): each block of BLOCK rows summed over its rows in
// order (R k's a pass), then the blocks in order. The blocks are pulled by the threads (the last is
// short: halved statically, the second thread waited 55-65 us of a 150 us call in the step), and
// the blocks' sum is split over the threads by entry (each entry's sum in block order).
template <typename T>
void weight_grad(const T* g, const T* rows, const int64_t* idx, int64_t M, int64_t K, int64_t C, T* G) {
  typedef typename Vec<T>::V V;
  constexpr int64_t L = sizeof(V) / sizeof(T);
  const int64_t nb = (M + BLOCK - 1) / BLOCK;
  std::vector<T> part(static_cast<size_t>(nb * K * C));
  dibrgs::dynamic_for(nb, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      T* P = part.data() + b * K * C;
      const int64_t i0 = b * BLOCK, i1 = std::min(M, i0 + BLOCK);
      for (int64_t k = 0; k < K; k += R) {
        const int64_t n = std::min(R, K - k);
        int64_t kk[R];
        for (int64_t r = 0; r < R; ++r) kk[r] = k + std::min(r, n - 1);
        int64_t c0 = 0;
        for (; c0 + L <= C; c0 += L) {
          V acc[R] = {};
          for (int64_t i = i0; i < i1; ++i) {
            const V gi = ssim::load<V>(g + i * C + c0);
            const T* x = rows + idx[i] * K;
            for (int64_t r = 0; r < R; ++r) acc[r] += x[kk[r]] * gi;
          }
          for (int64_t r = 0; r < n; ++r) ssim::store(P + (k + r) * C + c0, acc[r]);
        }
        for (int64_t c = c0; c < C; ++c)
          for (int64_t r = 0; r < n; ++r) {
            T acc = 0;
            for (int64_t i = i0; i < i1; ++i) acc += rows[idx[i] * K + k + r] * g[i * C + c];
            P[(k + r) * C + c] = acc;
          }
      }
    }
  });
  at::parallel_for(0, K * C, 2048, [&](int64_t j0, int64_t j1) {
    std::fill(G + j0, G + j1, T(0));
    for (int64_t b = 0; b < nb; ++b)
      for (int64_t j = j0; j < j1; ++j) G[j] += part[b * K * C + j];
  });
}

}  // namespace prows
}  // namespace dibrgs
