// CPU tile rasterizer for 3D Gaussian Splatting: binning, forward compositing
// and the hand-written backward. Same rules as reference.py (see there).
// Tiles are spread dynamically over torch's intra-op threads; each tile's
// 256 pixels are processed row by row in fixed-width loops that vectorise.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <vector>

#include <ATen/Parallel.h>

#include <atomic>

namespace {

constexpr int TILE = 16;
constexpr int TP = TILE * TILE;
constexpr double ALPHA_MIN = 1.0 / 255.0;
constexpr double ALPHA_MAX = 0.99;
constexpr double T_MIN = 1e-4;

// exp for power <= 0 in float: Cephes-style range reduction and polynomial
// (relative error ~1e-7), written with plain arithmetic so loops vectorise
// without -ffast-math. Arguments under -87 give ~0 (alpha is skipped there).
inline float exp_approx(float x) {
  x = std::min(std::max(x, -87.0f), 88.0f);
  const float t = x * 1.44269504088896341f;
  const int n = static_cast<int>(t - 0.5f);  // rounds to nearest for t <= 0.5
  const float nf = static_cast<float>(n);
  float r = x - nf * 0.693359375f;
  r = r - nf * -2.12194440e-4f;
  const float z = r * r;
  float y = 1.9875691500E-4f;
  y = y * r + 1.3981999507E-3f;
  y = y * r + 8.3334519073E-3f;
  y = y * r + 4.1665795894E-2f;
  y = y * r + 1.6666665459E-1f;
  y = y * r + 5.0000001201E-1f;
  y = y * z + r + 1.0f;
  int32_t bits = (n + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(float));
  return y * scale;
}
inline double exp_approx(double x) { return std::exp(x); }

template <typename T>
struct Gauss {
  T mx, my, a, b, c, o;
};

// Rows [r0, r1] (inclusive, tile-local) where the Gaussian may reach
// alpha >= 1/255, given its half-extent ey (already widened).
inline void row_range(double my, double ey, int ty0, int H, int& r0, int& r1) {
  const double lo = std::ceil(my - ey - 0.5) - ty0;
  const double hi = std::floor(my + ey - 0.5) - ty0;
  const int last = std::min(TILE - 1, H - 1 - ty0);
  r0 = lo < 0 ? 0 : (lo > TILE ? TILE : static_cast<int>(lo));
  r1 = hi > last ? last : (hi < -1 ? -1 : static_cast<int>(hi));
}

// The alpha >= 1/255 region is the ellipse q <= 2 ln(255 o) with
// q = a dx^2 + 2 b dx dy + c dy^2. Culling uses a slightly larger level so that
// float32 rounding of the per-pixel test can never reach outside it; the
// culls below only save work, they never change a result.
inline double cull_level(double o) {
  if (!(o * 255.0 >= 1.0)) return -1.0;
  return 2.0 * std::log(o * 255.0) * 1.01 + 0.01;
}

// Whether tile row r (pixel centres at y = ty0 + r + 0.5) has a pixel centre
// of the tile's columns inside the ellipse q <= lvl (widened by a pixel).
inline bool row_hits(double mx, double my, double a, double b, double c, double lvl, int tx0, int ty0, int r) {
  const double dy = my - (ty0 + r + 0.5);
  const double disc = b * b * dy * dy - a * (c * dy * dy - lvl);
  if (disc < 0) return false;
  const double sq = std::sqrt(disc);
  // dx = mx - px lies in [(-b dy - sq) / a, (-b dy + sq) / a].
  const double pxlo = mx - (-b * dy + sq) / a - 1.0;
  const double pxhi = mx - (-b * dy - sq) / a + 1.0;
  return pxhi >= tx0 + 0.5 && pxlo <= tx0 + TILE - 0.5;
}

// Runs worker(next) on every torch intra-op thread; workers pull tile indices
// from the shared counter (dynamic scheduling: tile costs vary a lot).
template <typename F>
void run_workers(F&& worker) {
  std::atomic<int64_t> next(0);
  at::parallel_for(0, at::get_num_threads(), 1, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) worker(next);
  });
}

}  // namespace

