// Z-buffer of planar convex quads (geometry/surface.py rasterise_depth, the same rules): the
// depth map of a height field's mesh for the pseudo views. The numpy version spends about 45 ms a
// 256x256 view on ~70,000 quads in array temporaries per row and per pixel; here a quad is set up
// once and its rows and pixels are a plain loop.
//
// Rules (shared with the numpy version, which tests compare against): a quad is left out when a
// corner is not finite or not in front of the camera (z <= 1e-9 of the largest finite |z|), when
// it is seen edge-on, or when its pixel-centre rows or columns miss the image; each row's span
// runs between the crossings of the quad's edges with the row's centre line, both ends included,
// so quads that share an edge leave no gap; an edge's crossing is computed from its lower end (v,
// then u), so both quads get the same number; 1/z is affine in the image plane, fitted through
// corners 0, 1, 2; the nearest quad wins. OpenCV camera axes, pixel centres at +0.5.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace dibrgs {
namespace zbuffer {

struct Quad {
  double A, B, C;                        // 1/z = A u + B v + C
  double lu[4], lv[4], hv[4], slope[4];  // per edge: lower end, upper v (-inf: horizontal), du/dv
  int64_t y0, y1;                        // first and last pixel row (inclusive)
};

// quads: (3, 4, Q) corner coordinates, axis-major as numpy's (3, 4, Q) array; M (3x3, row-major)
// and b (3) take them to camera axes; K (3x3, row-major). Writes depth (H*W), 0 where no quad
// covers a pixel centre.
inline void rasterise(const double* quads, int64_t Q, const double* M, const double* b, const double* K, int64_t H,
                      int64_t W, double* depth) {
  const double inf = std::numeric_limits<double>::infinity();
  auto corner = [&](int64_t axis, int64_t c, int64_t q) { return quads[(axis * 4 + c) * Q + q]; };
  auto cam = [&](int64_t k, int64_t c, int64_t q) {
    return M[3 * k] * corner(0, c, q) + M[3 * k + 1] * corner(1, c, q) + M[3 * k + 2] * corner(2, c, q) + b[k];
  };
  double zabs = 0.0;
  for (int64_t q = 0; q < Q; ++q)
    for (int c = 0; c < 4; ++c) {
      const double z = std::fabs(cam(2, c, q));
      if (std::isfinite(z)) zabs = std::max(zabs, z);
    }
  const double znear = 1e-9 * std::max(zabs, 1e-300);

  std::vector<Quad> kept;
  kept.reserve(Q);
  for (int64_t q = 0; q < Q; ++q) {
    double u[4], v[4], iz[4];
    bool front = true;
    for (int c = 0; c < 4; ++c) {
      const double x = cam(0, c, q), y = cam(1, c, q), z = cam(2, c, q);
      front = front && z > znear && std::isfinite(x) && std::isfinite(y);  // a NaN corner drops its quad only
      iz[c] = 1.0 / z;
      u[c] = (K[0] * x + K[1] * y) * iz[c] + K[2];
      v[c] = K[4] * y * iz[c] + K[5];
    }
    if (!front) continue;
    const double vmin = std::min(std::min(v[0], v[1]), std::min(v[2], v[3]));
    const double vmax = std::max(std::max(v[0], v[1]), std::max(v[2], v[3]));
    const double umin = std::min(std::min(u[0], u[1]), std::min(u[2], u[3]));
    const double umax = std::max(std::max(u[0], u[1]), std::max(u[2], u[3]));
    const int64_t y0 = static_cast<int64_t>(std::clamp(std::ceil(vmin - 0.5), 0.0, static_cast<double>(H)));
    const int64_t y1 = static_cast<int64_t>(std::clamp(std::floor(vmax - 0.5), -1.0, static_cast<double>(H - 1)));
    const double du1 = u[1] - u[0], dv1 = v[1] - v[0], dw1 = iz[1] - iz[0];
    const double du2 = u[2] - u[0], dv2 = v[2] - v[0], dw2 = iz[2] - iz[0];
    const double det = du1 * dv2 - du2 * dv1;
    const double span = std::fabs(du1) + std::fabs(dv1) + std::fabs(du2) + std::fabs(dv2);
    if (y1 < y0 || umax < 0.0 || umin > static_cast<double>(W) || !(std::fabs(det) > 1e-12 * span * span)) continue;
    Quad t;
    t.A = (dw1 * dv2 - dw2 * dv1) / det;
    t.B = (du1 * dw2 - du2 * dw1) / det;
    t.C = iz[0] - t.A * u[0] - t.B * v[0];
    for (int e = 0; e < 4; ++e) {
      const int f = (e + 1) % 4;
      const bool swap = v[f] < v[e] || (v[f] == v[e] && u[f] < u[e]);
      const double lu = swap ? u[f] : u[e], lv = swap ? v[f] : v[e];
      const double hu = swap ? u[e] : u[f], hv = swap ? v[e] : v[f];
      t.lu[e] = lu;
      t.lv[e] = lv;
      t.hv[e] = hv > lv ? hv : -inf;
      t.slope[e] = hv > lv ? (hu - lu) / (hv - lv) : 0.0;
    }
    t.y0 = y0;
    t.y1 = y1;
    kept.push_back(t);
  }

  // Rows r0..r1-1 of quad t into depth.
  auto draw = [&](const Quad& t, int64_t r0, int64_t r1) {
    for (int64_t y = std::max(t.y0, r0); y <= std::min(t.y1, r1 - 1); ++y) {
      const double yc = static_cast<double>(y) + 0.5;
      double lo = inf, hi = -inf;
      for (int e = 0; e < 4; ++e) {
        if (t.lv[e] <= yc && yc <= t.hv[e]) {
          const double x = t.lu[e] + (yc - t.lv[e]) * t.slope[e];
          lo = std::min(lo, x);
          hi = std::max(hi, x);
        }
      }
      if (!(lo <= hi)) continue;
      const int64_t x0 = static_cast<int64_t>(std::clamp(std::ceil(lo - 0.5), 0.0, static_cast<double>(W)));
      const int64_t x1 = static_cast<int64_t>(std::clamp(std::floor(hi - 0.5), -1.0, static_cast<double>(W - 1)));
      double* row = depth + y * W;
      const double base = t.B * yc + t.C;
      for (int64_t x = x0; x <= x1; ++x) {
        const double iz = t.A * (static_cast<double>(x) + 0.5) + base;
        if (iz > 0.0) row[x] = std::min(row[x], 1.0 / iz);
      }
    }
  };

  // Bands of rows, one a task, each with the quads that reach it (a quad spans a few rows): no
  // two tasks write the same pixel.
  std::fill(depth, depth + H * W, inf);
  const int64_t band = 16, nb = (H + band - 1) / band;
  std::vector<int64_t> start(nb + 1, 0);
  for (const Quad& t : kept)
    for (int64_t k = t.y0 / band; k <= t.y1 / band; ++k) ++start[k + 1];
  for (int64_t k = 0; k < nb; ++k) start[k + 1] += start[k];
  std::vector<int64_t> order(start[nb]);
  {
    std::vector<int64_t> next(start.begin(), start.end() - 1);
    for (int64_t i = 0; i < static_cast<int64_t>(kept.size()); ++i)
      for (int64_t k = kept[i].y0 / band; k <= kept[i].y1 / band; ++k) order[next[k]++] = i;
  }
  at::parallel_for(0, nb, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t k = b0; k < b1; ++k) {
      const int64_t r0 = k * band, r1 = std::min(H, r0 + band);
      for (int64_t j = start[k]; j < start[k + 1]; ++j) draw(kept[order[j]], r0, r1);
    }
  });
  for (int64_t i = 0; i < H * W; ++i)
    if (!std::isfinite(depth[i])) depth[i] = 0.0;
}

}  // namespace zbuffer
}  // namespace dibrgs
