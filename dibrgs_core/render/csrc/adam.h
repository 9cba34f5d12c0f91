// One Adam step over many parameter tensors in one parallel loop (training/optim.py).
// torch's CPU Adam runs about ten operators per tensor; a Scaffold model has nineteen
// tensors of a few dozen to 84,000 elements, so the step is mostly dispatch and it does
// not split over threads. Here all tensors' elements, end to end, are one parallel loop
// (chunks.h). The arithmetic is torch's (torch/optim/adam.py, single-tensor path), in
// float32 with the same order of operations:
//   decoupled:  p *= 1 - lr wd            else: g += wd p   (when wd != 0)
//   m = lerp(m, g, 1 - b1)   v = v b2 + (1 - b2) g^2
//   p -= (lr / (1 - b1^t)) m / (sqrt(v) / sqrt(1 - b2^t) + eps)
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

#include "chunks.h"

namespace dibrgs {
namespace adam {

// Per tensor: its pointers, length and the step's scalars (float, as torch casts them).
struct Slot {
  float* p;
  const float* g;
  float* m;
  float* v;
  int64_t n;
  float decay;      // 1 - lr wd (decoupled) or 1
  float l2;         // wd (coupled) or 0
  float one_m_b1;   // 1 - b1
  float b2;
  float one_m_b2;   // 1 - b2
  float bc2_sqrt;   // sqrt(1 - b2^t)
  float eps;
  float neg_step;   // -lr / (1 - b1^t)
};

// torch's lerp(self, end, w) for a weight below one half: self + w (end - self).
inline float lerp_small(float a, float b, float w) { return w < 0.5f ? a + w * (b - a) : b - (b - a) * (1.0f - w); }

inline void run(const std::vector<Slot>& slots, int64_t grain) {
  std::vector<int64_t> lengths;
  for (const Slot& s : slots) lengths.push_back(s.n);
  parallel_chunks(lengths, grain, [&](int64_t t, int64_t i0, int64_t i1) {
    const Slot& s = slots[t];
    for (int64_t i = i0; i < i1; ++i) {
      float p = s.p[i];
      float g = s.g[i];
      if (s.decay != 1.0f) p = p * s.decay;
      if (s.l2 != 0.0f) g = g + s.l2 * p;
      const float m = lerp_small(s.m[i], g, s.one_m_b1);
      const float v = s.v[i] * s.b2 + s.one_m_b2 * g * g;
      const float denom = std::sqrt(v) / s.bc2_sqrt + s.eps;
      s.m[i] = m;
      s.v[i] = v;
      s.p[i] = p + s.neg_step * m / denom;
    }
  });
}

}  // namespace adam
}  // namespace dibrgs
