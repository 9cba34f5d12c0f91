// SSIM map of two images and its gradient with respect to the first, for the
// training loss (training/losses.py: ssim_map is the torch formulation these
// kernels reproduce). Images are (H, W, C) contiguous, channels interleaved.
// Local statistics use a separable window g (2r + 1 taps) with the borders
// replicated:
//   B(i)[y, x] = sum_{k,l} g[k] g[l] i[clamp(y + k - r), clamp(x + l - r)]
//   mx = B(x), my = B(y), vx = B(x^2) - mx^2, vy = B(y^2) - my^2, cxy = B(xy) - mx my
//   S = (2 mx my + C1)(2 cxy + C2) / ((mx^2 + my^2 + C1)(vx + vy + C2))
// The forward also returns, per pixel, dS/dB(x) (a), dS/dB(x^2) (b) and
// dS/dB(xy) (c); the backward is then dL/dx = B'(G a) + 2 x B'(G b) + y B'(G c)
// with B' the adjoint of B (a window of zero-padded gradients whose share
// outside the image folds onto the edge pixels it replicated).
//
// The forward's threads work through bands of rows (two threads a band, from its two ends), each
// keeping the horizontally blurred statistics of the last 2r + 1 image rows in a ring (L2-sized)
// instead of a whole-image buffer, and every window sum is accumulated in registers over a
// block of NV native vectors (composite.h's width) and stored once: a loop that
// adds one tap at a time into memory is bound by its stores and by loads 4 KiB
// apart from them. Row buffers are padded so that consecutive rows are not.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <vector>

#include "chunks.h"
#include "composite.h"

namespace dibrgs {
namespace ssim {

constexpr double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;
constexpr int NS = 5;  // local statistics: x, y, x^2, y^2, xy
constexpr int NB = 3;  // backward maps: G a, G b, G c
constexpr int NV = 2;  // vectors a block: NS * NV accumulators fit AVX2's 16 registers

template <typename T>
struct Block {
  typedef typename Vec<T>::V V;
  static constexpr int64_t L = VBYTES / static_cast<int64_t>(sizeof(T));  // lanes of V
  static constexpr int64_t N = NV * L;                                     // values a block
};

inline VF madd(VF a, VF b, VF c) { return fmadd(a, b, c); }
inline VD madd(VD a, VD b, VD c) { return fmadd(a, b, c); }
inline float madd(float a, float b, float c) { return a * b + c; }
inline double madd(double a, double b, double c) { return a * b + c; }

// U is a native vector or the scalar T (row tails): loads and stores of sizeof(U) bytes, Lanes<U>
// values.
template <typename U, typename T>
inline U load(const T* p) {
  U v;
  std::memcpy(&v, p, sizeof(U));
  return v;
}
template <typename U, typename T>
inline void store(T* p, const U& v) {
  std::memcpy(p, &v, sizeof(U));
}
template <typename U>
struct Lanes {
  static constexpr int64_t value = 1;
};
template <>
struct Lanes<VF> {
  static constexpr int64_t value = VBYTES / 4;
};
template <>
struct Lanes<VD> {
  static constexpr int64_t value = VBYTES / 8;
};

// A row of n values in whole blocks plus one block of padding: buffers whose rows are this far
// apart never put two rows a multiple of 4 KiB apart.
template <typename T>
inline int64_t padded(int64_t n) {
  constexpr int64_t B = Block<T>::N;
  return (n + B - 1) / B * B + B;
}

// The five statistics of one image row (x, y: W * C values), blurred horizontally, into
// out[s * ld + j] for j < W * C (the rest of each out row gets values of the zero padding).
// P: scratch of NS rows of pld = padded(W * C) + 2 r C.
template <typename T>
void blur_row(const T* x, const T* y, int64_t W, int64_t C, const T* g, int r, T* P, int64_t pld, T* out,
              int64_t ld) {
  typedef typename Block<T>::V V;
  constexpr int64_t L = Block<T>::L;
  const int64_t WC = W * C, PW = (W + 2 * r) * C;
  auto put = [&](int64_t dst, T u, T v) {
    P[dst] = u, P[pld + dst] = v, P[2 * pld + dst] = u * u, P[3 * pld + dst] = v * v, P[4 * pld + dst] = u * v;
  };
  for (int64_t s = 0; s < r; ++s)  // replicate the border
    for (int64_t c = 0; c < C; ++c) {
      put(s * C + c, x[c], y[c]);
      put((W + r + s) * C + c, x[(W - 1) * C + c], y[(W - 1) * C + c]);
    }
  T* p0 = P + r * C;
#pragma GCC ivdep
  for (int64_t i = 0; i < WC; ++i) {
    const T u = x[i], v = y[i];
    p0[i] = u, p0[pld + i] = v, p0[2 * pld + i] = u * u, p0[3 * pld + i] = v * v, p0[4 * pld + i] = u * v;
  }
  for (int q = 0; q < NS; ++q) std::fill(P + q * pld + PW, P + (q + 1) * pld, T(0));
  for (int64_t j = 0; j < WC; j += Block<T>::N) {
    V acc[NS][NV] = {};
    for (int k = 0; k <= 2 * r; ++k) {
      const V w = V{} + g[k];
      for (int q = 0; q < NS; ++q) {
        const T* p = P + q * pld + j + k * C;
        for (int n = 0; n < NV; ++n) acc[q][n] = madd(w, load<V>(p + n * L), acc[q][n]);
      }
    }
    for (int q = 0; q < NS; ++q)
      for (int n = 0; n < NV; ++n) store(out + q * ld + j + n * L, acc[q][n]);
  }
}

// S, a, b and c (vectors of T) from their five blurred statistics.
template <typename T, typename U>
inline void formula(const U* m, U& S, U& A, U& Bc, U& Cc) {
  const U ux = m[0], uy = m[1], two = U{} + T(2);
  const U a1 = two * ux * uy + T(C1);
  const U a2 = two * (m[4] - ux * uy) + T(C2);
  const U b1 = ux * ux + uy * uy + T(C1);
  const U b2 = (m[2] - ux * ux) + (m[3] - uy * uy) + T(C2);
  const U ib1 = T(1) / b1, ib2 = T(1) / b2;  // two divisions, not four: they are the slow part here
  const U inv = ib1 * ib2;
  const U s = a1 * a2 * inv;
  S = s;
  // dS/dmx (through a1, a2, b1 and b2), dS/dB(x^2) (through b2), dS/dB(xy) (through a2).
  A = two * uy * (a2 - a1) * inv - two * ux * s * ib1 + two * ux * s * ib2;
  Bc = -s * ib2;
  Cc = two * a1 * inv;
}

// Rows of a band [y0, y1) shared by one or two threads: the first takes rows from the top down,
// the second from the bottom up, each claiming one row at a time from a common count, until they
// meet. Each thread blurs the rows of its own windows only once, like a static split, and both end
// together whatever slows one of them: on two cores, with static halves, either thread could take up
// to 23 % longer than the other (the one back from the Python between two calls, or the one whose
// core a neighbour shares; docs/benchmarks.md, session 40).
class TwoEnded {
  std::atomic<int64_t> claimed_{0};
  int64_t y0_ = 0, y1_ = 0, taken_[2] = {0, 0};

