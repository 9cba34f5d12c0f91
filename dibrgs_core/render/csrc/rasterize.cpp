// CPU tile rasterizer for 3D Gaussian Splatting: binning, compositing (the
// per-tile kernels are in composite.h) and the fused EWA projection (project.h),
// as a torch extension. Same rules as reference.py (see there). Tiles are spread
// dynamically over torch's intra-op threads (the extension is built with
// -fopenmp: at::parallel_for is a header template and would run serially
// otherwise).
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <limits>
#include <mutex>
#include <new>
#include <string>
#include <type_traits>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <vector>

#include "adam.h"
#include "chunks.h"
#include "composite.h"
#include "decoder.h"
#include "loss.h"
#include "spawn.h"
#include "project.h"
#include "project_rows.h"
#include "rows.h"
#include "ssim.h"
#include "zbuffer.h"

using dibrgs::TILE;

namespace {

// The alpha >= 1/255 region is the ellipse q <= 2 ln(255 o) with
// q = a dx^2 + 2 b dx dy + c dy^2. Culling uses a larger level so that the
// kernels' float32 rounding of the per-pixel test can never reach outside it:
// a fixed 1 % + 0.01, and for a thin Gaussian (its terms cancel) about 4 eps
// cond q more (cond: the conic's eigenvalue ratio, bounded above by
// (a + c)^2 / det). Past twice the level, or for a conic that is not positive
// definite, it is infinite: no ellipse cull, the radius alone bounds the tiles.
// float64 inputs get the same level, so that they give the same tile lists.
// The culls below only save work, they never change a result.
inline double cull_level(double o, double a, double c, double det) {
  if (!(o * 255.0 >= 1.0)) return -1.0;
  const double grow = 8.0 * std::numeric_limits<float>::epsilon() * (a + c) * (a + c) / det;
  if (!(det > 0) || !(grow <= 1.0)) return std::numeric_limits<double>::infinity();  // NaN too
  return (2.0 * std::log(o * 255.0) * 1.01 + 0.01) * (1.0 + grow);
}

// Blocks of about `grain` items for the binning's parallel passes: as many as the threads can
// share out dynamically, none so small that its fork costs more than its work; one on one thread.
inline int64_t block_count(int64_t n, int64_t grain) {
  const int64_t T = at::get_num_threads();
  return T < 2 ? 1 : std::max<int64_t>(1, std::min<int64_t>(T * 8, (n + grain - 1) / grain));
}

// Calls fn(b) for b in [0, nb), the blocks pulled dynamically by torch's intra-op threads.
template <typename F>
void for_blocks(int64_t nb, F&& fn) {
  dibrgs::run_workers([&](std::atomic<int64_t>& next) {
    for (int64_t b = next++; b < nb; b = next++) fn(b);
  });
}

// Uninitialised storage of n objects, constructed in place by their users.
template <typename T>
class RawArray {
  static_assert(std::is_trivially_copyable<T>::value && std::is_trivially_destructible<T>::value,
                "RawArray holds trivial types only");
  T* p_;

 public:
  explicit RawArray(int64_t n) : p_(static_cast<T*>(::operator new(sizeof(T) * std::max<int64_t>(n, 1)))) {}
  RawArray(RawArray&& o) noexcept : p_(o.p_) { o.p_ = nullptr; }
  ~RawArray() { ::operator delete(p_); }
  RawArray(const RawArray&) = delete;
  RawArray& operator=(const RawArray&) = delete;
  RawArray& operator=(RawArray&& o) noexcept {
    std::swap(p_, o.p_);
    return *this;
  }
  T& operator[](int64_t i) { return p_[i]; }
  T* data() { return p_; }
};

// Stable LSD radix sort of the n (key, idx) pairs at key, idx by key (bytes that all keys
// share skipped; the histograms of all bytes from one pass); k2, i2: scratch of n each. The
// result ends in key, idx.
template <typename K>
void radix_sort(K* key, int32_t* idx, int64_t n, K* k2, int32_t* i2) {
  constexpr int NB = sizeof(K);
  if (n == 0) return;
  std::vector<int64_t> cnt(NB * 256, 0);
  for (int64_t i = 0; i < n; ++i)
    for (int b = 0; b < NB; ++b) ++cnt[b * 256 + ((key[i] >> (8 * b)) & 0xFF)];
  bool swapped = false;
  for (int b = 0; b < NB; ++b) {
    const int64_t* c = cnt.data() + b * 256;
    const int shift = 8 * b;
    if (c[(key[0] >> shift) & 0xFF] == n) continue;
    int64_t pos[256], sum = 0;
    for (int v = 0; v < 256; ++v) pos[v] = sum, sum += c[v];
    for (int64_t i = 0; i < n; ++i) {
      const int64_t p = pos[(key[i] >> shift) & 0xFF]++;
      k2[p] = key[i];
      i2[p] = idx[i];
    }
    std::swap(key, k2);
    std::swap(idx, i2);
    swapped = !swapped;
  }
  if (swapped) {  // the result is in the caller's scratch
    std::copy(key, key + n, k2);
    std::copy(idx, idx + n, i2);
  }
}

// (key, idx) pairs sorted by key, ties in their given order. On more than one thread the two
// halves are sorted side by side and merged, each thread writing its own part of the output
// (a parallel radix pass would have both threads writing into every bucket: false sharing).
template <typename K>
void sort_by_key(RawArray<K>& key, RawArray<int32_t>& idx, int64_t n) {
  RawArray<K> k2(n);
  RawArray<int32_t> i2(n);
  const int64_t T = at::get_num_threads();
  if (T < 2 || n < 8192) {
    radix_sort(key.data(), idx.data(), n, k2.data(), i2.data());
    return;
  }
  const int64_t h = n / 2;
  at::parallel_for(0, 2, 1, [&](int64_t b, int64_t e) {
    for (int64_t part = b; part < e; ++part) {
      const int64_t o = part ? h : 0, m = part ? n - h : h;
      radix_sort(key.data() + o, idx.data() + o, m, k2.data() + o, i2.data() + o);
    }
  });
  // Merge [0, h) and [h, n) into k2, i2: output range [d0, d1) of each thread from the
  // split of the merge path at d0 (ties taken from the first half, whose entries come first).
  const K* A = key.data();
  const K* B = key.data() + h;
  const int64_t na = h, nb = n - h;
  auto split = [&](int64_t d) {
    int64_t lo = std::max<int64_t>(0, d - nb), hi = std::min(d, na);
    while (lo < hi) {
      const int64_t mid = (lo + hi) / 2;
      if (A[mid] <= B[d - mid - 1])
        lo = mid + 1;
      else
        hi = mid;
    }
    return lo;
  };
  at::parallel_for(0, T, 1, [&](int64_t tb, int64_t te) {
    for (int64_t t = tb; t < te; ++t) {
      const int64_t d0 = n * t / T, d1 = n * (t + 1) / T;
      int64_t i = split(d0), j = d0 - i;
      for (int64_t d = d0; d < d1; ++d) {
        const bool fa = j >= nb || (i < na && A[i] <= B[j]);
        const int64_t src = fa ? i++ : h + j++;
        k2[d] = key[src];
        i2[d] = idx[src];
      }
    }
  });
  key = std::move(k2);
  idx = std::move(i2);
}

// Order-preserving maps of a float / double to an unsigned integer.
inline uint32_t depth_key(float d) {
  uint32_t u;
  std::memcpy(&u, &d, sizeof(u));
  return (u >> 31) ? ~u : (u | (uint32_t(1) << 31));
}
inline uint64_t depth_key(double d) {
  uint64_t u;
  std::memcpy(&u, &d, sizeof(u));
  return (u >> 63) ? ~u : (u | (uint64_t(1) << 63));
}

// What the tile emission needs of a Gaussian (kept at the Gaussian's index: bins[i] is Gaussian
// i's, read in depth order through the live list).
struct Bin {
  double mx, my;
  dibrgs::Chords ch;
  int32_t x0, x1, y0, y1;
};

// The tile rectangle and chords of Gaussian i (screen-space inputs of type S, radius of type R);
// false when it reaches no tile (out is then left unwritten).
template <typename S, typename R>
inline bool make_bin(const S* pm, const S* pc, const S* po, const R* pr, int64_t i, int64_t tx, int64_t ty, Bin* out) {
  const double r = static_cast<double>(pr[i]);
  const double mx = pm[2 * i], my = pm[2 * i + 1];
  const double a = pc[3 * i], b = pc[3 * i + 1], c = pc[3 * i + 2];
  double det = a * c - b * b;
  const double t = cull_level(po[i], a, c, det);
  if (pr[i] <= 0 || t < 0 || !std::isfinite(mx) || !std::isfinite(my)) return false;
  if (!(det > 0)) det = 1.0;
  // Exact in double against the kernels' own mean; the pad only covers the extents' rounding.
  const double ex = std::sqrt(t * c / det) * (1.0 + 1e-9) + 0.01;
  const double ey = std::sqrt(t * a / det) * (1.0 + 1e-9) + 0.01;
  auto clampt = [](double v, int64_t hi) {
    return static_cast<int32_t>(std::min(std::max(v, 0.0), static_cast<double>(hi)));
  };
  const int32_t x0 = clampt(std::max(std::floor((mx - r) / TILE), std::floor((mx - ex) / TILE)), tx);
  const int32_t x1 = clampt(std::min(std::ceil((mx + r) / TILE), std::floor((mx + ex) / TILE) + 1), tx);
  const int32_t y0 = clampt(std::max(std::floor((my - r) / TILE), std::floor((my - ey) / TILE)), ty);
  const int32_t y1 = clampt(std::min(std::ceil((my + r) / TILE), std::floor((my + ey) / TILE) + 1), ty);
  if (x1 <= x0 || y1 <= y0) return false;
  new (out) Bin{mx, my, dibrgs::Chords(a, b, c, t), x0, x1, y0, y1};
  return true;
}

// The Gaussians' bins (indexed by Gaussian) and the live ones in increasing depth, ties by index
// (keys: 32-bit for float32 depths, the same order as their exact double values). Blocks of the
// Gaussians build their bins, keys and rectangles' tile counts in parallel and compact them in
// index order; the sort is parallel too. live (nout): the live Gaussians in depth order; area
// (nout + 1): area[j + 1] the tiles of live[j]'s rectangle (area[0] = 0). The bins are read in
// depth order where the tiles are listed, not copied into it first: on two threads that copy and
// its reading back each moved about half of the records between the cores' caches.
template <typename S, typename R, typename D>
RawArray<Bin> bins_and_depth_order(const S* pm, const S* pc, const S* po, const R* pr, const D* dep, int64_t N,
                                  int64_t tx, int64_t ty, int64_t& nout, RawArray<int32_t>& live,
                                  RawArray<int64_t>& area) {
  typedef typename std::conditional<sizeof(D) == 4, uint32_t, uint64_t>::type K;
  // Scratch left uninitialised: every entry is written before it is read (zeroing it was
  // serial memsets of the calling thread).
  RawArray<Bin> bins(N);
  RawArray<uint8_t> alive(N);
  RawArray<int64_t> tiles(N);  // of each live Gaussian's rectangle
  const int64_t nb = block_count(N, 1024);
  std::vector<int64_t> first(nb + 1, 0);
  for_blocks(nb, [&](int64_t blk) {
    int64_t n = 0;
    for (int64_t i = N * blk / nb, e = N * (blk + 1) / nb; i < e; ++i) {
      alive[i] = make_bin(pm, pc, po, pr, i, tx, ty, &bins[i]);
      if (alive[i]) tiles[i] = int64_t(bins[i].x1 - bins[i].x0) * (bins[i].y1 - bins[i].y0);
      n += alive[i];
    }
    first[blk + 1] = n;
  });
  for (int64_t blk = 0; blk < nb; ++blk) first[blk + 1] += first[blk];
  const int64_t nlive = first[nb];
  RawArray<K> key(nlive);
  live = RawArray<int32_t>(nlive);
  for_blocks(nb, [&](int64_t blk) {
    int64_t j = first[blk];
    for (int64_t i = N * blk / nb, e = N * (blk + 1) / nb; i < e; ++i)
      if (alive[i]) key[j] = depth_key(dep[i]), live[j++] = static_cast<int32_t>(i);
  });
  sort_by_key(key, live, nlive);
  nout = nlive;
  area = RawArray<int64_t>(nlive + 1);
  area[0] = 0;
  at::parallel_for(0, nlive, 4096, [&](int64_t b, int64_t e) {
    for (int64_t j = b; j < e; ++j) area[j + 1] = tiles[live[j]];
  });
  return bins;
}

}  // namespace

