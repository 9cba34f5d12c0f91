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
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <memory>
#include <vector>

namespace dibrgs {
namespace ssim {

constexpr double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;
constexpr int NS = 5;  // local statistics: x, y, x^2, y^2, xy

// Rows of the five horizontally blurred statistics (each H x W*C).
template <typename T>
void blur_rows(const T* x, const T* y, int64_t H, int64_t W, int64_t C, const T* g, int r, T* h) {
  const int64_t WC = W * C, plane = H * WC, PW = (W + 2 * r) * C;
  at::parallel_for(0, H, 8, [&](int64_t y0, int64_t y1) {
    std::vector<T> px(PW), py(PW);
    for (int64_t row = y0; row < y1; ++row) {
      const T* xr = x + row * WC;
      const T* yr = y + row * WC;
      for (int64_t s = -r; s < W + r; ++s) {  // replicate the border
        const int64_t src = std::min<int64_t>(std::max<int64_t>(s, 0), W - 1) * C;
        for (int64_t c = 0; c < C; ++c) px[(s + r) * C + c] = xr[src + c], py[(s + r) * C + c] = yr[src + c];
      }
      T* o[NS];
      for (int s = 0; s < NS; ++s) o[s] = h + s * plane + row * WC;
      for (int64_t j = 0; j < WC; ++j) o[0][j] = o[1][j] = o[2][j] = o[3][j] = o[4][j] = T(0);
      for (int k = 0; k <= 2 * r; ++k) {
        const T w = g[k];
        const T* a = px.data() + k * C;
        const T* b = py.data() + k * C;
#pragma GCC ivdep
        for (int64_t j = 0; j < WC; ++j) {
          const T u = a[j], v = b[j];
          o[0][j] += w * u;
          o[1][j] += w * v;
          o[2][j] += w * u * u;
          o[3][j] += w * v * v;
          o[4][j] += w * u * v;
        }
      }
    }
  });
}

// Forward: S, a, b, c (each H x W x C) from the horizontally blurred rows h.
template <typename T>
void forward(const T* x, const T* y, int64_t H, int64_t W, int64_t C, const T* g, int r, T* S, T* A, T* Bc,
             T* Cc) {
  const int64_t WC = W * C, plane = H * WC;
  // Uninitialised (every element is written first): zero-filling it would be a serial pass.
  std::unique_ptr<T[]> hbuf(new T[NS * plane]);
  const T* const h = hbuf.get();
  blur_rows(x, y, H, W, C, g, r, hbuf.get());
  at::parallel_for(0, H, 8, [&](int64_t y0, int64_t y1) {
    std::vector<T> m(NS * WC);
    for (int64_t row = y0; row < y1; ++row) {
      std::fill(m.begin(), m.end(), T(0));
      for (int k = 0; k <= 2 * r; ++k) {
        const int64_t src = std::min<int64_t>(std::max<int64_t>(row + k - r, 0), H - 1);
        const T w = g[k];
        for (int s = 0; s < NS; ++s) {
          const T* a = h + s * plane + src * WC;
          T* o = m.data() + s * WC;
#pragma GCC ivdep
          for (int64_t j = 0; j < WC; ++j) o[j] += w * a[j];
        }
      }
      const T* mx = m.data();
      const T* my = mx + WC;
      const T* sxx = my + WC;
      const T* syy = sxx + WC;
      const T* sxy = syy + WC;
      const int64_t base = row * WC;
#pragma GCC ivdep
      for (int64_t j = 0; j < WC; ++j) {
        const T ux = mx[j], uy = my[j];
        const T a1 = T(2) * ux * uy + T(C1);
        const T a2 = T(2) * (sxy[j] - ux * uy) + T(C2);
        const T b1 = ux * ux + uy * uy + T(C1);
        const T b2 = (sxx[j] - ux * ux) + (syy[j] - uy * uy) + T(C2);
        const T inv = T(1) / (b1 * b2);
        const T s = a1 * a2 * inv;
        S[base + j] = s;
        // dS/dmx (through a1, a2, b1 and b2), dS/dB(x^2) (through b2), dS/dB(xy) (through a2).
        A[base + j] = T(2) * uy * (a2 - a1) * inv - T(2) * ux * s / b1 + T(2) * ux * s / b2;
        Bc[base + j] = -s / b2;
        Cc[base + j] = T(2) * a1 * inv;
      }
    }
  });
}

// Backward: dx (H x W x C) from the upstream gradient G of S.
template <typename T>
void backward(const T* G, const T* x, const T* y, const T* A, const T* Bc, const T* Cc, int64_t H, int64_t W,
              int64_t C, const T* g, int r, T* dx) {
  constexpr int NB = 3;
  const int64_t WC = W * C, plane = H * WC;
  // Vertical adjoint of G a, G b, G c: row m gathers the rows t that replicate it (t = m inside,
  // t <= 0 for the first row, t >= H - 1 for the last), each t the window's zero-padded rows.
  std::unique_ptr<T[]> vbuf(new T[NB * plane]);  // uninitialised: each row is zeroed by its thread
  T* const v = vbuf.get();
  at::parallel_for(0, H, 8, [&](int64_t m0, int64_t m1) {
    for (int64_t m = m0; m < m1; ++m) {
      T* o[NB];
      for (int s = 0; s < NB; ++s) {
        o[s] = v + s * plane + m * WC;
        std::fill(o[s], o[s] + WC, T(0));
      }
      const int64_t t0 = m == 0 ? -r : m, t1 = m == H - 1 ? H - 1 + r : m;
      for (int64_t t = t0; t <= t1; ++t)
        for (int k = 0; k <= 2 * r; ++k) {
          const int64_t src = t - k + r;
          if (src < 0 || src >= H) continue;
          const T w = g[k];
          const T* gr = G + src * WC;
          const T* ar = A + src * WC;
          const T* br = Bc + src * WC;
          const T* cr = Cc + src * WC;
#pragma GCC ivdep
          for (int64_t j = 0; j < WC; ++j) {
            const T wg = w * gr[j];
            o[0][j] += wg * ar[j];
            o[1][j] += wg * br[j];
            o[2][j] += wg * cr[j];
          }
        }
    }
  });
  // Horizontal adjoint on each row (zero-padded by 2r pixels, folded at the edges), then the
  // chain rule through x, x^2 and xy.
  at::parallel_for(0, H, 8, [&](int64_t y0, int64_t y1) {
    const int64_t ZW = (W + 4 * r) * C, EW = (W + 2 * r) * C;
    std::vector<T> z(NB * ZW, T(0)), e(NB * EW);
    for (int64_t row = y0; row < y1; ++row) {
      for (int s = 0; s < NB; ++s) {
        std::copy(v + s * plane + row * WC, v + s * plane + (row + 1) * WC, z.data() + s * ZW + 2 * r * C);
        T* es = e.data() + s * EW;
        std::fill(es, es + EW, T(0));
        for (int k = 0; k <= 2 * r; ++k) {
          const T w = g[k];
          const T* zs = z.data() + s * ZW + (2 * r - k) * C;
#pragma GCC ivdep
          for (int64_t j = 0; j < EW; ++j) es[j] += w * zs[j];
        }
        // Fold the padding's share onto the edge pixels (pixel u of e is image pixel u - r).
        for (int64_t u = 0; u < r; ++u)
          for (int64_t c = 0; c < C; ++c) {
            es[r * C + c] += es[u * C + c];
            es[(W - 1 + r) * C + c] += es[(W + r + u) * C + c];
          }
      }
      const T* pa = e.data() + r * C;
      const T* pb = pa + EW;
      const T* pc = pb + EW;
      const int64_t base = row * WC;
#pragma GCC ivdep
      for (int64_t j = 0; j < WC; ++j) dx[base + j] = pa[j] + T(2) * x[base + j] * pb[j] + y[base + j] * pc[j];
    }
  });
}

}  // namespace ssim
}  // namespace dibrgs
