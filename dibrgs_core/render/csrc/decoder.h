// The decoder of the neural Gaussians (models/decoder.py), forward and backward, for the M
// visible anchors of a view: the IBR fusion, the decoders' input and their MLP heads.
//   fused  f = f_s + sigmoid(v Wmod^T + bmod) * (v Wref^T + bref)     (f = f_s without fusion)
//   input  x = [f, view / dist, dist / dist_scale],  view = anchor - centre,  dist = max(|view|, 1e-8)
//   head h hidden = relu(x W1^T + b1),  out = act(hidden W2^T + b2)
//          act: NONE, TANH (d = 1 - out^2), SIGMOID (d = out (1 - out))
// In torch this is about 60 small operators and autograd nodes a step whose matrix products (a
// few thousand rows, 32 to 70 columns) split badly over two threads (issue 17). Here the rows are
// cut into one block a thread; a block runs its matrix products through ATen (one thread inside
// the parallel region) and the elementwise steps in the same pass; the weight gradients are
// summed over the blocks at the end (so they differ from torch's in the last bits).
#pragma once

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace dibrgs {
namespace decoder {

enum Act : int64_t { NONE = 0, TANH = 1, SIGMOID = 2 };

constexpr double DIST_EPS = 1e-8;  // models/decoder.py clamps the camera distance at this

// Fewer rows than this a block cost more in the fork and the weight-gradient sums than they save.
constexpr int64_t MIN_BLOCK_ROWS = 256;

inline int64_t blocks(int64_t M) {
  if (at::in_parallel_region()) return 1;
  return std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), M / MIN_BLOCK_ROWS));
}

}  // namespace decoder
}  // namespace dibrgs

// MKL's per-thread thread count (its C interface; weak: absent from a torch built without MKL).
extern "C" int MKL_Set_Num_Threads_Local(int) __attribute__((weak));

namespace dibrgs {
namespace decoder {

// MKL on one thread for this thread while alive, inside a parallel region. Left to itself, MKL
// runs a product called from inside an OpenMP region on one thread but by a slower path for a
// transposed left factor (the weight gradients' g^T h): 26-78 % slower a product on 2 cores
// (docs/benchmarks.md, session 39); told it has one thread, as fast as on one thread outside.
class SerialMkl {
  int prev_ = 0;
  bool set_ = false;