// Tile lists. Returns (offsets int64 (tiles + 1), gauss_ids int32 (M), masks
// int64 (M)): Gaussians of a tile in increasing depth (ties by index), and the
// row segments of its tile that each one reaches (dibrgs::segment_mask, laid
// out for the dtype of means2d). A Gaussian is listed in the tiles of its
// 3-sigma square that its culling ellipse reaches. means2d, conics and opac are
// read in their own dtype when they share float32 or float64 (else as float64),
// radii as int32 or int64; the bins are computed in double either way.
std::vector<torch::Tensor> bin_tiles(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                     torch::Tensor depths, torch::Tensor radii, int64_t W, int64_t H) {
  const auto st = means2d.scalar_type();
  const bool same = conics.scalar_type() == st && opac.scalar_type() == st &&
                    (st == torch::kFloat32 || st == torch::kFloat64);
  const auto sdt = same ? st : torch::kFloat64;
  const auto m = means2d.to(sdt).contiguous(), con = conics.to(sdt).contiguous(), op = opac.to(sdt).contiguous();
  const auto rad = radii.scalar_type() == torch::kInt32 ? radii.contiguous() : radii.to(torch::kInt64).contiguous();
  const auto dep = depths.to(depths.scalar_type() == torch::kFloat32 ? torch::kFloat32 : torch::kFloat64).contiguous();
  const int64_t N = m.size(0);
  const int64_t tx = (W + TILE - 1) / TILE, ty = (H + TILE - 1) / TILE, ntiles = tx * ty;
  RawArray<Bin> bins(0);
  RawArray<int32_t> live(0);  // the live Gaussians in depth order
  int64_t nlive = 0;
  RawArray<int64_t> work(0);  // the rectangles' tiles, then their running sum (below)
  AT_DISPATCH_FLOATING_TYPES(sdt, "dibrgs_bin_tiles", [&] {
    const scalar_t *pm = m.data_ptr<scalar_t>(), *pc = con.data_ptr<scalar_t>(), *po = op.data_ptr<scalar_t>();
    auto by_radius = [&](const auto* pr) {
      bins = dep.scalar_type() == torch::kFloat32
                 ? bins_and_depth_order(pm, pc, po, pr, dep.data_ptr<float>(), N, tx, ty, nlive, live, work)
                 : bins_and_depth_order(pm, pc, po, pr, dep.data_ptr<double>(), N, tx, ty, nlive, live, work);
    };
    if (rad.scalar_type() == torch::kInt32)
      by_radius(rad.data_ptr<int32_t>());
    else
      by_radius(rad.data_ptr<int64_t>());
  });
  // Tiles of each Gaussian's rectangle that its culling ellipse reaches, in depth order, with
  // the segments it reaches there: chunks of the depth order list their hits in parallel, then
  // scatter them (a tile's entries: the chunks in order, each in depth order). The chunks hold
  // equal numbers of rectangle tiles, not of Gaussians: the nearest Gaussians, first in the
  // order, cover the most tiles. Per-chunk tile counts are bounded to about 2^20 entries.
  std::partial_sum(work.data(), work.data() + nlive + 1, work.data());
  const int64_t nchunk =
      std::max<int64_t>(1, std::min(block_count(nlive, 512), (int64_t(1) << 20) / std::max<int64_t>(ntiles, 1)));
  std::vector<int64_t> cut(nchunk + 1);
  for (int64_t c = 0; c <= nchunk; ++c)
    cut[c] = std::lower_bound(work.data(), work.data() + nlive + 1, work[nlive] * c / nchunk) - work.data();
  cut[nchunk] = nlive;
  struct Hit {
    int32_t tile, id;
    uint64_t mask;
  };
  std::vector<std::vector<Hit>> hits(nchunk);
  std::vector<std::vector<int64_t>> counts(nchunk);
  const bool dbl = means2d.scalar_type() == torch::kFloat64;
  for_blocks(nchunk, [&](int64_t c) {
    // Local vectors, moved in at the end: neighbouring chunks' headers share cache lines.
    std::vector<Hit> ht;
    std::vector<int64_t> cnt(ntiles, 0);
    ht.reserve(work[cut[c + 1]] - work[cut[c]]);
    for (int64_t j = cut[c]; j < cut[c + 1]; ++j) {
      if (j + 8 < cut[c + 1]) {  // the depth order is random in memory; a bin may span two lines
        const char* ahead = reinterpret_cast<const char*>(&bins[live[j + 8]]);
        __builtin_prefetch(ahead);
        __builtin_prefetch(ahead + sizeof(Bin) - 1);
      }
      const int32_t id = live[j];
      const Bin& g = bins[id];
      for (int32_t y = g.y0; y < g.y1; ++y)
        for (int32_t x = g.x0; x < g.x1; ++x) {
          const float mxr = static_cast<float>(g.mx - x * TILE), myr = static_cast<float>(g.my - y * TILE);
          const uint64_t mk = dbl ? dibrgs::segment_mask<double>(g.ch, mxr, myr)
                                  : dibrgs::segment_mask<float>(g.ch, mxr, myr);
          if (mk == 0) continue;  // no pixel of this tile can reach alpha >= 1/255
          ht.push_back(Hit{static_cast<int32_t>(y * tx + x), id, mk});
          ++cnt[y * tx + x];
        }
    }
    hits[c] = std::move(ht);
    counts[c] = std::move(cnt);
  });
  auto offsets = torch::empty({ntiles + 1}, torch::kInt64);
  int64_t* off = offsets.data_ptr<int64_t>();
  // Start of each chunk's run in each tile: tiles in order, chunks in order.
  off[0] = 0;
  for (int64_t t = 0; t < ntiles; ++t) {
    int64_t pos = off[t];
    for (int64_t c = 0; c < nchunk; ++c) {
      const int64_t n = counts[c][t];
      counts[c][t] = pos;
      pos += n;
    }
    off[t + 1] = pos;
  }
  const int64_t M = off[ntiles];
  auto gids = torch::empty({M}, torch::kInt32);
  auto masks = torch::empty({M}, torch::kInt64);
  int32_t* pg = gids.data_ptr<int32_t>();
  uint64_t* pk = reinterpret_cast<uint64_t*>(masks.data_ptr<int64_t>());
  // Each thread scatters a run of consecutive chunks holding about M / threads hits: its entries
  // in a tile are then one contiguous stretch (with chunks dealt out one by one, neighbouring
  // chunks' few entries a tile would share cache lines between the threads).
  std::vector<int64_t> seen(nchunk + 1, 0);
  for (int64_t c = 0; c < nchunk; ++c) seen[c + 1] = seen[c] + static_cast<int64_t>(hits[c].size());
  const int64_t T = std::min<int64_t>(at::get_num_threads(), nchunk);
  at::parallel_for(0, T, 1, [&](int64_t tb, int64_t te) {
    for (int64_t t = tb; t < te; ++t) {
      const int64_t c0 = std::lower_bound(seen.begin(), seen.end(), M * t / T) - seen.begin();
      const int64_t c1 = std::lower_bound(seen.begin(), seen.end(), M * (t + 1) / T) - seen.begin();
      for (int64_t c = c0; c < std::min(c1, nchunk); ++c) {
        auto& pos = counts[c];
        for (const Hit& h : hits[c]) {
          const int64_t p = pos[h.tile]++;
          pg[p] = h.id;
          pk[p] = h.mask;
        }
      }
    }
  });
  return {offsets, gids, masks};
}

// Compositing: per-Gaussian records (make_records), then the tiles.

template <typename T>
dibrgs::Scene<T> scene(const torch::Tensor& rec, const torch::Tensor& offsets, const torch::Tensor& gids,
                       const torch::Tensor& masks, int64_t W, int64_t H) {
  return dibrgs::Scene<T>{rec.data_ptr<T>(), offsets.data_ptr<int64_t>(), gids.data_ptr<int32_t>(),
                          reinterpret_cast<const uint64_t*>(masks.data_ptr<int64_t>()), rec.size(1) - dibrgs::G_F,
                          W, H, (W + TILE - 1) / TILE};
}

// Records (N, G_F + C) of the Gaussians for the kernels (see composite.h): feats (N, Cf) and, when
// depth (N,) is defined, each Gaussian's depth and a one (C = Cf + 2), else C = Cf.
torch::Tensor records(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac, torch::Tensor feats,
                      torch::Tensor depth) {
  const int64_t N = feats.size(0), Cf = feats.size(1), C = depth.defined() ? Cf + 2 : Cf;
  TORCH_CHECK(!depth.defined() || (depth.numel() == N && depth.scalar_type() == feats.scalar_type() &&
                                   depth.is_contiguous()),
              "composite: depth must be (N,) contiguous, of the features' dtype");
  auto rec = torch::empty({N, dibrgs::G_F + C}, feats.options());
  const auto lop = at::log(at::clamp_min(opac, 1e-30));  // ATen's vectorised log (a scalar one cost 5 % of the forward)
  AT_DISPATCH_FLOATING_TYPES(feats.scalar_type(), "dibrgs_records", [&] {
    const scalar_t *pm = means2d.data_ptr<scalar_t>(), *pc = conics.data_ptr<scalar_t>();
    const scalar_t *po = opac.data_ptr<scalar_t>(), *pl = lop.data_ptr<scalar_t>(), *pf = feats.data_ptr<scalar_t>();
    const scalar_t* pd = depth.defined() ? depth.data_ptr<scalar_t>() : nullptr;
    scalar_t* pr = rec.data_ptr<scalar_t>();
    at::parallel_for(0, N, 8192,
                     [&](int64_t b, int64_t e) { dibrgs::make_records(pm, pc, po, pl, pf, pd, b, e, Cf, pr); });
  });
  return rec;
}

// Compile-time channel counts of the kernels (RGB / 1 channel + depth +
// alpha in rasterize); others run with the count at run time.
template <typename F>
void by_channels(int64_t C, F&& f) {
  switch (C) {
    case 5: f(std::integral_constant<int, 5>()); break;
    case 3: f(std::integral_constant<int, 3>()); break;
    default: f(std::integral_constant<int, 0>());
  }
}

// The channels [0, C) of a pixel over consecutive ranges of the given counts, one (H, W, n)
// buffer each (composite.h Planes); an undefined or empty tensor is a null buffer.
template <typename P>
dibrgs::Planes<P> planes(const std::vector<torch::Tensor>& bufs, const std::vector<int64_t>& counts) {
  TORCH_CHECK(!counts.empty() && counts.size() <= 4 && bufs.size() == counts.size(),
              "composite: one to four channel groups, one buffer each");
  dibrgs::Planes<P> p;
  p.n = static_cast<int>(counts.size());
  for (int b = 0; b < p.n; ++b) {
    TORCH_CHECK(counts[b] > 0, "composite: a channel group is empty");
    p.first[b + 1] = p.first[b] + counts[b];
    if (bufs[b].defined() && bufs[b].numel() > 0) {
      TORCH_CHECK(bufs[b].is_contiguous() && bufs[b].size(-1) == counts[b], "composite: buffer ", b,
                  " must be contiguous with ", counts[b], " channels");
      p.buf[b] = bufs[b].data_ptr<typename std::remove_const<P>::type>();
    }
  }
  return p;
}

template <typename T, bool STATS>
void forward_tiles(const dibrgs::Scene<T>& sc, const dibrgs::Planes<T>& out, T* tfin, int32_t* ncon,
                   dibrgs::Stats* stats) {
  const int64_t tiles = sc.tx * ((sc.H + TILE - 1) / TILE);
  by_channels(sc.C, [&](auto ct) {
    std::mutex mu;
    dibrgs::run_workers([&](std::atomic<int64_t>& next) {
      dibrgs::Workspace<T> ws;
      dibrgs::Stats st;
      for (int64_t t = next++; t < tiles; t = next++)
        dibrgs::forward_tile<T, decltype(ct)::value, STATS>(sc, t, ws, out, tfin, ncon, &st);
      if (STATS) {
        std::lock_guard<std::mutex> lock(mu);
        stats->add(st);
      }
    });
  });
}