 public:
  void reset(int64_t y0, int64_t y1) { y0_ = y0, y1_ = y1, claimed_ = 0, taken_[0] = taken_[1] = 0; }
  // The next row of end e (0: top, 1: bottom) into row; false when the band is done.
  bool next(int e, int64_t& row) {
    if (claimed_.fetch_add(1, std::memory_order_relaxed) >= y1_ - y0_) return false;
    row = e == 0 ? y0_ + taken_[0]++ : y1_ - 1 - taken_[1]++;
    return true;
  }
};

// Forward: S, a, b, c (each H x W x C).
template <typename T>
void forward(const T* x, const T* y, int64_t H, int64_t W, int64_t C, const T* g, int r, T* S, T* A, T* Bc,
             T* Cc) {
  typedef typename Block<T>::V V;
  constexpr int64_t L = Block<T>::L, N = Block<T>::N;
  const int64_t WC = W * C, ld = padded<T>(WC), pld = ld + 2 * r * C, R = 2 * r + 1;
  // The rows one thread computes, in the order band.next(end, row) gives them: the ring holds the
  // blurred statistics of the window of the last row, and a row's window differs from it by one
  // row when the rows go one by one up or down. One function for every split: two instantiations
  // of the arithmetic could contract its products and sums into FMAs differently.
  auto rows = [&](TwoEnded& band, int end) {
    std::vector<T> P(NS * pld), ring(R * NS * ld);
    std::vector<const T*> window(R);  // the blurred rows under the window of the current row
    auto slot = [&](int64_t row) { return ring.data() + (row % R) * NS * ld; };
    int64_t lo = 0, hi = -1;  // the image rows whose blurred statistics the ring holds
    for (int64_t row; band.next(end, row);) {
      const int64_t a = std::max<int64_t>(row - r, 0), b = std::min<int64_t>(row + r, H - 1);
      for (int64_t q = a; q <= b; ++q)
        if (q < lo || q > hi) blur_row(x + q * WC, y + q * WC, W, C, g, r, P.data(), pld, slot(q), ld);
      lo = a, hi = b;
      // Once a row, not in the loop below: there the modulo was an integer division a tap and
      // a block, half of this pass's time.
      for (int k = 0; k <= 2 * r; ++k) window[k] = slot(std::min<int64_t>(std::max<int64_t>(row + k - r, 0), H - 1));
      const int64_t base = row * WC;
      for (int64_t j = 0; j < WC; j += N) {
        V m[NS][NV] = {};
        for (int k = 0; k <= 2 * r; ++k) {
          const T* h = window[k] + j;
          const V w = V{} + g[k];
          for (int q = 0; q < NS; ++q)
            for (int n = 0; n < NV; ++n) m[q][n] = madd(w, load<V>(h + q * ld + n * L), m[q][n]);
        }
        T out[4][N];
        for (int n = 0; n < NV; ++n) {
          V s, a, b, c;
          const V mn[NS] = {m[0][n], m[1][n], m[2][n], m[3][n], m[4][n]};
          formula<T>(mn, s, a, b, c);
          store(out[0] + n * L, s), store(out[1] + n * L, a), store(out[2] + n * L, b), store(out[3] + n * L, c);
        }
        const int64_t cnt = std::min<int64_t>(N, WC - j);  // the row's last block may be partial
        std::memcpy(S + base + j, out[0], cnt * sizeof(T));
        std::memcpy(A + base + j, out[1], cnt * sizeof(T));
        std::memcpy(Bc + base + j, out[2], cnt * sizeof(T));
        std::memcpy(Cc + base + j, out[3], cnt * sizeof(T));
      }
    }
  };
  // A band of rows for each pair of threads (and one for a last thread on its own), at least
  // 16 rows a thread.
  const int64_t nt = std::min<int64_t>(at::in_parallel_region() ? 1 : at::get_num_threads(), H / 16);
  if (nt < 2) {
    TwoEnded all;
    all.reset(0, H);
    rows(all, 0);
    return;
  }
  const int64_t bands = (nt + 1) / 2;
  std::vector<TwoEnded> band(bands);
  auto band_rows = [&](int64_t i) { return H * std::min<int64_t>(2 * i, nt) / nt; };  // pairs share twice the rows
  for (int64_t i = 0; i < bands; ++i) band[i].reset(band_rows(i), band_rows(i + 1));
  at::parallel_for(0, nt, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) rows(band[t / 2], static_cast<int>(t % 2));
  });
}