// Tile lists. Returns (offsets int64 (tiles+1), gauss_ids int32 (isects),
// extents float64 (N, 3)): Gaussians of a tile in increasing depth (ties by
// index); extents are the half-sizes (+1 px) of the culling ellipse and its level.
std::vector<torch::Tensor> bin_tiles(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                     torch::Tensor depths, torch::Tensor radii, int64_t W, int64_t H) {
  auto m = means2d.to(torch::kFloat64).contiguous();
  auto con = conics.to(torch::kFloat64).contiguous();
  auto op = opac.to(torch::kFloat64).contiguous();
  auto dep = depths.to(torch::kFloat64).contiguous();
  auto rad = radii.to(torch::kInt64).contiguous();
  const int64_t N = m.size(0);
  const int64_t tx = (W + TILE - 1) / TILE, ty = (H + TILE - 1) / TILE;
  const double* pm = m.data_ptr<double>();
  const double* pc = con.data_ptr<double>();
  const double* po = op.data_ptr<double>();
  const double* pd = dep.data_ptr<double>();
  const int64_t* pr = rad.data_ptr<int64_t>();
  auto ext = torch::zeros({N, 3}, torch::kFloat64);
  double* pe = ext.data_ptr<double>();
  std::vector<int32_t> rect(4 * N, 0);
  std::vector<int64_t> live;
  live.reserve(N);
  for (int64_t i = 0; i < N; ++i) {
    const double r = static_cast<double>(pr[i]);
    const double mx = pm[2 * i], my = pm[2 * i + 1];
    const double t = cull_level(po[i]);
    if (pr[i] <= 0 || t < 0 || !std::isfinite(mx) || !std::isfinite(my)) continue;
    double det = pc[3 * i] * pc[3 * i + 2] - pc[3 * i + 1] * pc[3 * i + 1];
    if (!(det > 0)) det = 1.0;
    const double ex = std::sqrt(t * pc[3 * i + 2] / det) + 1.0;
    const double ey = std::sqrt(t * pc[3 * i] / det) + 1.0;
    pe[3 * i] = ex;
    pe[3 * i + 1] = ey;
    pe[3 * i + 2] = t;
    auto clampt = [](double v, int64_t hi) {
      return static_cast<int32_t>(std::min(std::max(v, 0.0), static_cast<double>(hi)));
    };
    const int32_t x0 = clampt(std::max(std::floor((mx - r) / TILE), std::floor((mx - ex) / TILE)), tx);
    const int32_t x1 = clampt(std::min(std::ceil((mx + r) / TILE), std::floor((mx + ex) / TILE) + 1), tx);
    const int32_t y0 = clampt(std::max(std::floor((my - r) / TILE), std::floor((my - ey) / TILE)), ty);
    const int32_t y1 = clampt(std::min(std::ceil((my + r) / TILE), std::floor((my + ey) / TILE) + 1), ty);
    if (x1 <= x0 || y1 <= y0) continue;
    rect[4 * i] = x0;
    rect[4 * i + 1] = x1;
    rect[4 * i + 2] = y0;
    rect[4 * i + 3] = y1;
    live.push_back(i);
  }
  std::stable_sort(live.begin(), live.end(), [pd](int64_t a, int64_t b) { return pd[a] < pd[b]; });
  auto offsets = torch::zeros({tx * ty + 1}, torch::kInt64);
  int64_t* off = offsets.data_ptr<int64_t>();
  for (int64_t i : live)
    for (int32_t y = rect[4 * i + 2]; y < rect[4 * i + 3]; ++y)
      for (int32_t x = rect[4 * i]; x < rect[4 * i + 1]; ++x) off[y * tx + x + 1] += 1;
  for (int64_t t = 0; t < tx * ty; ++t) off[t + 1] += off[t];
  auto gids = torch::empty({off[tx * ty]}, torch::kInt32);
  int32_t* pg = gids.data_ptr<int32_t>();
  std::vector<int64_t> pos(off, off + tx * ty);
  for (int64_t i : live)
    for (int32_t y = rect[4 * i + 2]; y < rect[4 * i + 3]; ++y)
      for (int32_t x = rect[4 * i]; x < rect[4 * i + 1]; ++x) pg[pos[y * tx + x]++] = static_cast<int32_t>(i);
  return {offsets, gids, ext};
}