namespace {

std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                             torch::Tensor feats, torch::Tensor depth, torch::Tensor offsets,
                                             torch::Tensor gids, torch::Tensor masks, int64_t W, int64_t H,
                                             const std::vector<int64_t>& groups) {
  const int64_t C = feats.size(1) + (depth.defined() ? 2 : 0);
  int64_t total = 0;
  for (const int64_t n : groups) total += n;
  TORCH_CHECK(total == C, "composite: channel groups sum to ", total, ", the features have ", C);
  auto rec = records(means2d, conics, opac, feats, depth);
  std::vector<torch::Tensor> res;
  for (const int64_t n : groups) res.push_back(torch::empty({H, W, n}, feats.options()));
  auto tfin = torch::empty({H, W}, feats.options());
  auto ncon = torch::empty({H, W}, torch::dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(feats.scalar_type(), "dibrgs_forward", [&] {
    forward_tiles<scalar_t, false>(scene<scalar_t>(rec, offsets, gids, masks, W, H), planes<scalar_t>(res, groups),
                                   tfin.data_ptr<scalar_t>(), ncon.data_ptr<int32_t>(), nullptr);
  });
  res.insert(res.end(), {tfin, ncon, rec});
  return res;
}

}  // namespace

// Forward compositing. Returns the composited features as one (H, W, n) tensor for each of
// the channel counts `groups` (summing to the features' C: [C] for one tensor), then T_final
// (H, W), n_contrib (H, W) int32 (1 + tile-list position of the last Gaussian composited) and
// the Gaussian records for backward.
std::vector<torch::Tensor> forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                   torch::Tensor feats, torch::Tensor offsets, torch::Tensor gids,
                                   torch::Tensor masks, int64_t W, int64_t H, std::vector<int64_t> groups) {
  return composite_forward(means2d, conics, opac, feats, torch::Tensor(), offsets, gids, masks, W, H, groups);
}

// forward with the features [colors (N, C), depth (N,), 1]: the renderer's colour, depth and alpha
// channels (C + 2 in all) read in place rather than concatenated first.
std::vector<torch::Tensor> forward_colour_depth(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                                torch::Tensor colors, torch::Tensor depth, torch::Tensor offsets,
                                                torch::Tensor gids, torch::Tensor masks, int64_t W, int64_t H,
                                                std::vector<int64_t> groups) {
  return composite_forward(means2d, conics, opac, colors, depth, offsets, gids, masks, W, H, groups);
}

template <typename T, bool STATS>
void backward_tiles(const dibrgs::Scene<T>& sc, const dibrgs::Planes<const T>& gout, const T* tfin,
                    const int32_t* ncon, T* buf, dibrgs::Stats* stats) {
  const int64_t tiles = sc.tx * ((sc.H + TILE - 1) / TILE);
  by_channels(sc.C, [&](auto ct) {
    std::mutex mu;
    dibrgs::run_workers([&](std::atomic<int64_t>& next) {
      dibrgs::Workspace<T> ws;
      dibrgs::Stats st;
      for (int64_t t = next++; t < tiles; t = next++)
        dibrgs::backward_tile<T, decltype(ct)::value, STATS>(sc, t, ws, gout, tfin, ncon, buf, &st);
      if (STATS) {
        std::lock_guard<std::mutex> lock(mu);
        stats->add(st);
      }
    });
  });
}

template <typename T>
void reduce_gradients(const T* buf, const int32_t* pg, int64_t M, int64_t N, int64_t C, T* gm, T* gc, T* go, T* gf) {
  const int64_t G = 6 + C;
  // Deterministic: each Gaussian sums its entries in list order into one
  // interleaved row (one cache line to miss, prefetched), threads owning
  // ranges of Gaussians (each reads the whole list); then the rows are split.
  RawArray<T> acc(N * G);  // each thread zeroes the rows it owns
  const int64_t nt = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), N / 1024));
  at::parallel_for(0, nt, 1, [&](int64_t tb, int64_t te) {
    for (int64_t t = tb; t < te; ++t) {
      const int64_t g0 = N * t / nt, g1 = N * (t + 1) / nt;
      std::fill(&acc[g0 * G], &acc[0] + g1 * G, T(0));
      for (int64_t k = 0; k < M; ++k) {
        // Only its own rows: a prefetch for writing of the other thread's rows took their cache
        // lines away from the core that was adding into them.
        if (k + 16 < M && pg[k + 16] >= g0 && pg[k + 16] < g1) __builtin_prefetch(&acc[0] + pg[k + 16] * G, 1);
        const int64_t g = pg[k];
        if (g < g0 || g >= g1) continue;
        const T* b = buf + k * G;
        T* a = &acc[0] + g * G;
        for (int64_t j = 0; j < G; ++j) a[j] += b[j];
      }
    }
  });
  at::parallel_for(0, N, 4096, [&](int64_t b, int64_t e) {
    for (int64_t g = b; g < e; ++g) {
      const T* a = &acc[0] + g * G;
      gm[2 * g] = a[0], gm[2 * g + 1] = a[1];
      gc[3 * g] = a[2], gc[3 * g + 1] = a[3], gc[3 * g + 2] = a[4];
      go[g] = a[5];
      for (int64_t ch = 0; ch < C; ++ch) gf[g * C + ch] = a[6 + ch];
    }
  });
}

// Backward: gradients (means2d (N, 2), conics (N, 3), opac (N,), feats (N, C))
// from the gradients of forward's channel groups (an empty tensor: zeros).
std::vector<torch::Tensor> backward(torch::Tensor rec, torch::Tensor offsets, torch::Tensor gids, torch::Tensor masks,
                                    std::vector<torch::Tensor> gouts, std::vector<int64_t> groups, torch::Tensor tfin,
                                    torch::Tensor ncon, int64_t W, int64_t H) {
  const int64_t N = rec.size(0), C = rec.size(1) - dibrgs::G_F, M = gids.size(0);
  auto opts = rec.options();
  auto gm = torch::empty({N, 2}, opts), gc = torch::empty({N, 3}, opts);
  auto go = torch::empty({N}, opts), gf = torch::empty({N, C}, opts);  // every row is written
  auto buf = torch::empty({M * (6 + C)}, opts);  // every entry is written
  for (auto& g : gouts)
    if (g.defined()) g = g.to(rec.scalar_type()).contiguous();
  AT_DISPATCH_FLOATING_TYPES(rec.scalar_type(), "dibrgs_backward", [&] {
    backward_tiles<scalar_t, false>(scene<scalar_t>(rec, offsets, gids, masks, W, H), planes<const scalar_t>(gouts, groups),
                                    tfin.data_ptr<scalar_t>(), ncon.data_ptr<int32_t>(), buf.data_ptr<scalar_t>(),
                                    nullptr);
    reduce_gradients<scalar_t>(buf.data_ptr<scalar_t>(), gids.data_ptr<int32_t>(), M, N, C, gm.data_ptr<scalar_t>(),
                               gc.data_ptr<scalar_t>(), go.data_ptr<scalar_t>(), gf.data_ptr<scalar_t>());
  });
  return {gm, gc, go, gf};
}

// Instrumented forward and backward (for benchmarks): int64 (2, 5), rows
// forward / backward, columns (Gaussian, vector) pairs evaluated, (Gaussian,
// pixel) pairs evaluated, pairs that composited / carried a gradient, list
// entries that reached a vector, list entries.
torch::Tensor composite_stats(torch::Tensor rec, torch::Tensor offsets, torch::Tensor gids, torch::Tensor masks,
                              torch::Tensor gout, int64_t W, int64_t H) {
  const int64_t C = rec.size(1) - dibrgs::G_F, M = gids.size(0);
  auto opts = rec.options();
  auto out = torch::empty({H, W, C}, opts), tfin = torch::empty({H, W}, opts);
  auto ncon = torch::empty({H, W}, torch::dtype(torch::kInt32));
  auto buf = torch::empty({M * (6 + C)}, opts);
  auto res = torch::zeros({2, 5}, torch::kInt64);
  int64_t* r = res.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(rec.scalar_type(), "dibrgs_stats", [&] {
    const auto sc = scene<scalar_t>(rec, offsets, gids, masks, W, H);
    dibrgs::Stats f, b;
    forward_tiles<scalar_t, true>(sc, planes<scalar_t>({out}, {C}), tfin.data_ptr<scalar_t>(), ncon.data_ptr<int32_t>(),
                                  &f);
    backward_tiles<scalar_t, true>(sc, planes<const scalar_t>({gout.contiguous()}, {C}), tfin.data_ptr<scalar_t>(),
                                   ncon.data_ptr<int32_t>(), buf.data_ptr<scalar_t>(), &b);
    int i = 0;
    for (const auto* s : {&f, &b}) {
      r[i++] = s->vectors, r[i++] = s->lanes, r[i++] = s->contrib, r[i++] = s->gaussians, r[i++] = s->entries;
    }
  });
  return res;
}

// The vector code path this build uses, and its float lanes.
std::string simd() { return std::string(dibrgs::simd_name()) + " x" + std::to_string(dibrgs::VBYTES / 4); }

// A camera as the kernels read it (project.h Cam, spawn.h visible): float64 R (row-major 3x3)
// and t of the world-to-camera w2c (4, 4), then fx, fy, cx, cy of K (3, 3, pixels).
std::array<double, 16> camera_params(const torch::Tensor& K, const torch::Tensor& w2c) {
  TORCH_CHECK(K.numel() == 9 && w2c.numel() == 16, "camera: K must be 3 x 3 and w2c 4 x 4");
  // Read in their own dtype when it is float32 or float64 (a float64 copy of each was two small
  // allocations and conversions a call, three calls a step); other dtypes converted first.
  auto read = [](const torch::Tensor& m, double* out) {
    const auto st = m.scalar_type();
    const bool plain = m.device().is_cpu() && (st == torch::kFloat32 || st == torch::kFloat64);
    const auto c = plain ? m.contiguous() : m.cpu().to(torch::kFloat64).contiguous();
    AT_DISPATCH_FLOATING_TYPES(c.scalar_type(), "dibrgs_camera_params", [&] {
      const scalar_t* p = c.data_ptr<scalar_t>();
      for (int64_t i = 0; i < c.numel(); ++i) out[i] = static_cast<double>(p[i]);
    });
  };
  double pk[9], pv[16];
  read(K, pk);
  read(w2c, pv);
  std::array<double, 16> cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam[3 * i + j] = pv[4 * i + j];
    cam[9 + i] = pv[4 * i + 3];
  }
  cam[12] = pk[0], cam[13] = pk[4], cam[14] = pk[2], cam[15] = pk[5];
  return cam;
}

// Projection (EWA splatting, project.h): whole vectors of Gaussians, then the rest one by one.
template <typename F>
void over_gaussians(int64_t N, F&& f) {
  dibrgs::dynamic_for(N, 1024, [&](int64_t b0, int64_t b1) {  // a multiple of proj::LD
    int64_t i = b0;
    for (; i + dibrgs::proj::LD <= b1; i += dibrgs::proj::LD) f(i, std::true_type());
    for (; i < b1; ++i) f(i, std::false_type());
  });
}

// Forward projection. Returns (means2d (N, 2), conics (N, 3), depths (N,)) in
// the dtype of means, radii (N,) int32 (0 = culled) and visible (N,) bool (radii > 0; written
// here, where a torch comparison after the call cost about 40 us of the calling thread).
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor K, torch::Tensor w2c, int64_t W, int64_t H, double near,
                                           double far) {
  const int64_t N = means.size(0);
  auto m2 = torch::empty({N, 2}, means.options());
  auto con = torch::empty({N, 3}, means.options());
  auto dep = torch::empty({N}, means.options());
  auto rad = torch::empty({N}, torch::dtype(torch::kInt32));
  auto vis = torch::empty({N}, torch::dtype(torch::kBool));
  const dibrgs::proj::Cam cm(camera_params(K, w2c).data(), W, H);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "dibrgs_project_forward", [&] {
    const scalar_t *pm = means.data_ptr<scalar_t>(), *pq = quats.data_ptr<scalar_t>(), *ps = scales.data_ptr<scalar_t>();
    scalar_t *om = m2.data_ptr<scalar_t>(), *oc = con.data_ptr<scalar_t>(), *od = dep.data_ptr<scalar_t>();
    int32_t* orad = rad.data_ptr<int32_t>();
    bool* ovis = vis.data_ptr<bool>();
    over_gaussians(N, [&](int64_t i, auto vec) {
      typedef typename std::conditional<decltype(vec)::value, dibrgs::VD, double>::type D;
      dibrgs::proj::forward<D>(cm, pm, pq, ps, i, near, far, W, H, om, oc, od, orad);
      for (int64_t j = i, e = i + (decltype(vec)::value ? dibrgs::proj::LD : 1); j < e; ++j) ovis[j] = orad[j] > 0;
    });
  });
  return {m2, con, dep, rad, vis};
}

