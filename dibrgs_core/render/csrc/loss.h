// The sums of the training loss beside the SSIM kernels (rasterize.cpp photometric_forward;
// training/losses.py photometric_loss):
//   loss = (1 - lam) sum(|x - y| wl) + lam sum((1 - S) ws)
// over n values (pixels x channels, the weights given per value); its gradient is added in the SSIM
// backward's pass (ssim.h). Native vectors of composite.h's width, scalar tails; the sums go by
// fixed blocks of BLOCK values (partial sums in double, added in block order) so that the result
// does not depend on the thread count. Branch-free: a sign on random data is a misprediction per
// value as a branch.
#pragma once

#include <ATen/Parallel.h>

#include <cstdint>
#include <vector>

#include "ssim.h"

namespace dibrgs {
namespace loss {

constexpr int64_t BLOCK = 4096;

// |d| of a native vector or a scalar (the same select for both).
template <typename U>
inline U vabs(U d) {
  return d < 0 ? -d : d;
}

// The lanes of v summed in double (composite.h's hsum sums them in T).
template <typename U, typename T>
inline double hsum(const U& v) {
  double s = 0.0;
  for (int64_t l = 0; l < ssim::Lanes<U>::value; ++l) s += static_cast<double>(reinterpret_cast<const T*>(&v)[l]);
  return s;
}

// {sum |x - y| wl, sum (1 - S) ws} over n values.
template <typename T>
void sums(const T* x, const T* y, const T* S, const T* wl, const T* ws, int64_t n, double out[2]) {
  typedef typename Vec<T>::V V;
  constexpr int64_t L = ssim::Lanes<V>::value;
  const int64_t nb = (n + BLOCK - 1) / BLOCK;
  std::vector<double> pa(nb), pb(nb);
  dynamic_for(nb, 2, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t i0 = b * BLOCK, i1 = std::min(n, i0 + BLOCK);
      V a{}, s{};
      const V one = V{} + T(1);
      int64_t i = i0;
      for (; i + L <= i1; i += L) {
        const V d = ssim::load<V>(x + i) - ssim::load<V>(y + i);
        a += vabs(d) * ssim::load<V>(wl + i);
        s += (one - ssim::load<V>(S + i)) * ssim::load<V>(ws + i);
      }
      double ta = hsum<V, T>(a), ts = hsum<V, T>(s);
      for (; i < i1; ++i) {
        ta += static_cast<double>(vabs(x[i] - y[i]) * wl[i]);
        ts += static_cast<double>((T(1) - S[i]) * ws[i]);
      }
      pa[b] = ta;
      pb[b] = ts;
    }
  });
  out[0] = out[1] = 0.0;
  for (int64_t b = 0; b < nb; ++b) {
    out[0] += pa[b];
    out[1] += pb[b];
  }
}

// The volume regulariser (training/losses.py mean_volume): sum over n rows of s (n, 3) of
// (s0 / u)(s1 / u)(s2 / u), by fixed blocks of rows (the result does not depend on the thread
// count). Products and sums in double, where three float factors can neither overflow nor
// underflow, and 1 / u^3 applied once at the end (one divide a row cost more than the rest).
template <typename T>
double volume_sum(const T* s, int64_t n, double u) {
  const int64_t nb = (n + BLOCK - 1) / BLOCK;
  std::vector<double> part(nb);
  at::parallel_for(0, nb, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      double acc[4] = {0.0, 0.0, 0.0, 0.0};  // four chains: an add's latency, not one chain
      for (int64_t i = b * BLOCK, i1 = std::min(n, i + BLOCK); i < i1; ++i)
        acc[i & 3] += static_cast<double>(s[3 * i]) * s[3 * i + 1] * s[3 * i + 2];
      part[b] = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    }
  });
  double total = 0.0;
  for (const double p : part) total += p;
  const double inv = 1.0 / u;
  return total * inv * inv * inv;
}

// ds = k d(volume_sum)/ds: ds_ij = k / u^3 (product of row i's other two scales).
template <typename T>
void volume_grad(const T* s, int64_t n, double k, double u, T* ds) {
  const double inv = 1.0 / u, c = k * inv * inv * inv;
  at::parallel_for(0, n, BLOCK, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const double a = s[3 * i], b = s[3 * i + 1], d = s[3 * i + 2];
      ds[3 * i] = static_cast<T>(c * b * d);
      ds[3 * i + 1] = static_cast<T>(c * a * d);
      ds[3 * i + 2] = static_cast<T>(c * a * b);
    }
  });
}

}  // namespace loss
}  // namespace dibrgs