// The taps of image row m's vertical adjoint: row m gathers the rows t that replicate it (t = m
// inside, t <= 0 for the first row, t >= H - 1 for the last), each t the window's zero-padded
// rows; tap i reads image row offset[i] / WC with weight w[i] (t, then the window, in order).
// Returns the number of taps, under (2 r + 1)^2.
template <typename T>
inline int vadjoint_taps(int64_t H, int64_t WC, const T* g, int r, int64_t m, int64_t* offset, T* w) {
  int n = 0;
  const int64_t t0 = m == 0 ? -r : m, t1 = m == H - 1 ? H - 1 + r : m;
  for (int64_t t = t0; t <= t1; ++t)
    for (int k = 0; k <= 2 * r; ++k) {
      const int64_t src = t - k + r;
      if (src < 0 || src >= H) continue;
      offset[n] = src * WC, w[n] = g[k], ++n;
    }
  return n;
}

// Vertical adjoint of G a, G b, G c for one image row, values [j, j + NN Lanes<U>::value) into
// z[s * zld + j], from its taps (vadjoint_taps): one flat loop, whose accumulators stay in
// registers (the two nested loops with a skip kept them on the stack).
template <typename U, int NN, typename T>
inline void vadjoint_block(const T* G, const T* A, const T* Bc, const T* Cc, const int64_t* offset, const T* w,
                           int taps, int64_t j, T* z, int64_t zld) {
  constexpr int64_t L = Lanes<U>::value;
  U acc[NB][NN] = {};
  for (int i = 0; i < taps; ++i) {
    const U wv = U{} + w[i];
    const int64_t o = offset[i] + j;
    for (int n = 0; n < NN; ++n) {
      const U wg = wv * load<U>(G + o + n * L);
      acc[0][n] = madd(wg, load<U>(A + o + n * L), acc[0][n]);
      acc[1][n] = madd(wg, load<U>(Bc + o + n * L), acc[1][n]);
      acc[2][n] = madd(wg, load<U>(Cc + o + n * L), acc[2][n]);
    }
  }
  for (int q = 0; q < NB; ++q)
    for (int n = 0; n < NN; ++n) store(z + q * zld + j + n * L, acc[q][n]);
}