template <typename T>
static void forward_impl(const T* pm, const T* pc, const T* po, const T* pf, const int64_t* off, const int32_t* pg,
                         const double* pe, int64_t C, int64_t W, int64_t H, T* out, T* tfin, int32_t* ncon) {
  const int64_t tx = (W + TILE - 1) / TILE, ty = (H + TILE - 1) / TILE;
  run_workers([&](std::atomic<int64_t>& next) {
    std::vector<T> acc(C * TP);
    alignas(64) T Tp[TP];
    alignas(64) int32_t done[TP];
    alignas(64) int32_t nc[TP];
    alignas(64) T w[TILE];
    int rowdone[TILE];
    for (int64_t tile = next++; tile < tx * ty; tile = next++) {
      const int ty0 = static_cast<int>((tile / tx) * TILE), tx0 = static_cast<int>((tile % tx) * TILE);
      std::fill(acc.begin(), acc.end(), T(0));
      std::fill(rowdone, rowdone + TILE, 0);
      int ndone = 0;
      for (int p = 0; p < TP; ++p) {
        Tp[p] = T(1);
        nc[p] = 0;
        const bool out_img = (tx0 + p % TILE >= W) || (ty0 + p / TILE >= H);
        done[p] = out_img ? 1 : 0;
        ndone += done[p];
        rowdone[p / TILE] += done[p];
      }
      const int64_t s = off[tile], e = off[tile + 1];
      for (int64_t k = s; k < e && ndone < TP; ++k) {
        const int32_t g = pg[k];
        const T mx = pm[2 * g], my = pm[2 * g + 1];
        const T a = pc[3 * g], b = pc[3 * g + 1], c = pc[3 * g + 2], o = po[g];
        const double* eg = pe + 3 * g;
        int r0, r1;
        row_range(static_cast<double>(my), eg[1], ty0, static_cast<int>(H), r0, r1);
        const int32_t kk = static_cast<int32_t>(k - s + 1);
        for (int r = r0; r <= r1; ++r) {
          if (rowdone[r] == TILE || !row_hits(mx, my, a, b, c, eg[2], tx0, ty0, r)) continue;
          const T dy = my - (T(ty0 + r) + T(0.5));
          T* Tr = Tp + r * TILE;
          int32_t* dr = done + r * TILE;
          int32_t* nr = nc + r * TILE;
          int nstop = 0, nvalid = 0;
#pragma omp simd reduction(+ : nstop, nvalid)
          for (int x = 0; x < TILE; ++x) {
            const T dx = mx - (T(tx0 + x) + T(0.5));
            const T power = T(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
            const T al = std::min(T(ALPHA_MAX), o * exp_approx(power));
            const bool cand = (dr[x] == 0) & (power <= T(0)) & (al >= T(ALPHA_MIN));
            const T testT = Tr[x] * (T(1) - al);
            const bool stop = cand & (testT < T(T_MIN));
            const bool valid = cand & !stop;
            w[x] = valid ? al * Tr[x] : T(0);
            Tr[x] = valid ? testT : Tr[x];
            nr[x] = valid ? kk : nr[x];
            dr[x] = stop ? 1 : dr[x];
            nstop += stop ? 1 : 0;
            nvalid += valid ? 1 : 0;
          }
          ndone += nstop;
          rowdone[r] += nstop;
          if (nvalid == 0) continue;
          for (int64_t ch = 0; ch < C; ++ch) {
            const T f = pf[g * C + ch];
            T* ar = acc.data() + ch * TP + r * TILE;
#pragma omp simd
            for (int x = 0; x < TILE; ++x) ar[x] += w[x] * f;
          }
        }
      }
      for (int p = 0; p < TP; ++p) {
        const int64_t X = tx0 + p % TILE, Y = ty0 + p / TILE;
        if (X >= W || Y >= H) continue;
        const int64_t pix = Y * W + X;
        for (int64_t ch = 0; ch < C; ++ch) out[pix * C + ch] = acc[ch * TP + p];
        tfin[pix] = Tp[p];
        ncon[pix] = nc[p];
      }
    }
  });
}

// Forward compositing. Returns (out (H, W, C), T_final (H, W), n_contrib
// (H, W) int32: 1 + tile-list position of the last Gaussian composited).
std::vector<torch::Tensor> forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                   torch::Tensor feats, torch::Tensor offsets, torch::Tensor gids,
                                   torch::Tensor ext, int64_t W, int64_t H) {
  const int64_t C = feats.size(1);
  auto out = torch::zeros({H, W, C}, feats.options());
  auto tfin = torch::ones({H, W}, feats.options());
  auto ncon = torch::zeros({H, W}, torch::dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(feats.scalar_type(), "dibrgs_forward", [&] {
    forward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                           feats.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(), gids.data_ptr<int32_t>(),
                           ext.data_ptr<double>(), C, W, H, out.data_ptr<scalar_t>(), tfin.data_ptr<scalar_t>(),
                           ncon.data_ptr<int32_t>());
  });
  return {out, tfin, ncon};
}