// Backward projection: gradients (means (N, 3), quats (N, 4), scales (N, 3)) from those of
// means2d (N, 2) and conics (N, 3), contiguous, and depths (N,), any stride, or None (zero: a
// colours-only render; a zero tensor made in Python was the first operator after the
// compositing's backward, tens of microseconds on the serial path).
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor K, torch::Tensor w2c, int64_t W, int64_t H, double near,
                                            double far, torch::Tensor g_m2, torch::Tensor g_con,
                                            c10::optional<torch::Tensor> g_dep_opt) {
  const int64_t N = means.size(0);
  torch::Tensor g_dep = g_dep_opt.has_value() ? *g_dep_opt : torch::Tensor();
  TORCH_CHECK(g_m2.is_contiguous() && g_m2.numel() == 2 * N && g_con.is_contiguous() && g_con.numel() == 3 * N &&
                  (!g_dep.defined() || (g_dep.dim() == 1 && g_dep.size(0) == N)),
              "project_backward: gradients must be means2d (N, 2) and conics (N, 3) contiguous, depths (N,)");
  for (const auto* g : {&g_m2, &g_con, &g_dep})
    TORCH_CHECK(!g->defined() || g->scalar_type() == means.scalar_type(),
                "project_backward: gradients in the means' dtype");
  auto gm = torch::empty_like(means);
  auto gq = torch::empty_like(quats);
  auto gs = torch::empty_like(scales);
  const int64_t ds = g_dep.defined() ? g_dep.stride(0) : 0;  // stride 0: one zero read N times
  const dibrgs::proj::Cam cm(camera_params(K, w2c).data(), W, H);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "dibrgs_project_backward", [&] {
    const scalar_t zero = 0;
    const scalar_t *pm = means.data_ptr<scalar_t>(), *pq = quats.data_ptr<scalar_t>(), *ps = scales.data_ptr<scalar_t>();
    const scalar_t *gm2 = g_m2.data_ptr<scalar_t>(), *gc = g_con.data_ptr<scalar_t>();
    const scalar_t* gd = g_dep.defined() ? g_dep.data_ptr<scalar_t>() : &zero;
    scalar_t *om = gm.data_ptr<scalar_t>(), *oq = gq.data_ptr<scalar_t>(), *os = gs.data_ptr<scalar_t>();
    over_gaussians(N, [&](int64_t i, auto vec) {
      typedef typename std::conditional<decltype(vec)::value, dibrgs::VD, double>::type D;
      dibrgs::proj::backward<D>(cm, pm, pq, ps, i, near, far, gm2, gc, gd, ds, om, oq, os);
    });
  });
  return {gm, gq, gs};
}

// SSIM map of x against y ((H, W, C) each; g: the 1-D window) and the per-pixel factors of its
// gradient (ssim.h): {S, a, b, c}.
std::vector<torch::Tensor> ssim_forward(torch::Tensor x, torch::Tensor y, torch::Tensor g) {
  TORCH_CHECK(x.dim() == 3 && y.sizes() == x.sizes(), "ssim_forward: x and y must be (H, W, C) of one shape");
  TORCH_CHECK(g.dim() == 1 && g.numel() % 2 == 1, "ssim_forward: the window must have an odd length");
  TORCH_CHECK(x.size(0) > 0 && x.size(1) > 0, "ssim_forward: the image is empty");
  x = x.contiguous();
  y = y.to(x.scalar_type()).contiguous();
  g = g.to(x.scalar_type()).contiguous();
  auto S = torch::empty_like(x), A = torch::empty_like(x), B = torch::empty_like(x), C = torch::empty_like(x);
  const int r = static_cast<int>(g.numel() / 2);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "dibrgs_ssim_forward", [&] {
    dibrgs::ssim::forward<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), x.size(0), x.size(1), x.size(2),
                                    g.data_ptr<scalar_t>(), r, S.data_ptr<scalar_t>(), A.data_ptr<scalar_t>(),
                                    B.data_ptr<scalar_t>(), C.data_ptr<scalar_t>());
  });
  return {S, A, B, C};
}

namespace {

// k dS/dx applied to G plus, with wl defined, kl sign(x - y) wl (ssim.h backward); G and wl
// contiguous, of x's dtype.
torch::Tensor ssim_adjoint(const torch::Tensor& G, double k, const torch::Tensor& x, const torch::Tensor& y,
                           const torch::Tensor& A, const torch::Tensor& B, const torch::Tensor& C,
                           const torch::Tensor& g, const torch::Tensor& wl, double kl) {
  auto dx = torch::empty_like(x);
  const int r = static_cast<int>(g.numel() / 2);
  const auto gc = g.to(x.scalar_type()).contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "dibrgs_ssim_backward", [&] {
    dibrgs::ssim::backward<scalar_t>(G.data_ptr<scalar_t>(), static_cast<scalar_t>(k), x.data_ptr<scalar_t>(),
                                     y.data_ptr<scalar_t>(), A.data_ptr<scalar_t>(), B.data_ptr<scalar_t>(),
                                     C.data_ptr<scalar_t>(), x.size(0), x.size(1), x.size(2), gc.data_ptr<scalar_t>(),
                                     r, wl.defined() ? wl.data_ptr<scalar_t>() : nullptr, static_cast<scalar_t>(kl),
                                     dx.data_ptr<scalar_t>());
  });
  return dx;
}

}  // namespace

// Gradient of sum(gS * S) with respect to x (ssim.h), from ssim_forward's factors.
torch::Tensor ssim_backward(torch::Tensor gS, torch::Tensor x, torch::Tensor y, torch::Tensor A, torch::Tensor B,
                            torch::Tensor C, torch::Tensor g) {
  return ssim_adjoint(gS.to(x.scalar_type()).contiguous(), 1.0, x, y, A, B, C, g, torch::Tensor(), 0.0);
}

// The training loss (training/losses.py photometric_loss) of x against y ((H, W, C) each) in one
// node: (1 - lam) sum(|x - y| wl) + lam sum((1 - S) ws) (loss.h), S the SSIM map (window g), wl and
// ws (H, W, C) weights (the plain loss: 1 / (H W C) everywhere and the SSIM interior's 1 / (n C); a
// pseudo view's: mask / (sum(mask) C) for both). Returns {loss (0-d), A, B, C}.
std::vector<torch::Tensor> photometric_forward(torch::Tensor x, torch::Tensor y, torch::Tensor g, torch::Tensor wl,
                                               torch::Tensor ws, double lam) {
  x = x.contiguous();
  y = y.to(x.scalar_type()).contiguous();
  TORCH_CHECK(wl.sizes() == x.sizes() && ws.sizes() == x.sizes(), "photometric_forward: the weights must be (H, W, C)");
  wl = wl.to(x.scalar_type()).contiguous();
  ws = ws.to(x.scalar_type()).contiguous();
  auto f = ssim_forward(x, y, g);
  double sums[2];
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "dibrgs_photometric_forward", [&] {
    dibrgs::loss::sums<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), f[0].data_ptr<scalar_t>(),
                                 wl.data_ptr<scalar_t>(), ws.data_ptr<scalar_t>(), x.numel(), sums);
  });
  auto loss = torch::full({}, (1.0 - lam) * sums[0] + lam * sums[1], x.options());
  return {loss, f[1], f[2], f[3]};
}

// Gradient of photometric_forward's loss with respect to x, times gl (the loss's gradient, 0-d).
torch::Tensor photometric_backward(torch::Tensor gl, torch::Tensor x, torch::Tensor y, torch::Tensor A,
                                   torch::Tensor B, torch::Tensor C, torch::Tensor g, torch::Tensor wl,
                                   torch::Tensor ws, double lam) {
  const double G = gl.item<double>();
  wl = wl.to(x.scalar_type()).contiguous();  // as the forward reads them
  ws = ws.to(x.scalar_type()).contiguous();
  // The SSIM term's upstream gradient is -lam G ws: ws and its factor go to the adjoint apart, the
  // L1 term's gradient is added in the same pass (ssim.h backward).
  return ssim_adjoint(ws, -lam * G, x, y, A, B, C, g, wl, (1.0 - lam) * G);
}

// Expected depth of a render (render/depth.py): depth_acc / alpha where alpha > 0, else 0, for
// float tensors of one shape; and its gradient (g_acc, g_alpha) for the depth's gradient g.
torch::Tensor expected_depth_forward(torch::Tensor acc, torch::Tensor alpha) {
  TORCH_CHECK(acc.sizes() == alpha.sizes() && acc.scalar_type() == alpha.scalar_type() && acc.device().is_cpu(),
              "expected_depth_forward: depth_acc and alpha must be CPU tensors of one shape and dtype");
  acc = acc.contiguous(), alpha = alpha.contiguous();
  auto out = torch::empty_like(acc);
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "dibrgs_expected_depth", [&] {
    const scalar_t *a = acc.data_ptr<scalar_t>(), *w = alpha.data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    at::parallel_for(0, acc.numel(), 1 << 15, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) o[i] = w[i] > 0 ? a[i] / w[i] : scalar_t(0);
    });
  });
  return out;
}

std::vector<torch::Tensor> expected_depth_backward(torch::Tensor g, torch::Tensor acc, torch::Tensor alpha) {
  g = g.contiguous().to(acc.scalar_type()), acc = acc.contiguous(), alpha = alpha.contiguous();
  TORCH_CHECK(g.sizes() == acc.sizes(), "expected_depth_backward: the gradient must match the depth");
  auto ga = torch::empty_like(acc), gw = torch::empty_like(acc);
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "dibrgs_expected_depth_backward", [&] {
    const scalar_t *gp = g.data_ptr<scalar_t>(), *a = acc.data_ptr<scalar_t>(), *w = alpha.data_ptr<scalar_t>();
    scalar_t *pa = ga.data_ptr<scalar_t>(), *pw = gw.data_ptr<scalar_t>();
    at::parallel_for(0, acc.numel(), 1 << 15, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        // Uncovered pixels get exactly 0 (as torch's where does), even for an infinite gradient.
        if (w[i] > 0) {
          const scalar_t inv = scalar_t(1) / w[i];
          pa[i] = gp[i] * inv;
          pw[i] = -gp[i] * (a[i] * inv) * inv;
        } else {
          pa[i] = pw[i] = scalar_t(0);
        }
      }
    });
  });
  return {ga, gw};
}

// The volume regulariser of (N, 3) scales (training/losses.py mean_volume): weight times the mean
// over rows of prod(s / unit), 0 without rows; a 0-d tensor of the scales' dtype.
torch::Tensor volume_forward(torch::Tensor s, double unit, double weight) {
  TORCH_CHECK(s.dim() == 2 && s.size(1) == 3 && s.device().is_cpu(), "volume_forward: scales must be (N, 3) on the CPU");
  TORCH_CHECK(unit > 0.0 && std::isfinite(unit), "volume_forward: unit must be positive and finite");
  s = s.contiguous();
  const int64_t n = s.size(0);
  double total = 0.0;
  AT_DISPATCH_FLOATING_TYPES(s.scalar_type(), "dibrgs_volume_forward", [&] {
    total = dibrgs::loss::volume_sum<scalar_t>(s.data_ptr<scalar_t>(), n, unit);
  });
  return torch::full({}, n > 0 ? weight * total / static_cast<double>(n) : 0.0, s.options());
}

// Gradient of volume_forward with respect to the scales, times g (its 0-d gradient).
torch::Tensor volume_backward(torch::Tensor g, torch::Tensor s, double unit, double weight) {
  s = s.contiguous();
  const int64_t n = s.size(0);
  auto ds = torch::empty_like(s);
  if (n == 0) return ds;
  const double k = g.item<double>() * weight / static_cast<double>(n);
  AT_DISPATCH_FLOATING_TYPES(s.scalar_type(), "dibrgs_volume_backward", [&] {
    dibrgs::loss::volume_grad<scalar_t>(s.data_ptr<scalar_t>(), n, k, unit, ds.data_ptr<scalar_t>());
  });
  return ds;
}