// Backward: dx (H x W x C) = k dS/dx applied to G (the upstream gradient of S: the adjoint is
// linear in it, so the training loss passes its weights and their factor separately) plus, with
// wl, the L1 term's gradient kl sign(x - y) wl, in the same pass over the rows (the loss's three
// passes over whole images were three regions and about 4 MB of reads and writes a 256x256 step).
// Rows are independent: the threads pull runs of them.
template <typename T>
void backward(const T* G, T k, const T* x, const T* y, const T* A, const T* Bc, const T* Cc, int64_t H, int64_t W,
              int64_t C, const T* g, int r, const T* wl, T kl, T* dx) {
  typedef typename Block<T>::V V;
  constexpr int64_t L = Block<T>::L, N = Block<T>::N;
  const int64_t WC = W * C, EW = (W + 2 * r) * C, eld = padded<T>(EW), zld = eld + 2 * r * C;
  dynamic_for(H, 8, [&](int64_t m0, int64_t m1) {
    // z: the vertical adjoint of a row with 2r zero pixels each side; e: its horizontal adjoint
    // over the row and r pixels each side (pixel u of e is image pixel u - r).
    std::vector<T> z(NB * zld, T(0)), e(NB * eld), tw((2 * r + 1) * (2 * r + 1));
    std::vector<int64_t> to(tw.size());
    for (int64_t m = m0; m < m1; ++m) {
      T* zm = z.data() + 2 * r * C;
      const int taps = vadjoint_taps(H, WC, g, r, m, to.data(), tw.data());
      int64_t j = 0;
      for (; j + N <= WC; j += N) vadjoint_block<V, NV>(G, A, Bc, Cc, to.data(), tw.data(), taps, j, zm, zld);
      for (; j < WC; ++j) vadjoint_block<T, 1>(G, A, Bc, Cc, to.data(), tw.data(), taps, j, zm, zld);
      for (int64_t i = 0; i < EW; i += N) {
        V acc[NB][NV] = {};
        for (int kk = 0; kk <= 2 * r; ++kk) {
          const V w = V{} + g[kk];
          for (int q = 0; q < NB; ++q) {
            const T* zs = z.data() + q * zld + (2 * r - kk) * C + i;
            for (int n = 0; n < NV; ++n) acc[q][n] = madd(w, load<V>(zs + n * L), acc[q][n]);
          }
        }
        for (int q = 0; q < NB; ++q)
          for (int n = 0; n < NV; ++n) store(e.data() + q * eld + i + n * L, acc[q][n]);
      }
      // Fold the padding's share onto the edge pixels.
      for (int q = 0; q < NB; ++q) {
        T* es = e.data() + q * eld;
        for (int64_t u = 0; u < r; ++u)
          for (int64_t c = 0; c < C; ++c) {
            es[r * C + c] += es[u * C + c];
            es[(W - 1 + r) * C + c] += es[(W + r + u) * C + c];
          }
      }
      // The chain rule through x, x^2 and xy, then the L1 term (torch's sign: 0 where x == y; a
      // vector select: a sign on real images is a misprediction a value as a branch).
      const T* pa = e.data() + r * C;
      const T* pb = pa + eld;
      const T* pc = pb + eld;
      const T *xm = x + m * WC, *ym = y + m * WC, *wm = wl == nullptr ? nullptr : wl + m * WC;
      T* dm = dx + m * WC;
      const V kv = V{} + k, klv = V{} + kl, two = V{} + T(2), zero{};
      int64_t i = 0;
      for (; i + L <= WC; i += L) {
        const V xv = load<V>(xm + i), yv = load<V>(ym + i);
        V out = kv * (load<V>(pa + i) + two * xv * load<V>(pb + i) + yv * load<V>(pc + i));
        if (wm != nullptr) {
          const V d = xv - yv;
          out += (d > zero ? klv : (d < zero ? -klv : zero)) * load<V>(wm + i);
        }
        store(dm + i, out);
      }
      for (; i < WC; ++i) {
        T out = k * (pa[i] + T(2) * xm[i] * pb[i] + ym[i] * pc[i]);
        if (wm != nullptr) {
          const T d = xm[i] - ym[i];
          out += (d > T(0) ? kl : (d < T(0) ? -kl : T(0))) * wm[i];
        }
        dm[i] = out;
      }
    }
  });
}

}  // namespace ssim
}  // namespace dibrgs