template <typename T>
static void backward_impl(const T* pm, const T* pc, const T* po, const T* pf, const int64_t* off, const int32_t* pg,
                          const double* pe, const T* gout, const T* tfin, const int32_t* ncon, int64_t C, int64_t W,
                          int64_t H, T* gm, T* gc, T* go, T* gf) {
  const int64_t tx = (W + TILE - 1) / TILE, ty = (H + TILE - 1) / TILE;
  const int64_t G = 6 + C;  // per intersection: mx, my, a, b, c, o, feats
  const int64_t M = off[tx * ty];
  std::vector<T> buf(M * G);
  run_workers([&](std::atomic<int64_t>& next) {
    std::vector<T> S(C * TP), D(C * TP), gfeat(C);
    alignas(64) T Tp[TP];
    alignas(64) int32_t nc[TP];
    alignas(64) T va[TILE], vT[TILE], dla[TILE], ok[TILE], Gs[TILE];
    int rowmax[TILE];
    for (int64_t tile = next++; tile < tx * ty; tile = next++) {
      const int64_t s = off[tile], e = off[tile + 1];
      if (e == s) continue;
      const int ty0 = static_cast<int>((tile / tx) * TILE), tx0 = static_cast<int>((tile % tx) * TILE);
      int maxnc = 0;
      std::fill(rowmax, rowmax + TILE, 0);
      for (int p = 0; p < TP; ++p) {
        const int64_t X = tx0 + p % TILE, Y = ty0 + p / TILE;
        const bool in = X < W && Y < H;
        const int64_t pix = Y * W + X;
        Tp[p] = in ? tfin[pix] : T(1);
        nc[p] = in ? ncon[pix] : 0;
        maxnc = std::max(maxnc, nc[p]);
        rowmax[p / TILE] = std::max(rowmax[p / TILE], nc[p]);
        for (int64_t ch = 0; ch < C; ++ch) {
          S[ch * TP + p] = T(0);
          D[ch * TP + p] = in ? gout[pix * C + ch] : T(0);
        }
      }
      for (int64_t k = s + maxnc - 1; k >= s; --k) {
        const int32_t g = pg[k];
        const T mx = pm[2 * g], my = pm[2 * g + 1];
        const T a = pc[3 * g], b = pc[3 * g + 1], c = pc[3 * g + 2], o = po[g];
        const int32_t kk = static_cast<int32_t>(k - s);
        const double* eg = pe + 3 * g;
        int r0, r1;
        row_range(static_cast<double>(my), eg[1], ty0, static_cast<int>(H), r0, r1);
        T gmx = 0, gmy = 0, ga = 0, gb = 0, gcc = 0, gop = 0;
        std::fill(gfeat.begin(), gfeat.end(), T(0));
        for (int r = r0; r <= r1; ++r) {
          if (kk >= rowmax[r] || !row_hits(mx, my, a, b, c, eg[2], tx0, ty0, r)) continue;
          const T dy = my - (T(ty0 + r) + T(0.5));
          T* Tr = Tp + r * TILE;
          const int32_t* nr = nc + r * TILE;
          int nvalid = 0;
#pragma omp simd reduction(+ : nvalid)
          for (int x = 0; x < TILE; ++x) {
            const T dx = mx - (T(tx0 + x) + T(0.5));
            const T power = T(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
            const T Gv = exp_approx(power);
            const T al = std::min(T(ALPHA_MAX), o * Gv);
            Gs[x] = Gv;
            const bool valid = (kk < nr[x]) & (power <= T(0)) & (al >= T(ALPHA_MIN));
            Tr[x] = valid ? Tr[x] / (T(1) - al) : Tr[x];
            va[x] = valid ? al : T(0);
            ok[x] = valid ? T(1) : T(0);
            vT[x] = Tr[x];
            dla[x] = T(0);
            nvalid += valid ? 1 : 0;
          }
          if (nvalid == 0) continue;
          for (int64_t ch = 0; ch < C; ++ch) {
            const T f = pf[g * C + ch];
            T* Sr = S.data() + ch * TP + r * TILE;
            const T* Dr = D.data() + ch * TP + r * TILE;
            T gfc = 0;
#pragma omp simd reduction(+ : gfc)
            for (int x = 0; x < TILE; ++x) {
              dla[x] += ok[x] * Dr[x] * (f - Sr[x]) * vT[x];
              gfc += va[x] * vT[x] * Dr[x];
              Sr[x] = va[x] * f + (T(1) - va[x]) * Sr[x];
            }
            gfeat[ch] += gfc;
          }
#pragma omp simd reduction(+ : gmx, gmy, ga, gb, gcc, gop)
          for (int x = 0; x < TILE; ++x) {
            const T dx = mx - (T(tx0 + x) + T(0.5));
            const T Gv = Gs[x];
            // No gradient through the 0.99 clamp (as torch.clamp).
            const bool unclamped = (ok[x] > T(0)) & (o * Gv <= T(ALPHA_MAX));
            const T dal = unclamped ? dla[x] : T(0);
            gop += Gv * dal;
            const T dp = o * Gv * dal;
            gmx -= dp * (a * dx + b * dy);
            gmy -= dp * (c * dy + b * dx);
            ga -= T(0.5) * dp * dx * dx;
            gb -= dp * dx * dy;
            gcc -= T(0.5) * dp * dy * dy;
          }
        }
        T* bk = buf.data() + k * G;
        bk[0] = gmx;
        bk[1] = gmy;
        bk[2] = ga;
        bk[3] = gb;
        bk[4] = gcc;
        bk[5] = gop;
        for (int64_t ch = 0; ch < C; ++ch) bk[6 + ch] = gfeat[ch];
      }
    }
  });
  // Deterministic reduction (fixed order per Gaussian), parallel over columns.
  at::parallel_for(0, G, 1, [&](int64_t cb, int64_t ce) {
    for (int64_t col = cb; col < ce; ++col) {
      T* dst;
      int64_t stride, base;
      if (col < 2) {
        dst = gm, stride = 2, base = col;
      } else if (col < 5) {
        dst = gc, stride = 3, base = col - 2;
      } else if (col == 5) {
        dst = go, stride = 1, base = 0;
      } else {
        dst = gf, stride = C, base = col - 6;
      }
      for (int64_t k = 0; k < M; ++k) dst[pg[k] * stride + base] += buf[k * G + col];
    }
  });
}

// Backward: gradients (means2d (N, 2), conics (N, 3), opac (N,), feats (N, C))
// from the gradient of the composited features (H, W, C).
std::vector<torch::Tensor> backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                    torch::Tensor feats, torch::Tensor offsets, torch::Tensor gids,
                                    torch::Tensor ext, torch::Tensor gout, torch::Tensor tfin, torch::Tensor ncon,
                                    int64_t W, int64_t H) {
  const int64_t C = feats.size(1);
  auto gm = torch::zeros_like(means2d);
  auto gc = torch::zeros_like(conics);
  auto go = torch::zeros_like(opac);
  auto gf = torch::zeros_like(feats);
  auto go_c = gout.contiguous();
  AT_DISPATCH_FLOATING_TYPES(feats.scalar_type(), "dibrgs_backward", [&] {
    backward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                            feats.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(), gids.data_ptr<int32_t>(),
                            ext.data_ptr<double>(), go_c.data_ptr<scalar_t>(), tfin.data_ptr<scalar_t>(),
                            ncon.data_ptr<int32_t>(), C, W, H, gm.data_ptr<scalar_t>(), gc.data_ptr<scalar_t>(),
                            go.data_ptr<scalar_t>(), gf.data_ptr<scalar_t>());
  });
  return {gm, gc, go, gf};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("bin_tiles", &bin_tiles, "tile lists of screen-space Gaussians");
  m.def("forward", &forward, "front-to-back compositing");
  m.def("backward", &backward, "gradients of the compositing");
}