// One Adam step (adam.h) over float32 CPU tensors: params, grads, exp_avgs and exp_avg_sqs
// (same shapes a tensor), steps (float32 scalars, incremented here) and hyper (six numbers a tensor:
// lr, beta1, beta2, eps, weight_decay, decoupled 0/1). Returns false, with nothing changed, when
// any tensor is not a plain contiguous float32 CPU tensor of its parameter's size (the caller then
// takes torch's step): the caller's Python checks cost more than the step on a small model.
bool adam_step(std::vector<torch::Tensor> params, std::vector<torch::Tensor> grads, std::vector<torch::Tensor> exp_avgs,
               std::vector<torch::Tensor> exp_avg_sqs, std::vector<torch::Tensor> steps,
               std::vector<double> hyper) {
  const size_t n = params.size();
  TORCH_CHECK(grads.size() == n && exp_avgs.size() == n && exp_avg_sqs.size() == n && steps.size() == n,
              "adam_step: one grad, exp_avg, exp_avg_sq and step a parameter");
  TORCH_CHECK(hyper.size() == 6 * n, "adam_step: hyper must hold six numbers a parameter");
  for (size_t i = 0; i < n; ++i) {
    for (const auto* t : {&params[i], &grads[i], &exp_avgs[i], &exp_avg_sqs[i]})
      if (!(t->defined() && t->layout() == torch::kStrided && t->scalar_type() == torch::kFloat32 &&
            t->is_contiguous() && t->device().is_cpu() && t->numel() == params[i].numel()))
        return false;
    if (!(steps[i].defined() && steps[i].numel() == 1 && steps[i].scalar_type() == torch::kFloat32 &&
          steps[i].device().is_cpu() && !steps[i].requires_grad()))
      return false;
  }
  const double* h = hyper.data();
  std::vector<dibrgs::adam::Slot> slots(n);
  for (size_t i = 0; i < n; ++i) {
    float* st = steps[i].data_ptr<float>();
    *st += 1.0f;
    const double t = *st, lr = h[6 * i], b1 = h[6 * i + 1], b2 = h[6 * i + 2], eps = h[6 * i + 3],
                 wd = h[6 * i + 4];
    const bool decoupled = h[6 * i + 5] != 0.0;
    dibrgs::adam::Slot& s = slots[i];
    s.p = params[i].data_ptr<float>();
    s.g = grads[i].data_ptr<float>();
    s.m = exp_avgs[i].data_ptr<float>();
    s.v = exp_avg_sqs[i].data_ptr<float>();
    s.n = params[i].numel();
    s.decay = static_cast<float>(decoupled && wd != 0.0 ? 1.0 - lr * wd : 1.0);
    s.l2 = static_cast<float>(decoupled ? 0.0 : wd);
    s.one_m_b1 = static_cast<float>(1.0 - b1);
    s.b2 = static_cast<float>(b2);
    s.one_m_b2 = static_cast<float>(1.0 - b2);
    s.bc2_sqrt = static_cast<float>(std::sqrt(1.0 - std::pow(b2, t)));
    s.eps = static_cast<float>(eps);
    s.neg_step = static_cast<float>(-lr / (1.0 - std::pow(b1, t)));
  }
  dibrgs::adam::run(slots, 4096);
  // Written in place through their data: bump the version counters as torch's in-place operators
  // do, so that caches keyed on a parameter's version (the IBR features) see the change.
  for (size_t i = 0; i < n; ++i)
    for (auto* t : {&params[i], &exp_avgs[i], &exp_avg_sqs[i], &steps[i]}) torch::autograd::impl::bump_version(*t);
  return true;
}

// Neural Gaussians of the visible anchors (spawn.h): nop (M k), color (M, 3 k), cov (M, 7 k),
// anchor (M, 3), log_scal (M, 6), offset (M, k, 3), one dtype, contiguous. Returns {means (S, 3),
// quats (S, 4), scales (S, 3), opacities (S), colors (S, 3), start (M + 1) int64, selected (M k)
// bool: the rows kept}.
std::vector<torch::Tensor> spawn_forward(torch::Tensor nop, torch::Tensor color, torch::Tensor cov,
                                         torch::Tensor anchor, torch::Tensor log_scal, torch::Tensor offset) {
  const int64_t M = anchor.size(0), k = offset.dim() == 3 ? offset.size(1) : 0;
  TORCH_CHECK(anchor.dim() == 2 && anchor.size(1) == 3 && log_scal.sizes() == torch::IntArrayRef({M, 6}) &&
                  offset.sizes() == torch::IntArrayRef({M, k, 3}) && nop.numel() == M * k &&
                  color.sizes() == torch::IntArrayRef({M, 3 * k}) && cov.sizes() == torch::IntArrayRef({M, 7 * k}),
              "spawn_forward: shapes must be nop (M k), color (M, 3 k), cov (M, 7 k), anchor (M, 3), log_scal (M, 6), "
              "offset (M, k, 3)");
  for (const auto* t : {&nop, &color, &cov, &anchor, &log_scal, &offset})
    TORCH_CHECK(t->scalar_type() == anchor.scalar_type() && t->is_contiguous() && t->device().is_cpu(),
                "spawn_forward: tensors must be contiguous CPU tensors of one dtype");
  auto start = torch::empty({M + 1}, torch::kInt64);
  auto selected = torch::empty({M * k}, torch::kBool);
  std::vector<torch::Tensor> out;
  AT_DISPATCH_FLOATING_TYPES(anchor.scalar_type(), "dibrgs_spawn_forward", [&] {
    const int64_t S = dibrgs::spawn::count<scalar_t>(nop.data_ptr<scalar_t>(), M, k, start.data_ptr<int64_t>(),
                                                     selected.data_ptr<bool>());
    auto o = anchor.options();
    out = {torch::empty({S, 3}, o), torch::empty({S, 4}, o), torch::empty({S, 3}, o), torch::empty({S}, o),
           torch::empty({S, 3}, o)};
    dibrgs::spawn::forward<scalar_t>(nop.data_ptr<scalar_t>(), color.data_ptr<scalar_t>(), cov.data_ptr<scalar_t>(),
                                     anchor.data_ptr<scalar_t>(), log_scal.data_ptr<scalar_t>(),
                                     offset.data_ptr<scalar_t>(), M, k, start.data_ptr<int64_t>(),
                                     out[0].data_ptr<scalar_t>(), out[1].data_ptr<scalar_t>(),
                                     out[2].data_ptr<scalar_t>(), out[3].data_ptr<scalar_t>(),
                                     out[4].data_ptr<scalar_t>());
  });
  out.push_back(start);
  out.push_back(selected);
  return out;
}

// Rows idx (M,) int64 of each src (N, ...) (rows.h gather): returns the (M, ...) tensors and
// whether idx is strictly increasing (the backward's case). One call for all of a model's
// per-anchor parameters: each autograd node costs tens of microseconds in Python.
std::tuple<std::vector<torch::Tensor>, bool> take_rows_forward(std::vector<torch::Tensor> srcs, torch::Tensor idx) {
  TORCH_CHECK(idx.dim() == 1 && idx.scalar_type() == torch::kInt64, "take_rows: idx must be (M,) int64");
  auto ix = idx.contiguous();
  const int64_t M = ix.size(0);
  const int64_t* pi = ix.data_ptr<int64_t>();
  // The indices' range once, checked against each source's rows.
  const int64_t lo = M ? *std::min_element(pi, pi + M) : 0, hi = M ? *std::max_element(pi, pi + M) : -1;
  std::vector<torch::Tensor> outs;
  for (const auto& src : srcs) {
    TORCH_CHECK(src.dim() >= 1, "take_rows: a source has no rows");
    auto s = src.contiguous();
    const int64_t N = s.size(0), D = N ? s.numel() / N : 0;
    TORCH_CHECK(lo >= 0 && hi < N, "take_rows: index ", lo < 0 ? lo : hi, " out of range for ", N, " rows");
    auto sizes = s.sizes().vec();
    sizes[0] = M;
    auto out = torch::empty(sizes, s.options());
    AT_DISPATCH_FLOATING_TYPES(s.scalar_type(), "dibrgs_take_rows", [&] {
      dibrgs::rows::gather<scalar_t>(s.data_ptr<scalar_t>(), pi, M, D, out.data_ptr<scalar_t>());
    });
    outs.push_back(out);
  }
  return {outs, dibrgs::rows::strictly_increasing(pi, M)};
}

// Gradient of take_rows_forward for strictly increasing idx (rows.h scatter): for each upstream
// gradient (M, ...), the (N, ...) gradient of its source.
std::vector<torch::Tensor> take_rows_backward(std::vector<torch::Tensor> grads, torch::Tensor idx, int64_t N) {
  auto ix = idx.contiguous();
  const int64_t M = ix.size(0);
  std::vector<torch::Tensor> outs;
  for (const auto& g : grads) {
    auto gc = g.contiguous();
    const int64_t D = M ? gc.numel() / M : 0;
    auto sizes = gc.sizes().vec();
    sizes[0] = N;
    auto out = torch::empty(sizes, gc.options());
    if (M == 0) {
      outs.push_back(out.zero_());
      continue;
    }
    AT_DISPATCH_FLOATING_TYPES(gc.scalar_type(), "dibrgs_take_rows_backward", [&] {
      dibrgs::rows::scatter<scalar_t>(gc.data_ptr<scalar_t>(), ix.data_ptr<int64_t>(), M, N, D,
                                      out.data_ptr<scalar_t>());
    });
    outs.push_back(out);
  }
  return outs;
}

// Positions (int64, increasing) of the true entries of a 1-d bool tensor: torch.nonzero(mask)[:, 0].
// One pass on the calling thread; torch's nonzero (a count, an allocation, a fill through
// TensorIterator) cost 40 us a step for 2,900 anchors and 150-300 us for 29,000.
torch::Tensor true_indices(torch::Tensor mask) {
  TORCH_CHECK(mask.dim() == 1 && mask.scalar_type() == torch::kBool && mask.device().is_cpu(),
              "true_indices: the mask must be a 1-d bool CPU tensor");
  mask = mask.contiguous();
  const bool* m = mask.data_ptr<bool>();
  const int64_t n = mask.numel();
  auto out = torch::empty({std::count(m, m + n, true)}, torch::kInt64);
  int64_t* o = out.data_ptr<int64_t>();
  for (int64_t i = 0; i < n; ++i)
    if (m[i]) *o++ = i;
  return out;
}

// Growth statistics of one view (strategy/anchor.py, strategy/densify.py), in place: for the i-th
// rasterized Gaussian with visible[i], the norm of its screen-space gradient in pixels,
// sqrtf(fma(gy, gy, gx gx)) with gx = grad[i, 0] sx, gy = grad[i, 1] sy (torch's norm over the
// pair, to the bit; NaN and +inf count 0), is added to acc[slot] and 1 to denom[slot] (float32).
// slot = i, or with anchors (aidx (M) the visible anchors, selected (M k) bool which of their k
// offsets were rasterized, in order) aidx[p / k] k + p % k for the offset p of the i-th Gaussian.
// Each masked torch read or write was a nonzero and a gather: about 1.5 ms a 256x256 step.
void grad_norm_stats(torch::Tensor acc, torch::Tensor denom, torch::Tensor grad, torch::Tensor visible, double sx,
                     double sy, torch::Tensor aidx, torch::Tensor selected, int64_t k) {
  TORCH_CHECK(acc.scalar_type() == torch::kFloat32 && denom.scalar_type() == torch::kFloat32 && acc.is_contiguous() &&
                  denom.is_contiguous() && acc.numel() == denom.numel() && acc.device().is_cpu(),
              "grad_norm_stats: acc and denom must be contiguous float32 CPU tensors of one length");
  const int64_t G = visible.numel();
  TORCH_CHECK(visible.scalar_type() == torch::kBool && grad.dim() == 2 && grad.size(0) == G && grad.size(1) == 2 &&
                  grad.scalar_type() == torch::kFloat32,
              "grad_norm_stats: grad must be (G, 2) float32 and visible (G,) bool");
  const bool anchors = aidx.numel() > 0 || selected.numel() > 0;
  TORCH_CHECK(!anchors || (aidx.scalar_type() == torch::kInt64 && selected.scalar_type() == torch::kBool && k > 0 &&
                           selected.numel() == aidx.numel() * k),
              "grad_norm_stats: selected must hold k entries an anchor of aidx");
  const auto g = grad.contiguous();
  const auto vis = visible.contiguous(), ai = aidx.contiguous(), sel = selected.contiguous();
  const float* pg = g.data_ptr<float>();
  const bool* pv = vis.data_ptr<bool>();
  const int64_t* pa = anchors ? ai.data_ptr<int64_t>() : nullptr;
  const bool* ps = anchors ? sel.data_ptr<bool>() : nullptr;
  const int64_t P = anchors ? sel.numel() : G, n = acc.numel(), M = ai.numel();
  // Checked before anything is added: an error leaves the sums as they were.
  if (anchors) {
    const int64_t ns = std::count(ps, ps + P, true);
    TORCH_CHECK(ns == G, "grad_norm_stats: ", ns, " selected offsets for ", G, " rasterized Gaussians");
    TORCH_CHECK(M == 0 || (*std::min_element(pa, pa + M) >= 0 && (*std::max_element(pa, pa + M) + 1) * k <= n),
                "grad_norm_stats: an anchor's slots outside acc");
  } else {
    TORCH_CHECK(G <= n, "grad_norm_stats: more Gaussians than slots");
  }
  float* pacc = acc.data_ptr<float>();
  float* pden = denom.data_ptr<float>();
  const float fx = static_cast<float>(sx), fy = static_cast<float>(sy);
  int64_t i = 0;  // the rasterized Gaussian of slot p
  for (int64_t p = 0; p < P; ++p) {
    if (anchors && !ps[p]) continue;
    if (pv[i]) {
      const int64_t slot = anchors ? pa[p / k] * k + p % k : i;
      const float gx = pg[2 * i] * fx, gy = pg[2 * i + 1] * fy;
      float v = std::sqrt(std::fma(gy, gy, gx * gx));
      if (std::isnan(v) || std::isinf(v)) v = 0.0f;
      pacc[slot] += v;
      pden[slot] += 1.0f;
    }
    ++i;
  }
}