 public:
  SerialMkl() {
    if (MKL_Set_Num_Threads_Local != nullptr && at::in_parallel_region()) {
      prev_ = MKL_Set_Num_Threads_Local(1);
      set_ = true;
    }
  }
  ~SerialMkl() {
    if (set_) MKL_Set_Num_Threads_Local(prev_);  // 0: back to MKL's global count
  }
  SerialMkl(const SerialMkl&) = delete;
  SerialMkl& operator=(const SerialMkl&) = delete;
};

// Runs fn(block, first row, rows) for each of nb blocks of M rows, one block a thread.
template <typename F>
void for_blocks(int64_t M, int64_t nb, F&& fn) {
  const int64_t rows = (M + nb - 1) / nb;
  at::parallel_for(0, nb, 1, [&](int64_t b0, int64_t b1) {
    at::AutoDispatchBelowADInplaceOrView guard;  // on every thread: the guard is thread-local
    const SerialMkl one_mkl_thread;
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t r0 = std::min(M, b * rows), n = std::min(M, r0 + rows) - r0;
      if (n > 0) fn(b, r0, n);
    }
  });
}

// The layers: IBR fusion (absent when Wref is undefined) and the heads.
struct Weights {
  at::Tensor Wref, bref, Wmod, bmod;
  std::vector<at::Tensor> W1, b1, W2, b2;
  std::vector<Act> acts;
  bool fusion() const { return Wref.defined(); }
};

// What the forward keeps for the backward (rows of all anchors).
struct Saved {
  at::Tensor x, dist, gate, ref;  // gate, ref: sigmoid(v Wmod^T + bmod), v Wref^T + bref (fusion only)
  std::vector<at::Tensor> hidden, out;
};

// x rows: [f_s (+ gate * ref), view / dist, dist / dist_scale]; dist kept.
template <typename T>
void input_rows(const T* feat, const T* gate, const T* ref, const T* anchor, const T* centre, double dist_scale,
                T* x, T* dist, int64_t n, int64_t F) {
  const int64_t D = F + 4;
  for (int64_t r = 0; r < n; ++r) {
    T* xr = x + r * D;
    const T* fr = feat + r * F;
    if (gate != nullptr) {
      const T *gr = gate + r * F, *er = ref + r * F;
      for (int64_t j = 0; j < F; ++j) xr[j] = fr[j] + gr[j] * er[j];
    } else {
      for (int64_t j = 0; j < F; ++j) xr[j] = fr[j];
    }
    T v[3];
    double s = 0;
    for (int d = 0; d < 3; ++d) {
      v[d] = anchor[r * 3 + d] - centre[d];
      s += static_cast<double>(v[d]) * v[d];
    }
    const T len = std::max(static_cast<T>(std::sqrt(s)), static_cast<T>(DIST_EPS));
    for (int d = 0; d < 3; ++d) xr[F + d] = v[d] / len;
    xr[F + 3] = len / static_cast<T>(dist_scale);
    dist[r] = len;
  }
}

// y (n, C) += b (C), then max(y, 0) when relu. addmm adds a bias by copying it into every row
// before the product, a pass that cost as much as a third of the products (strided broadcast
// copies of 10-70 columns); here it is one pass with the ReLU.
template <typename T>
void add_bias(T* y, const T* b, int64_t n, int64_t C, bool relu) {
  for (int64_t r = 0; r < n; ++r) {
    T* yr = y + r * C;
    if (relu)
      for (int64_t c = 0; c < C; ++c) yr[c] = std::max(yr[c] + b[c], T(0));
    else
      for (int64_t c = 0; c < C; ++c) yr[c] += b[c];
  }
}

// gz (n, O) = g * act'(out) and its column sums added to db2 (O). Without an activation gz is g
// itself: the caller passes gz == g (out unread), and only the sums are taken.
template <typename T>
void output_grad(const T* g, const T* out, T* gz, T* db2, int64_t n, int64_t O, Act act) {
  for (int64_t r = 0; r < n; ++r) {
    const T *gr = g + r * O, *yr = out + r * O;
    T* zr = gz + r * O;
    if (act == TANH)
      for (int64_t o = 0; o < O; ++o) zr[o] = gr[o] * (T(1) - yr[o] * yr[o]);
    else if (act == SIGMOID)
      for (int64_t o = 0; o < O; ++o) zr[o] = gr[o] * yr[o] * (T(1) - yr[o]);
    else if (zr != gr)
      for (int64_t o = 0; o < O; ++o) zr[o] = gr[o];
    for (int64_t o = 0; o < O; ++o) db2[o] += zr[o];
  }
}

// gh (n, H) zeroed where the ReLU was off, its column sums added to db1 (H).
template <typename T>
void relu_grad(T* gh, const T* hidden, T* db1, int64_t n, int64_t H) {
  for (int64_t r = 0; r < n; ++r) {
    T* gr = gh + r * H;
    const T* hr = hidden + r * H;
    for (int64_t j = 0; j < H; ++j) {
      gr[j] = hr[j] > T(0) ? gr[j] : T(0);
      db1[j] += gr[j];
    }
  }
}

// From dx (n, D): dfeat (n, F), the anchors' gradient (n, 3) and, with fusion, the gradients of
// the gate's and the reference's pre-activations (n, F) with their column sums (dbmod, dbref).
template <typename T>
void input_grad(const T* dx, const T* x, const T* dist, const T* gate, const T* ref, double dist_scale, T* dfeat,
                T* danchor, T* dpre_gate, T* dref, T* dbmod, T* dbref, int64_t n, int64_t F) {
  const int64_t D = F + 4;
  for (int64_t r = 0; r < n; ++r) {
    const T* gr = dx + r * D;
    for (int64_t j = 0; j < F; ++j) dfeat[r * F + j] = gr[j];
    if (gate != nullptr) {
      for (int64_t j = 0; j < F; ++j) {
        const T g = gate[r * F + j], e = ref[r * F + j];
        const T dg = gr[j] * e * g * (T(1) - g), de = gr[j] * g;
        dpre_gate[r * F + j] = dg;
        dref[r * F + j] = de;
        dbmod[j] += dg;
        dbref[j] += de;
      }
    }
    // view / dist and dist / scale: the unit vector's gradient is its component across u, the
    // distance's along u; below DIST_EPS the distance is the constant clamp.
    const T* u = x + r * D + F;
    const T len = dist[r];
    T* da = danchor + r * 3;
    const bool clamped = !(len > static_cast<T>(DIST_EPS));
    if (clamped) {
      for (int d = 0; d < 3; ++d) da[d] = gr[F + d] / len;
    } else {
      const T along = u[0] * gr[F] + u[1] * gr[F + 1] + u[2] * gr[F + 2];
      const T gd = gr[F + 3] / static_cast<T>(dist_scale);
      for (int d = 0; d < 3; ++d) da[d] = (gr[F + d] - u[d] * along) / len + u[d] * gd;
    }
  }
}

}  // namespace decoder
}  // namespace dibrgs
