// Neural Gaussians spawned from the decoder outputs of the visible anchors (models/spawn.py),
// forward and backward, in one parallel pass over the anchors. In torch this step is about
// twenty small operators (a nonzero, five gathers, sigmoid, quaternion normalisation, their
// backward scatters into zero-filled tensors), about 4 ms a 256x256 DIBR-GS iteration, most of
// it dispatch that does not split over threads (issue 17).
//
// Row (a, j) is offset j of visible anchor a; it is kept when its opacity nop[a k + j] > 0, in
// row order, so the kept rows of one anchor are contiguous and start at start[a]; the anchor's
// scaling is scal = exp(clamp(log_scal[a], -30, 20)) (6 values; the clamp keeps exp finite):
//   mean  = anchor[a] + offset[a, j] * scal[a, 0:3]
//   scale = scal[a, 3:6] * sigmoid(cov[a, 7 j + 0..2])
//   quat  = cov[a, 7 j + 3..6] / |.|   (1, 0, 0, 0) when |.| <= 1e-12, w x y z
//   opacity = nop[a k + j],  colour = color[a, 3 j + 0..2]
// The backward owns one anchor a task, so its sums over the anchor's rows need no atomics.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "chunks.h"

namespace dibrgs {
namespace spawn {

constexpr double QUAT_EPS = 1e-12;  // models/spawn.py's threshold of a zero quaternion

template <typename T>
inline T sigmoid(T x) {
  return T(1) / (T(1) + std::exp(-x));
}

constexpr double LOG_SCALING_MIN = -30.0, LOG_SCALING_MAX = 20.0;  // models/spawn.py's clamp

// An anchor's scaling from its log (6 values), and whether each log is inside the clamp (where
// its gradient passes; outside it is 0, not 0 times the gradient, which could be inf).
template <typename T>
inline void activate(const T* l, T* s, bool* inside) {
  for (int d = 0; d < 6; ++d) {
    inside[d] = l[d] >= T(LOG_SCALING_MIN) && l[d] <= T(LOG_SCALING_MAX);
    s[d] = std::exp(std::min(std::max(l[d], T(LOG_SCALING_MIN)), T(LOG_SCALING_MAX)));
  }
}

// |q| of a quaternion in double: its squares overflow float32 from |q| ~ 1.8e19.
template <typename T>
inline double quat_norm(const T* q) {
  double s = 0;
  for (int d = 0; d < 4; ++d) s += static_cast<double>(q[d]) * q[d];
  return std::sqrt(s);
}

// start (M + 1): first kept row of each anchor, and selected (M k): whether each row is kept;
// returns the number of kept rows.
template <typename T>
int64_t count(const T* nop, int64_t M, int64_t k, int64_t* start, bool* selected) {
  at::parallel_for(0, M, 1024, [&](int64_t b, int64_t e) {
    for (int64_t a = b; a < e; ++a) {
      int64_t n = 0;
      for (int64_t j = 0; j < k; ++j) {
        selected[a * k + j] = nop[a * k + j] > T(0);
        n += selected[a * k + j];
      }
      start[a + 1] = n;
    }
  });
  start[0] = 0;
  for (int64_t a = 0; a < M; ++a) start[a + 1] += start[a];
  return start[M];
}

template <typename T>
void forward(const T* nop, const T* color, const T* cov, const T* anchor, const T* log_scal, const T* offset,
             int64_t M, int64_t k, const int64_t* start, T* means, T* quats, T* scales, T* opac, T* colors) {
  dynamic_for(M, 128, [&](int64_t b, int64_t e) {
    for (int64_t a = b; a < e; ++a) {
      int64_t r = start[a];
      const T* an = anchor + 3 * a;
      T s[6];
      bool inside[6];
      activate(log_scal + 6 * a, s, inside);
      for (int64_t j = 0; j < k; ++j) {
        if (!(nop[a * k + j] > T(0))) continue;
        const T* o = offset + (a * k + j) * 3;
        const T* c = cov + a * 7 * k + 7 * j;
        for (int d = 0; d < 3; ++d) means[3 * r + d] = an[d] + o[d] * s[d];
        for (int d = 0; d < 3; ++d) scales[3 * r + d] = s[3 + d] * sigmoid(c[d]);
        const double qn = quat_norm(c + 3);
        if (qn > QUAT_EPS) {
          for (int d = 0; d < 4; ++d) quats[4 * r + d] = static_cast<T>(c[3 + d] / qn);
        } else {
          quats[4 * r] = T(1), quats[4 * r + 1] = quats[4 * r + 2] = quats[4 * r + 3] = T(0);
        }
        opac[r] = nop[a * k + j];
        for (int d = 0; d < 3; ++d) colors[3 * r + d] = color[a * 3 * k + 3 * j + d];
        ++r;
      }
    }
  });
}

// Gradients of the inputs from those of the outputs (g*: rows as the forward's; gcolors' rows gcs
// values apart). Every entry of the outputs is written (zero where a row was not kept).
template <typename T>
void backward(const T* gmeans, const T* gquats, const T* gscales, const T* gopac, const T* gcolors, int64_t gcs,
              const T* nop, const T* cov, const T* log_scal, const T* offset, int64_t M, int64_t k,
              const int64_t* start, T* dnop, T* dcolor, T* dcov, T* danchor, T* dlog_scal, T* doffset) {
  dynamic_for(M, 128, [&](int64_t b, int64_t e) {
    for (int64_t a = b; a < e; ++a) {
      int64_t r = start[a];
      T s[6];
      bool inside[6];
      activate(log_scal + 6 * a, s, inside);
      T ga[3] = {0, 0, 0}, gs[6] = {0, 0, 0, 0, 0, 0};
      for (int64_t j = 0; j < k; ++j) {
        const int64_t row = a * k + j;
        const T* o = offset + row * 3;
        const T* c = cov + a * 7 * k + 7 * j;
        T* dc = dcov + a * 7 * k + 7 * j;
        T* dcl = dcolor + a * 3 * k + 3 * j;
        T* dof = doffset + row * 3;
        if (!(nop[row] > T(0))) {
          dnop[row] = T(0);
          for (int d = 0; d < 7; ++d) dc[d] = T(0);
          for (int d = 0; d < 3; ++d) dcl[d] = T(0), dof[d] = T(0);
          continue;
        }
        const T* gm = gmeans + 3 * r;
        for (int d = 0; d < 3; ++d) {
          ga[d] += gm[d];
          dof[d] = gm[d] * s[d];
          gs[d] += gm[d] * o[d];
        }
        const T* gsc = gscales + 3 * r;
        for (int d = 0; d < 3; ++d) {
          const T sg = sigmoid(c[d]);
          gs[3 + d] += gsc[d] * sg;
          dc[d] = gsc[d] * s[3 + d] * sg * (T(1) - sg);
        }
        const double qn = quat_norm(c + 3);
        if (qn > QUAT_EPS) {
          const T* gq = gquats + 4 * r;
          double dot = 0;  // gq . q / |q|
          for (int d = 0; d < 4; ++d) dot += static_cast<double>(gq[d]) * (c[3 + d] / qn);
          for (int d = 0; d < 4; ++d) dc[3 + d] = static_cast<T>((gq[d] - c[3 + d] / qn * dot) / qn);
        } else {
          for (int d = 0; d < 4; ++d) dc[3 + d] = T(0);
        }
        dnop[row] = gopac[r];
        for (int d = 0; d < 3; ++d) dcl[d] = gcolors[gcs * r + d];
        ++r;
      }
      for (int d = 0; d < 3; ++d) danchor[3 * a + d] = ga[d];
      for (int d = 0; d < 6; ++d) dlog_scal[6 * a + d] = inside[d] ? gs[d] * s[d] : T(0);  // d exp = exp
    }
  });
}

// Which of N anchors can put a Gaussian into a W x H image (models/scaffold.py visible_anchors,
// frustum culling): in front of the near plane, and the projection grown by the farthest its
// Gaussians reach (largest |offset| times the largest offset scaling, plus 3 of the largest
// Gaussian scale) overlaps the image. cam: w2c rows R (9) and t (3), then fx, fy, cx, cy;
// log_scaling (N, 6) clamped to [-30, 20] before exp as anchor_scaling does. In double; a
// non-finite anchor is not visible. One parallel pass instead of about twenty torch operators
// on N values, which do not split over threads.
template <typename T>
void visible(const T* anchor, const T* offset, const T* log_scaling, int64_t N, int64_t k, const double* cam,
             int64_t W, int64_t H, double near, bool* out) {
  at::parallel_for(0, N, 2048, [&](int64_t b, int64_t e) {
    for (int64_t a = b; a < e; ++a) {
      const T* p = anchor + 3 * a;
      double x[3];
      for (int i = 0; i < 3; ++i)
        x[i] = cam[3 * i] * p[0] + cam[3 * i + 1] * p[1] + cam[3 * i + 2] * p[2] + cam[9 + i];
      // The largest of exp(clamp(l)) is exp(clamp(largest l)): two exps, not six.
      const T* l = log_scaling + 6 * a;
      auto act = [](double v) { return std::exp(std::min(std::max(v, LOG_SCALING_MIN), LOG_SCALING_MAX)); };
      const double so = act(std::max({l[0], l[1], l[2]})), sg = act(std::max({l[3], l[4], l[5]}));
      double off = 0;
      for (int64_t i = 0; i < 3 * k; ++i) off = std::max(off, std::fabs(static_cast<double>(offset[3 * k * a + i])));
      const double reach = off * so + 3.0 * sg, zs = std::max(x[2], near);
      const double u = cam[12] * x[0] / zs + cam[14], v = cam[13] * x[1] / zs + cam[15];
      const double r = std::fabs(cam[12]) * reach / zs;
      out[a] = x[2] > near && std::isfinite(u) && std::isfinite(v) && u + r > 0 && u - r < W && v + r > 0 &&
               v - r < H;
    }
  });
}

}  // namespace spawn
}  // namespace dibrgs