// The IBR projection P (project_rows.h) of the rows of rows (N, K) that mask (N,) bool selects (all
// of them when mask is empty): weights one (C, D_l, ...) a level, biases one (C,) a level, the D_l
// summing to K - 1. Returns out (M, C) and the selected rows' indices (M,) for the backward.
std::vector<torch::Tensor> project_rows_forward(torch::Tensor rows, torch::Tensor mask,
                                                std::vector<torch::Tensor> weights, std::vector<torch::Tensor> biases) {
  TORCH_CHECK(rows.dim() == 2 && rows.device().is_cpu(), "project_rows: rows must be (N, K) on the CPU");
  TORCH_CHECK(!weights.empty() && weights.size() == biases.size(), "project_rows: one weight and one bias a level");
  const int64_t N = rows.size(0), K = rows.size(1), C = weights[0].size(0);
  const auto dt = rows.scalar_type();
  auto x = rows.contiguous();
  torch::Tensor idx;
  if (mask.numel() == 0) {
    idx = torch::arange(N, torch::kInt64);
  } else {
    TORCH_CHECK(mask.dim() == 1 && mask.size(0) == N && mask.scalar_type() == torch::kBool,
                "project_rows: mask must be (N,) bool");
    idx = true_indices(mask);
  }
  // Wt (K, C): each level's weight transposed into its rows, the biases summed in the last (plain
  // loops: as ATen operators this assembly was a dozen dispatches a call).
  std::vector<at::Tensor> w(weights.size()), b(biases.size());
  int64_t width = 0;
  for (size_t l = 0; l < weights.size(); ++l) {
    TORCH_CHECK(weights[l].size(0) == C && biases[l].numel() == C && weights[l].scalar_type() == dt &&
                    biases[l].scalar_type() == dt,
                "project_rows: every level's weight (C, ...) and bias (C,) in the rows' dtype");
    w[l] = weights[l].contiguous(), b[l] = biases[l].contiguous();
    width += w[l].numel() / C;
  }
  TORCH_CHECK(width == K - 1, "project_rows: the levels' widths sum to ", width, ", the rows have ", K - 1,
              " feature columns");
  const int64_t M = idx.size(0);
  auto Wt = torch::empty({K, C}, x.options());
  auto out = torch::empty({M, C}, x.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_project_rows", [&] {
    scalar_t* pw = Wt.data_ptr<scalar_t>();
    int64_t start = 0;
    std::fill(pw + (K - 1) * C, pw + K * C, scalar_t(0));
    for (size_t l = 0; l < w.size(); ++l) {
      const int64_t D = w[l].numel() / C;
      const scalar_t* src = w[l].data_ptr<scalar_t>();
      const scalar_t* bias = b[l].data_ptr<scalar_t>();
      for (int64_t c = 0; c < C; ++c) {
        for (int64_t j = 0; j < D; ++j) pw[(start + j) * C + c] = src[c * D + j];
        pw[(K - 1) * C + c] += bias[c];
      }
      start += D;
    }
    dibrgs::prows::forward<scalar_t>(x.data_ptr<scalar_t>(), idx.data_ptr<int64_t>(), M, K, pw, C,
                                     out.data_ptr<scalar_t>());
  });
  return {out, idx};
}

// Gradients of project_rows_forward's weights (one a level, shaped as shapes[l]) and biases (one (C,)
// tensor a level, all equal: the biases are summed) from g (M, C), the rows and the indices it returned.
std::vector<torch::Tensor> project_rows_backward(torch::Tensor g, torch::Tensor rows, torch::Tensor idx,
                                                 std::vector<std::vector<int64_t>> shapes) {
  const int64_t M = idx.size(0), K = rows.size(1), C = g.size(1);
  TORCH_CHECK(g.dim() == 2 && g.size(0) == M, "project_rows_backward: g must be (M, C)");
  const auto dt = rows.scalar_type();
  auto gc = g.to(dt).contiguous(), x = rows.contiguous();
  std::vector<torch::Tensor> grads;
  for (const auto& shape : shapes) grads.push_back(torch::empty(shape, x.options()));
  for (size_t l = 0; l < shapes.size(); ++l) grads.push_back(torch::empty({C}, x.options()));
  AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_project_rows_backward", [&] {
    std::vector<scalar_t> G(static_cast<size_t>(K * C));
    dibrgs::prows::weight_grad<scalar_t>(gc.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(), idx.data_ptr<int64_t>(), M,
                                         K, C, G.data());
    // G (K, C) back into each level's (C, D_l) weight gradient; every bias gets the last row.
    const size_t n = shapes.size();
    int64_t start = 0;
    for (size_t l = 0; l < n; ++l) {
      const int64_t D = grads[l].numel() / C;
      TORCH_CHECK(grads[l].size(0) == C && start + D <= K - 1, "project_rows_backward: shapes do not fit the rows");
      scalar_t* gw = grads[l].data_ptr<scalar_t>();
      scalar_t* gb = grads[n + l].data_ptr<scalar_t>();
      for (int64_t c = 0; c < C; ++c) {
        for (int64_t j = 0; j < D; ++j) gw[c * D + j] = G[(start + j) * C + c];
        gb[c] = G[(K - 1) * C + c];
      }
      start += D;
    }
  });
  return grads;
}

// Frustum culling of anchors (spawn.h visible): anchor (N, 3), offset (N, k, 3), log_scaling (N, 6)
// of one dtype, K (3, 3) pixels, w2c (4, 4) world-to-camera. Returns (N,) bool.
torch::Tensor anchor_visibility(torch::Tensor anchor, torch::Tensor offset, torch::Tensor log_scaling, torch::Tensor K,
                                torch::Tensor w2c, int64_t W, int64_t H, double near) {
  const int64_t N = anchor.size(0), k = offset.dim() == 3 ? offset.size(1) : 0;
  TORCH_CHECK(anchor.dim() == 2 && anchor.size(1) == 3 && offset.sizes() == torch::IntArrayRef({N, k, 3}) &&
                  log_scaling.sizes() == torch::IntArrayRef({N, 6}),
              "anchor_visibility: shapes must be anchor (N, 3), offset (N, k, 3), log_scaling (N, 6)");
  const auto dt = anchor.scalar_type();
  auto a = anchor.contiguous(), o = offset.to(dt).contiguous(), l = log_scaling.to(dt).contiguous();
  const auto cam = camera_params(K, w2c);
  auto out = torch::empty({N}, torch::kBool);
  AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_anchor_visibility", [&] {
    dibrgs::spawn::visible<scalar_t>(a.data_ptr<scalar_t>(), o.data_ptr<scalar_t>(), l.data_ptr<scalar_t>(), N, k,
                                     cam.data(), W, H, near, out.data_ptr<bool>());
  });
  return out;
}

// Gradients {nop, color, cov, anchor, log_scal, offset} of spawn_forward's inputs from those of its
// outputs (gmeans, gquats, gscales, gopac, gcolors) and the inputs it saved.
std::vector<torch::Tensor> spawn_backward(torch::Tensor gmeans, torch::Tensor gquats, torch::Tensor gscales,
                                          torch::Tensor gopac, torch::Tensor gcolors, torch::Tensor nop,
                                          torch::Tensor cov, torch::Tensor log_scal, torch::Tensor offset,
                                          torch::Tensor start) {
  const int64_t M = log_scal.size(0), k = offset.size(1), S = start.data_ptr<int64_t>()[M];
  TORCH_CHECK(gmeans.numel() == 3 * S && gquats.numel() == 4 * S && gscales.numel() == 3 * S && gopac.numel() == S &&
                  gcolors.numel() == 3 * S,
              "spawn_backward: output gradients must match the forward's outputs");
  const auto dt = log_scal.scalar_type();
  gmeans = gmeans.to(dt).contiguous(), gquats = gquats.to(dt).contiguous(), gscales = gscales.to(dt).contiguous();
  gopac = gopac.to(dt).contiguous();
  // The colours' gradient is the compositing's feature gradient without its depth and alpha
  // columns: read with its row stride rather than copied (a strided copy cost 0.13 ms a step).
  const bool rows_strided = gcolors.dim() == 2 && gcolors.size(1) == 3 && gcolors.stride(1) == 1 &&
                            gcolors.stride(0) >= 3 && gcolors.scalar_type() == dt;
  if (!rows_strided) gcolors = gcolors.to(dt).contiguous();
  const int64_t gcs = rows_strided ? gcolors.stride(0) : 3;
  auto dnop = torch::empty_like(nop), dcov = torch::empty_like(cov), dlog_scal = torch::empty_like(log_scal);
  auto doffset = torch::empty_like(offset), danchor = torch::empty({M, 3}, log_scal.options());
  auto dcolor = torch::empty({M, 3 * k}, log_scal.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_spawn_backward", [&] {
    dibrgs::spawn::backward<scalar_t>(
        gmeans.data_ptr<scalar_t>(), gquats.data_ptr<scalar_t>(), gscales.data_ptr<scalar_t>(),
        gopac.data_ptr<scalar_t>(), gcolors.data_ptr<scalar_t>(), gcs, nop.data_ptr<scalar_t>(),
        cov.data_ptr<scalar_t>(),
        log_scal.data_ptr<scalar_t>(), offset.data_ptr<scalar_t>(), M, k, start.data_ptr<int64_t>(),
        dnop.data_ptr<scalar_t>(), dcolor.data_ptr<scalar_t>(), dcov.data_ptr<scalar_t>(),
        danchor.data_ptr<scalar_t>(), dlog_scal.data_ptr<scalar_t>(), doffset.data_ptr<scalar_t>());
  });
  return {dnop, dcolor, dcov, danchor, dlog_scal, doffset};
}

namespace {

// The decoder's layers from the bindings' lists (contiguous: the biases are read as arrays; not
// detached, see below_autograd; decoder::for_blocks sets the same guard on its threads), checked
// against feat (M, F) and ibr (M, C).
dibrgs::decoder::Weights decoder_weights(const torch::Tensor& feat, const torch::Tensor& ibr,
                                         const std::vector<torch::Tensor>& fusion, const std::vector<torch::Tensor>& W1,
                                         const std::vector<torch::Tensor>& b1, const std::vector<torch::Tensor>& W2,
                                         const std::vector<torch::Tensor>& b2, const std::vector<int64_t>& acts) {
  const int64_t F = feat.size(1), D = F + 4, C = ibr.dim() == 2 ? ibr.size(1) : 0;
  const size_t nh = W1.size();
  TORCH_CHECK(b1.size() == nh && W2.size() == nh && b2.size() == nh && acts.size() == nh,
              "decoder: W1, b1, W2, b2 and acts one per head");
  TORCH_CHECK(fusion.empty() || fusion.size() == 4, "decoder: fusion is [] or [Wref, bref, Wmod, bmod]");
  const auto dt = feat.scalar_type();
  auto check = [&](const torch::Tensor& t, torch::IntArrayRef shape, const char* what) {
    TORCH_CHECK(t.sizes() == shape && t.scalar_type() == dt && t.device().is_cpu(), "decoder: ", what,
                " must be ", shape, " of the features' dtype, got ", t.sizes());
    return t.contiguous();
  };
  dibrgs::decoder::Weights w;
  if (!fusion.empty()) {
    TORCH_CHECK(C > 0 && ibr.size(0) == feat.size(0), "decoder: fusion needs the IBR features (M, C)");
    w.Wref = check(fusion[0], {F, C}, "Wref"), w.bref = check(fusion[1], {F}, "bref");
    w.Wmod = check(fusion[2], {F, C}, "Wmod"), w.bmod = check(fusion[3], {F}, "bmod");
  }
  for (size_t h = 0; h < nh; ++h) {
    const int64_t H = W1[h].size(0), O = W2[h].size(0);
    TORCH_CHECK(acts[h] >= 0 && acts[h] <= 2, "decoder: activation codes are 0-2");
    w.W1.push_back(check(W1[h], {H, D}, "W1"));
    w.b1.push_back(check(b1[h], {H}, "b1"));
    w.W2.push_back(check(W2[h], {O, H}, "W2"));
    w.b2.push_back(check(b2[h], {O}, "b2"));
    w.acts.push_back(static_cast<dibrgs::decoder::Act>(acts[h]));
  }
  return w;
}

}  // namespace

// The decoder (decoder.h) of M visible anchors: feat (M, F) their own features, ibr (M, C) their
// IBR features (unused without fusion), fusion [] or [Wref (F, C), bref, Wmod (F, C), bmod],
// anchor (M, 3), centre (3), dist_scale, and per head W1 (H, F + 4), b1, W2 (O, H), b2 and its
// activation. Returns the heads' outputs (M, O_h), then what decoder_backward needs: x (M, F + 4),
// dist (M), gate and ref (M, F; empty without fusion), the hidden activations (M, H_h).
std::vector<torch::Tensor> decoder_forward(torch::Tensor feat, torch::Tensor ibr, std::vector<torch::Tensor> fusion,
                                           torch::Tensor anchor, torch::Tensor centre, double dist_scale,
                                           std::vector<torch::Tensor> W1, std::vector<torch::Tensor> b1,
                                           std::vector<torch::Tensor> W2, std::vector<torch::Tensor> b2,
                                           std::vector<int64_t> acts) {
  TORCH_CHECK(feat.dim() == 2 && feat.device().is_cpu(), "decoder_forward: feat must be (M, F) on the CPU");
  feat = feat.contiguous();
  const int64_t M = feat.size(0), F = feat.size(1), D = F + 4;
  const auto dt = feat.scalar_type();
  TORCH_CHECK(anchor.sizes() == torch::IntArrayRef({M, 3}) && centre.numel() == 3 && anchor.scalar_type() == dt &&
                  centre.scalar_type() == dt,
              "decoder_forward: anchor must be (M, 3) and centre (3), of the features' dtype");
  anchor = anchor.contiguous(), centre = centre.contiguous();
  const auto w = decoder_weights(feat, ibr, fusion, W1, b1, W2, b2, acts);
  if (w.fusion()) ibr = ibr.contiguous();
  const size_t nh = w.W1.size();
  const auto o = feat.options();
  dibrgs::decoder::Saved sv;
  sv.x = torch::empty({M, D}, o), sv.dist = torch::empty({M}, o);
  sv.gate = torch::empty({w.fusion() ? M : 0, F}, o), sv.ref = torch::empty({w.fusion() ? M : 0, F}, o);
  std::vector<torch::Tensor> W1t, W2t;
  for (size_t h = 0; h < nh; ++h) {
    W1t.push_back(w.W1[h].t()), W2t.push_back(w.W2[h].t());
    sv.hidden.push_back(torch::empty({M, w.W1[h].size(0)}, o));
    sv.out.push_back(torch::empty({M, w.W2[h].size(0)}, o));
  }
  const torch::Tensor WmodT = w.fusion() ? w.Wmod.t() : torch::Tensor(), WrefT = w.fusion() ? w.Wref.t() : torch::Tensor();
  // y = x W^T + b (+ ReLU) into the rows of out: the product, then the bias (decoder.h add_bias).
  auto linear = [&](torch::Tensor& y, const torch::Tensor& x, const torch::Tensor& Wt, const torch::Tensor& b,
                    bool relu) {
    at::mm_out(y, x, Wt);
    AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_decoder_bias", [&] {
      dibrgs::decoder::add_bias<scalar_t>(y.data_ptr<scalar_t>(), b.data_ptr<scalar_t>(), y.size(0), y.size(1), relu);
    });
  };
  dibrgs::decoder::for_blocks(M, dibrgs::decoder::blocks(M), [&](int64_t, int64_t r0, int64_t n) {
    if (w.fusion()) {
      const auto vs = ibr.narrow(0, r0, n);
      auto gs = sv.gate.narrow(0, r0, n), es = sv.ref.narrow(0, r0, n);
      linear(gs, vs, WmodT, w.bmod, false);
      gs.sigmoid_();
      linear(es, vs, WrefT, w.bref, false);
    }
    AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_decoder_input", [&] {
      const scalar_t* g = w.fusion() ? sv.gate.data_ptr<scalar_t>() + r0 * F : nullptr;
      const scalar_t* e = w.fusion() ? sv.ref.data_ptr<scalar_t>() + r0 * F : nullptr;
      dibrgs::decoder::input_rows<scalar_t>(feat.data_ptr<scalar_t>() + r0 * F, g, e,
                                            anchor.data_ptr<scalar_t>() + r0 * 3, centre.data_ptr<scalar_t>(),
                                            dist_scale, sv.x.data_ptr<scalar_t>() + r0 * D,
                                            sv.dist.data_ptr<scalar_t>() + r0, n, F);
    });
    const auto xs = sv.x.narrow(0, r0, n);
    for (size_t h = 0; h < nh; ++h) {
      auto hs = sv.hidden[h].narrow(0, r0, n), os = sv.out[h].narrow(0, r0, n);
      linear(hs, xs, W1t[h], w.b1[h], true);
      linear(os, hs, W2t[h], w.b2[h], false);
      if (w.acts[h] == dibrgs::decoder::TANH)  // ATen's vectorised tanh / sigmoid: scalar ones cost 10x
        os.tanh_();
      else if (w.acts[h] == dibrgs::decoder::SIGMOID)
        os.sigmoid_();
    }
  });
  std::vector<torch::Tensor> res(sv.out);
  res.insert(res.end(), {sv.x, sv.dist, sv.gate, sv.ref});
  res.insert(res.end(), sv.hidden.begin(), sv.hidden.end());
  return res;
}

// Gradients of decoder_forward from those of its outputs (gout[h] (M, O_h)) and what it returned
// for this: {dfeat (M, F), danchor (M, 3), dibr (M, C; empty without fusion or want_dibr), then
// with fusion dWref, dbref, dWmod, dbmod, then per head dW1, db1, dW2, db2}.
std::vector<torch::Tensor> decoder_backward(std::vector<torch::Tensor> gout, torch::Tensor ibr,
                                            std::vector<torch::Tensor> fusion, torch::Tensor x, torch::Tensor dist,
                                            torch::Tensor gate, torch::Tensor ref, std::vector<torch::Tensor> hidden,
                                            std::vector<torch::Tensor> out, double dist_scale,
                                            std::vector<torch::Tensor> W1, std::vector<torch::Tensor> b1,
                                            std::vector<torch::Tensor> W2, std::vector<torch::Tensor> b2,
                                            std::vector<int64_t> acts, bool want_dibr) {
  const int64_t M = x.size(0), D = x.size(1), F = D - 4;
  const auto feat_like = x.narrow(1, 0, F);
  const auto w = decoder_weights(feat_like, ibr, fusion, W1, b1, W2, b2, acts);
  const size_t nh = w.W1.size();
  TORCH_CHECK(gout.size() == nh && hidden.size() == nh && out.size() == nh,
              "decoder_backward: one gradient, hidden and output a head");
  const auto dt = x.scalar_type();
  const auto o = x.options();
  for (size_t h = 0; h < nh; ++h) {
    gout[h] = gout[h].to(dt).contiguous();
    TORCH_CHECK(gout[h].sizes() == out[h].sizes(), "decoder_backward: gradient ", h, " must match its output");
  }
  if (w.fusion()) ibr = ibr.contiguous();
  const int64_t C = w.fusion() ? ibr.size(1) : 0, nb = dibrgs::decoder::blocks(M);
  auto dx = torch::empty({M, D}, o), dfeat = torch::empty({M, F}, o), danchor = torch::empty({M, 3}, o);
  auto dibr = torch::empty({w.fusion() && want_dibr ? M : 0, C}, o);
  auto dpre_gate = torch::empty({w.fusion() ? M : 0, F}, o), dref = torch::empty({w.fusion() ? M : 0, F}, o);
  // Per block partial weight gradients, summed over the blocks at the end (zeros: no rows, no
  // block). One buffer (nb, total) holds every layer's, so that the zeroing and the sum are one
  // operator each instead of two a tensor.
  std::vector<std::vector<int64_t>> shapes;  // each partial's shape, in the buffer's order
  if (w.fusion()) shapes = {{F, C}, {F}, {F, C}, {F}};  // Wref, bref, Wmod, bmod
  for (size_t h = 0; h < nh; ++h) {
    const int64_t H = w.W1[h].size(0), O = w.W2[h].size(0);
    shapes.insert(shapes.end(), {{H, D}, {H}, {O, H}, {O}});  // W1, b1, W2, b2
  }
  std::vector<int64_t> starts{0};
  for (const auto& sh : shapes) {
    int64_t n = 1;
    for (const int64_t d : sh) n *= d;
    starts.push_back(starts.back() + n);
  }
  auto partial = torch::zeros({nb, starts.back()}, o);
  auto part = [&](size_t k) {  // (nb, shape...) view of partial k: its rows b are contiguous, not the view
    std::vector<int64_t> sh{nb};
    sh.insert(sh.end(), shapes[k].begin(), shapes[k].end());
    return partial.narrow(1, starts[k], starts[k + 1] - starts[k]).view(sh);
  };
  const size_t first_head = w.fusion() ? 4 : 0;
  std::vector<torch::Tensor> dW1, db1, dW2, db2;
  for (size_t h = 0; h < nh; ++h) {
    const size_t k = first_head + 4 * h;
    dW1.push_back(part(k)), db1.push_back(part(k + 1)), dW2.push_back(part(k + 2)), db2.push_back(part(k + 3));
  }
  torch::Tensor dWref, dbref, dWmod, dbmod;  // read only with fusion
  if (w.fusion()) dWref = part(0), dbref = part(1), dWmod = part(2), dbmod = part(3);
  dibrgs::decoder::for_blocks(M, nb, [&](int64_t b, int64_t r0, int64_t n) {
    const auto xs = x.narrow(0, r0, n);
    auto dxs = dx.narrow(0, r0, n);
    for (size_t h = 0; h < nh; ++h) {
      const int64_t H = w.W1[h].size(0), O = w.W2[h].size(0);
      const auto hs = hidden[h].narrow(0, r0, n);
      // Without an activation the pre-activation's gradient is the output's (a copy of it was
      // 0.75 MB written and read again a 256x256 step for the covariance head).
      auto gz = w.acts[h] == dibrgs::decoder::NONE ? gout[h].narrow(0, r0, n) : torch::empty({n, O}, o);
      auto gw2 = dW2[h][b], gw1 = dW1[h][b];
      AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_decoder_output_grad", [&] {
        dibrgs::decoder::output_grad<scalar_t>(gout[h].data_ptr<scalar_t>() + r0 * O,
                                               out[h].data_ptr<scalar_t>() + r0 * O, gz.data_ptr<scalar_t>(),
                                               db2[h][b].data_ptr<scalar_t>(), n, O, w.acts[h]);
      });
      at::mm_out(gw2, gz.t(), hs);
      auto gh = at::mm(gz, w.W2[h]);
      AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_decoder_relu_grad", [&] {
        dibrgs::decoder::relu_grad<scalar_t>(gh.data_ptr<scalar_t>(), hs.data_ptr<scalar_t>(),
                                             db1[h][b].data_ptr<scalar_t>(), n, H);
      });
      at::mm_out(gw1, gh.t(), xs);
      if (h == 0)
        at::mm_out(dxs, gh, w.W1[h]);
      else
        dxs.addmm_(gh, w.W1[h]);
    }
    AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_decoder_input_grad", [&] {
      const bool f = w.fusion();
      dibrgs::decoder::input_grad<scalar_t>(
          dx.data_ptr<scalar_t>() + r0 * D, x.data_ptr<scalar_t>() + r0 * D, dist.data_ptr<scalar_t>() + r0,
          f ? gate.data_ptr<scalar_t>() + r0 * F : nullptr, f ? ref.data_ptr<scalar_t>() + r0 * F : nullptr,
          dist_scale, dfeat.data_ptr<scalar_t>() + r0 * F, danchor.data_ptr<scalar_t>() + r0 * 3,
          f ? dpre_gate.data_ptr<scalar_t>() + r0 * F : nullptr, f ? dref.data_ptr<scalar_t>() + r0 * F : nullptr,
          f ? dbmod[b].data_ptr<scalar_t>() : nullptr, f ? dbref[b].data_ptr<scalar_t>() : nullptr, n, F);
    });
    if (w.fusion()) {
      const auto vs = ibr.narrow(0, r0, n), dgs = dpre_gate.narrow(0, r0, n), des = dref.narrow(0, r0, n);
      auto gwm = dWmod[b], gwr = dWref[b];
      at::mm_out(gwm, dgs.t(), vs);
      at::mm_out(gwr, des.t(), vs);
      if (want_dibr) {
        auto dvs = dibr.narrow(0, r0, n);
        at::mm_out(dvs, dgs, w.Wmod);
        dvs.addmm_(des, w.Wref);
      }
    }
  });
  // Summed over the blocks, then cut into the layers' gradients: contiguous views of one tensor
  // (they become the parameters' .grad as they are; nothing writes one through another).
  // Added into block 0's row in place: partial.sum(0), a reduction through TensorIterator, took
  // about 60 us of the calling thread's time a step for some ten thousand values.
  const auto total = partial[0];
  AT_DISPATCH_FLOATING_TYPES(dt, "dibrgs_decoder_partial_sum", [&] {
    scalar_t* t0 = partial.data_ptr<scalar_t>();  // (nb, n), contiguous: block b's row at b n
    const int64_t n = starts.back();
    for (int64_t b = 1; b < nb; ++b)
      for (int64_t i = 0; i < n; ++i) t0[i] += t0[b * n + i];
  });
  std::vector<torch::Tensor> res{dfeat, danchor, dibr};
  for (size_t k = 0; k < shapes.size(); ++k)
    res.push_back(total.narrow(0, starts[k], starts[k + 1] - starts[k]).view(shapes[k]));
  return res;
}

// The neural Gaussians of the visible anchors (models/visible.py) in one call each way: the rows
// idx (strictly increasing) of the model's per-anchor tensors srcs = {anchor (N, 3), feat (N, F),
// scaling (N, 6), offset (N, k, 3)} (take_rows_forward), the decoder (decoder_forward; three
// heads: opacity (M, k), covariance (M, 7 k), colour (M, 3 k)) and the spawning (spawn_forward).
// The same kernels as the three calls, one autograd node instead of three: between a step's large
// kernels the Python and autograd around each node ran on cold caches, on one thread. Returns
// {means, quats, scales, opacities, colors, selected, start, the rows' scaling (M, 6) and offset
// (M, k, 3), then decoder_forward's results}.
std::vector<torch::Tensor> visible_forward(std::vector<torch::Tensor> srcs, torch::Tensor idx, torch::Tensor ibr,
                                           std::vector<torch::Tensor> fusion, torch::Tensor centre, double dist_scale,
                                           std::vector<torch::Tensor> W1, std::vector<torch::Tensor> b1,
                                           std::vector<torch::Tensor> W2, std::vector<torch::Tensor> b2,
                                           std::vector<int64_t> acts) {
  TORCH_CHECK(srcs.size() == 4 && W1.size() == 3,
              "visible_forward: srcs are anchor, feat, scaling, offset; the heads opacity, covariance, colour");
  const auto taken = take_rows_forward(srcs, idx);
  const auto& rows = std::get<0>(taken);
  TORCH_CHECK(std::get<1>(taken), "visible_forward: idx must be strictly increasing");
  auto dec = decoder_forward(rows[1], ibr, fusion, rows[0], centre, dist_scale, W1, b1, W2, b2, acts);
  auto sp = spawn_forward(dec[0], dec[2], dec[1], rows[0], rows[2], rows[3]);  // nop, colour, covariance
  std::vector<torch::Tensor> res{sp[0], sp[1], sp[2], sp[3], sp[4], sp[6], sp[5], rows[2], rows[3]};
  res.insert(res.end(), dec.begin(), dec.end());
  return res;
}

// Gradients of visible_forward: from those of the Gaussians (gmeans .. gcolors) and what the
// forward returned for this (start, the rows' scaling and offset, decoder_forward's results),
// {[anchor (N, 3) when want_anchor], feat (N, F), scaling (N, 6), offset (N, k, 3), then
// decoder_backward's from dibr on}.
std::vector<torch::Tensor> visible_backward(torch::Tensor gmeans, torch::Tensor gquats, torch::Tensor gscales,
                                            torch::Tensor gopac, torch::Tensor gcolors, torch::Tensor start,
                                            torch::Tensor log_scal, torch::Tensor offset, torch::Tensor idx, int64_t N,
                                            torch::Tensor ibr, std::vector<torch::Tensor> fusion, torch::Tensor x,
                                            torch::Tensor dist, torch::Tensor gate, torch::Tensor ref,
                                            std::vector<torch::Tensor> hidden, std::vector<torch::Tensor> out,
                                            double dist_scale, std::vector<torch::Tensor> W1,
                                            std::vector<torch::Tensor> b1, std::vector<torch::Tensor> W2,
                                            std::vector<torch::Tensor> b2, std::vector<int64_t> acts, bool want_dibr,
                                            bool want_anchor) {
  TORCH_CHECK(out.size() == 3, "visible_backward: the heads are opacity, covariance, colour");
  // {dnop, dcolor, dcov, danchor, dlog_scal, doffset}
  const auto sb = spawn_backward(gmeans, gquats, gscales, gopac, gcolors, out[0], out[1], log_scal, offset, start);
  const auto db = decoder_backward({sb[0], sb[2], sb[1]}, ibr, fusion, x, dist, gate, ref, hidden, out, dist_scale,
                                   W1, b1, W2, b2, acts, want_dibr);
  std::vector<torch::Tensor> upstream{db[0], sb[4], sb[5]};
  if (want_anchor) upstream.insert(upstream.begin(), sb[3] + db[1]);
  auto res = take_rows_backward(upstream, idx, N);
  res.insert(res.end(), db.begin() + 2, db.end());
  return res;
}

// Whether none of the n floating-point values at p (of U's width) has all exponent bits
// (mask) set, i.e. is an infinity or a NaN. Integer tests vectorise (a float sum would not).
template <typename U>
inline bool exponents_finite(const void* p, int64_t n, U mask) {
  const char* c = static_cast<const char*>(p);
  U bad = 0;
  for (int64_t i = 0; i < n; ++i) {
    U u;
    std::memcpy(&u, c + sizeof(U) * i, sizeof(U));
    bad |= (u & mask) == mask;
  }
  return bad == 0;
}

// Whether every element of the float32 / float64 CPU tensors is finite (1, else 0): all tensors
// cut into chunks, one parallel loop (training/guard.py; a torch sum a tensor costs more in
// dispatch than the test itself for the model's small tensors). -1, having tested nothing, when a
// tensor is of another kind (the caller tests it in torch): checks in Python cost more a step.
int64_t all_finite(std::vector<torch::Tensor> ts) {
  std::vector<int64_t> lengths;
  for (auto& t : ts) {
    if (!(t.defined() && t.device().is_cpu() && t.layout() == torch::kStrided &&
          (t.scalar_type() == torch::kFloat32 || t.scalar_type() == torch::kFloat64)))
      return -1;
    t = t.contiguous();
    lengths.push_back(t.numel());
  }
  std::atomic<bool> ok(true);
  dibrgs::parallel_chunks(lengths, 16384, [&](int64_t t, int64_t i0, int64_t i1) {
    if (!ok.load(std::memory_order_relaxed)) return;
    const char* p = static_cast<const char*>(ts[t].data_ptr()) + ts[t].element_size() * i0;
    const bool fin = ts[t].scalar_type() == torch::kFloat64
                         ? exponents_finite<uint64_t>(p, i1 - i0, 0x7FF0000000000000ull)
                         : exponents_finite<uint32_t>(p, i1 - i0, 0x7F800000u);
    if (!fin) ok.store(false, std::memory_order_relaxed);
  });
  return ok.load() ? 1 : 0;
}

// Depth (H, W) float64 of planar quads (3, 4, Q) float64 in a frame that X -> M X + b takes to
// camera axes; 0 where none covers a pixel centre (geometry/surface.py rasterise_depth).
torch::Tensor zbuffer_quads(torch::Tensor quads, torch::Tensor M, torch::Tensor b, torch::Tensor K, int64_t H,
                            int64_t W) {
  TORCH_CHECK(quads.dim() == 3 && quads.size(0) == 3 && quads.size(1) == 4 && M.numel() == 9 && b.numel() == 3 &&
                  K.numel() == 9 && H >= 0 && W >= 0,
              "zbuffer_quads: shapes must be quads (3, 4, Q), M (3, 3), b (3), K (3, 3)");
  auto q = quads.to(torch::kFloat64).contiguous(), m = M.to(torch::kFloat64).contiguous();
  auto bb = b.to(torch::kFloat64).contiguous(), k = K.to(torch::kFloat64).contiguous();
  auto out = torch::empty({H, W}, torch::kFloat64);
  dibrgs::zbuffer::rasterise(q.data_ptr<double>(), q.size(2), m.data_ptr<double>(), bb.data_ptr<double>(),
                             k.data_ptr<double>(), H, W, out.data_ptr<double>());
  return out;
}

// The bindings run below autograd: each function is the forward or backward of an autograd node
// defined in Python, so the ATen operators it calls (allocations, views, products) need none of
// autograd's bookkeeping (about a microsecond an operator, hundreds a step in the decoder alone),
// and its inputs are read as they are, never detached (each detach makes a tensor object: the
// decoder's sixteen weights, detached, took 29-35 us of the calling thread a call).
template <typename R, typename... A>
auto below_autograd(R (*f)(A...)) {
  return [f](A... a) -> R {
    at::AutoDispatchBelowADInplaceOrView guard;
    return f(std::move(a)...);
  };
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("bin_tiles", below_autograd(&bin_tiles), "tile lists of screen-space Gaussians");
  m.def("forward", below_autograd(&forward), "front-to-back compositing");
  m.def("forward_colour_depth", below_autograd(&forward_colour_depth),
        "front-to-back compositing of colours, depth and alpha");
  m.def("backward", below_autograd(&backward), "gradients of the compositing");
  m.def("composite_stats", below_autograd(&composite_stats), "instrumented compositing (pair counts)");
  m.def("simd", &simd, "vector code path of this build");
  m.def("project_forward", below_autograd(&project_forward), "EWA projection of 3D Gaussians");
  m.def("project_backward", below_autograd(&project_backward), "gradients of the projection");
  m.def("ssim_forward", below_autograd(&ssim_forward), "SSIM map and its gradient factors");
  m.def("ssim_backward", below_autograd(&ssim_backward), "gradient of the SSIM map");
  m.def("photometric_forward", below_autograd(&photometric_forward), "L1 + D-SSIM training loss and its SSIM factors");
  m.def("photometric_backward", below_autograd(&photometric_backward), "gradient of photometric_forward");
  m.def("expected_depth_forward", below_autograd(&expected_depth_forward), "expected depth of a render");
  m.def("expected_depth_backward", below_autograd(&expected_depth_backward), "gradient of expected_depth_forward");
  m.def("volume_forward", below_autograd(&volume_forward), "mean volume of Gaussians' scales");
  m.def("volume_backward", below_autograd(&volume_backward), "gradient of volume_forward");
  m.def("adam_step", below_autograd(&adam_step), "one Adam step over many parameter tensors");
  m.def("all_finite", below_autograd(&all_finite), "whether every element of the tensors is finite");
  m.def("spawn_forward", below_autograd(&spawn_forward), "neural Gaussians of the visible anchors");
  m.def("spawn_backward", below_autograd(&spawn_backward), "gradients of spawn_forward");
  m.def("decoder_forward", below_autograd(&decoder_forward), "IBR fusion and decoder heads of the visible anchors");
  m.def("decoder_backward", below_autograd(&decoder_backward), "gradients of decoder_forward");
  m.def("anchor_visibility", below_autograd(&anchor_visibility), "frustum culling of anchors");
  m.def("true_indices", below_autograd(&true_indices), "positions of a bool mask's true entries");
  m.def("grad_norm_stats", below_autograd(&grad_norm_stats), "growth statistics of one view, in place");
  m.def("take_rows_forward", below_autograd(&take_rows_forward), "rows of a tensor");
  m.def("project_rows_forward", below_autograd(&project_rows_forward), "the IBR projection P of the selected rows");
  m.def("project_rows_backward", below_autograd(&project_rows_backward),
        "gradients of project_rows_forward's weights and biases");
  m.def("take_rows_backward", below_autograd(&take_rows_backward), "gradient of take_rows_forward");
  m.def("visible_forward", below_autograd(&visible_forward),
        "rows of the visible anchors, their decoder and their neural Gaussians");
  m.def("visible_backward", below_autograd(&visible_backward), "gradients of visible_forward");
  m.def("zbuffer_quads", below_autograd(&zbuffer_quads), "depth map of planar quads (a height field's mesh)");
}
