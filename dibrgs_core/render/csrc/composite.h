// Per-tile compositing kernels (forward and backward) of the CPU rasterizer,
// free of torch so that they can be compiled and inspected on their own.
// Same rules as reference.py: alpha = min(0.99, o exp(power)), skipped when
// power > 0 or alpha < 1/255; a pixel stops before the Gaussian that would
// take T under 1e-4.
//
// Vectors are GCC/Clang vector extensions of the build target's native width
// (the extension is compiled with -march=native): 64 bytes with AVX-512, 32
// with AVX/AVX2, 16 otherwise (SSE, NEON); 32 on AVX-512 CPUs that run it at
// half width (common/cpu.py: the build passes -DDIBRGS_VBYTES=32). One tile row of 16 pixels is
// 16 / L vectors of L lanes (float: 2 with AVX2, 1 with AVX-512). Every vector
// of a tile keeps its state (T, accumulators) in the workspace, and each
// Gaussian visits only the row segments its alpha >= 1/255 ellipse reaches
// (a per-row chord test, see segment_masks), so lanes far from a Gaussian
// are never evaluated.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

namespace dibrgs {

constexpr int TILE = 16;
constexpr double ALPHA_MIN = 1.0 / 255.0;
constexpr double ALPHA_MAX = 0.99;
constexpr double T_MIN = 1e-4;

#ifndef DIBRGS_VBYTES  // a build may choose a narrower width (-DDIBRGS_VBYTES=32: render/fast.py)
#if defined(__AVX512F__)
#define DIBRGS_VBYTES 64
#elif defined(__AVX__)
#define DIBRGS_VBYTES 32
#else
#define DIBRGS_VBYTES 16
#endif
#endif
constexpr int VBYTES = DIBRGS_VBYTES;

typedef float VF __attribute__((vector_size(VBYTES)));
typedef int32_t VIF __attribute__((vector_size(VBYTES)));
typedef double VD __attribute__((vector_size(VBYTES)));
typedef int64_t VID __attribute__((vector_size(VBYTES)));
// Lane masks (see cmp_lt below): mask registers with AVX-512 at its full width, else vectors.
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
typedef __mmask16 MF;
typedef __mmask8 MD;
#else
typedef VIF MF;
typedef VID MD;
#endif

template <typename T>
struct Vec;
template <>
struct Vec<float> {
  typedef VF V;
  typedef VIF I;
  typedef MF M;
  typedef int32_t IS;
};
template <>
struct Vec<double> {
  typedef VD V;
  typedef VID I;
  typedef MD M;
  typedef int64_t IS;
};

// Short name of the vector code path, for build reports.
inline const char* simd_name() {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return "avx512";
#elif DIBRGS_VBYTES == 32 && defined(__AVX512F__)
  return "avx512vl";  // AVX-512 instructions on 256-bit vectors
#elif defined(__AVX2__) && defined(__FMA__)
  return "avx2+fma";
#elif defined(__AVX__)
  return "avx";
#elif defined(__SSE2__)
  return "sse2";
#else
  return "generic";
#endif
}

// a * b + c, fused where the target has FMA (written out: the extension is
// compiled in ISO mode, where GCC does not contract a * b + c by itself).
inline VF fmadd(VF a, VF b, VF c) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VF)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c);
#elif defined(__FMA__) && DIBRGS_VBYTES == 32
  return (VF)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
#else
  return a * b + c;
#endif
}
inline VD fmadd(VD a, VD b, VD c) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VD)_mm512_fmadd_pd((__m512d)a, (__m512d)b, (__m512d)c);
#elif defined(__FMA__) && DIBRGS_VBYTES == 32
  return (VD)_mm256_fmadd_pd((__m256d)a, (__m256d)b, (__m256d)c);
#else
  return a * b + c;
#endif
}

inline VF vsqrt(VF x) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VF)_mm512_sqrt_ps((__m512)x);
#elif DIBRGS_VBYTES == 32
  return (VF)_mm256_sqrt_ps((__m256)x);
#elif defined(__SSE2__)
  return (VF)_mm_sqrt_ps((__m128)x);
#else
  for (int i = 0; i < VBYTES / 4; ++i) x[i] = std::sqrt(x[i]);
  return x;
#endif
}
inline VD vsqrt(VD x) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VD)_mm512_sqrt_pd((__m512d)x);
#elif DIBRGS_VBYTES == 32
  return (VD)_mm256_sqrt_pd((__m256d)x);
#elif defined(__SSE2__)
  return (VD)_mm_sqrt_pd((__m128d)x);
#else
  for (int i = 0; i < VBYTES / 8; ++i) x[i] = std::sqrt(x[i]);
  return x;
#endif
}

// Bit i = lane i of a 0 / -1 mask.
inline uint32_t lanes(VIF m) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return _mm512_test_epi32_mask((__m512i)m, (__m512i)m);
#elif DIBRGS_VBYTES == 32
  return static_cast<uint32_t>(_mm256_movemask_ps((__m256)m));
#elif defined(__SSE2__)
  return static_cast<uint32_t>(_mm_movemask_ps((__m128)m));
#else
  uint32_t r = 0;
  for (int i = 0; i < VBYTES / 4; ++i) r |= static_cast<uint32_t>(m[i] != 0) << i;
  return r;
#endif
}
inline uint32_t lanes(VID m) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return _mm512_test_epi64_mask((__m512i)m, (__m512i)m);
#elif DIBRGS_VBYTES == 32
  return static_cast<uint32_t>(_mm256_movemask_pd((__m256d)m));
#elif defined(__SSE2__)
  return static_cast<uint32_t>(_mm_movemask_pd((__m128d)m));
#else
  uint32_t r = 0;
  for (int i = 0; i < VBYTES / 8; ++i) r |= static_cast<uint32_t>(m[i] != 0) << i;
  return r;
#endif
}

template <typename V>
inline V splat(typename std::remove_reference<decltype(V()[0])>::type x) {
  return x - V{};  // x - 0 == x for every x, so this folds to a broadcast
}
// min / max with x86 semantics (the second operand when either is NaN), one
// instruction on x86 (the ternary form becomes compare + blend).
inline VF vmin(VF a, VF b) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VF)_mm512_min_ps((__m512)a, (__m512)b);
#elif DIBRGS_VBYTES == 32
  return (VF)_mm256_min_ps((__m256)a, (__m256)b);
#else
  return a < b ? a : b;
#endif
}
inline VF vmax(VF a, VF b) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VF)_mm512_max_ps((__m512)a, (__m512)b);
#elif DIBRGS_VBYTES == 32
  return (VF)_mm256_max_ps((__m256)a, (__m256)b);
#else
  return a > b ? a : b;
#endif
}
// Rounded down to an integer (a float's integer values are exact).
inline VF vfloor(VF x) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VF)_mm512_roundscale_ps((__m512)x, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
#elif DIBRGS_VBYTES == 32 && defined(__AVX__)
  return (VF)_mm256_floor_ps((__m256)x);
#elif defined(__SSE4_1__)
  return (VF)_mm_floor_ps((__m128)x);
#else
  for (int i = 0; i < VBYTES / 4; ++i) x[i] = std::floor(x[i]);
  return x;
#endif
}
inline VD vmin(VD a, VD b) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VD)_mm512_min_pd((__m512d)a, (__m512d)b);
#elif DIBRGS_VBYTES == 32
  return (VD)_mm256_min_pd((__m256d)a, (__m256d)b);
#else
  return a < b ? a : b;
#endif
}
inline VD vmax(VD a, VD b) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VD)_mm512_max_pd((__m512d)a, (__m512d)b);
#elif DIBRGS_VBYTES == 32
  return (VD)_mm256_max_pd((__m256d)a, (__m256d)b);
#else
  return a > b ? a : b;
#endif
}

// Lanes of v where m is set, 0 elsewhere (bitwise: NaN or inf never leak).
inline VF keep(VIF m, VF v) { return (VF)(m & (VIF)v); }
inline VD keep(VID m, VD v) { return (VD)(m & (VID)v); }

// Lane masks of the kernels' per-vector loops: AVX-512's mask registers at its full width (a
// compare writes one, masked instructions read one), 0 / -1 integer vectors elsewhere. Kept
// behind these helpers so that GCC never turns a mask register into a vector and back (a
// blend, a test and a masked move each time on AVX-512).
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
inline MF cmp_lt(VF a, VF b) { return _mm512_cmp_ps_mask((__m512)a, (__m512)b, _CMP_LT_OQ); }
inline MF cmp_le(VF a, VF b) { return _mm512_cmp_ps_mask((__m512)a, (__m512)b, _CMP_LE_OQ); }
inline MF cmp_gt(VF a, VF b) { return _mm512_cmp_ps_mask((__m512)a, (__m512)b, _CMP_GT_OQ); }
inline MF cmp_ge(VF a, VF b) { return _mm512_cmp_ps_mask((__m512)a, (__m512)b, _CMP_GE_OQ); }
inline MF cmp_lt(VIF a, VIF b) { return _mm512_cmplt_epi32_mask((__m512i)a, (__m512i)b); }
inline MD cmp_lt(VD a, VD b) { return _mm512_cmp_pd_mask((__m512d)a, (__m512d)b, _CMP_LT_OQ); }
inline MD cmp_le(VD a, VD b) { return _mm512_cmp_pd_mask((__m512d)a, (__m512d)b, _CMP_LE_OQ); }
inline MD cmp_gt(VD a, VD b) { return _mm512_cmp_pd_mask((__m512d)a, (__m512d)b, _CMP_GT_OQ); }
inline MD cmp_ge(VD a, VD b) { return _mm512_cmp_pd_mask((__m512d)a, (__m512d)b, _CMP_GE_OQ); }
inline MD cmp_lt(VID a, VID b) { return _mm512_cmplt_epi64_mask((__m512i)a, (__m512i)b); }
inline MF mask_of(VIF m) { return _mm512_test_epi32_mask((__m512i)m, (__m512i)m); }
inline MD mask_of(VID m) { return _mm512_test_epi64_mask((__m512i)m, (__m512i)m); }
inline uint32_t lanes(MF m) { return m; }
inline uint32_t lanes(MD m) { return m; }
inline MF mand(MF a, MF b) { return a & b; }
inline MD mand(MD a, MD b) { return a & b; }
inline MF mandnot(MF a, MF b) { return static_cast<MF>(~a & b); }  // ~a & b
inline MD mandnot(MD a, MD b) { return static_cast<MD>(~a & b); }
inline MF mor(MF a, MF b) { return a | b; }
inline MD mor(MD a, MD b) { return a | b; }
inline bool all_lanes(MF m) { return m == 0xFFFF; }
inline bool all_lanes(MD m) { return m == 0xFF; }
inline VF keep(MF m, VF v) { return (VF)_mm512_maskz_mov_ps(m, (__m512)v); }
inline VD keep(MD m, VD v) { return (VD)_mm512_maskz_mov_pd(m, (__m512d)v); }
// a / b where m is set, a elsewhere.
inline VF div_where(MF m, VF a, VF b) { return (VF)_mm512_mask_div_ps((__m512)a, m, (__m512)a, (__m512)b); }
inline VD div_where(MD m, VD a, VD b) { return (VD)_mm512_mask_div_pd((__m512d)a, m, (__m512d)a, (__m512d)b); }
// *p = v where m is set (the other lanes of *p kept).
inline void store_where(MF m, VF* p, VF v) { _mm512_mask_store_ps(p, m, (__m512)v); }
inline void store_where(MD m, VD* p, VD v) { _mm512_mask_store_pd(p, m, (__m512d)v); }
#else
template <typename V>
inline auto cmp_lt(V a, V b) { return a < b; }
template <typename V>
inline auto cmp_le(V a, V b) { return a <= b; }
template <typename V>
inline auto cmp_gt(V a, V b) { return a > b; }
template <typename V>
inline auto cmp_ge(V a, V b) { return a >= b; }
template <typename M>
inline M mask_of(M m) { return m; }
template <typename M>
inline M mand(M a, M b) { return a & b; }
template <typename M>
inline M mandnot(M a, M b) { return ~a & b; }
template <typename M>
inline M mor(M a, M b) { return a | b; }
template <typename M>
inline bool all_lanes(M m) { return !lanes(M(~m)); }
template <typename M, typename V>
inline V div_where(M m, V a, V b) { return m ? a / b : a; }
template <typename M, typename V>
inline void store_where(M m, V* p, V v) { *p = m ? v : *p; }
#endif

// out[i] = sum of the lanes of v[i], i < K: floats by a transposing tree of
// shuffles and adds (K <= 16 with AVX-512; 8 vectors at a time with AVX), else
// lane by lane.
template <int K, typename V, typename T>
inline void hsums(const V* v, T* out) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  if constexpr (std::is_same<V, VF>::value) {
    static_assert(K <= 16, "one tree of up to 16 vectors");
    auto x = [&](int i) { return i < K ? (__m512)v[i] : _mm512_setzero_ps(); };
    // a[i]: lanes 0-7 partial sums of v[2i], lanes 8-15 of v[2i + 1].
    __m512 a[8];
    for (int i = 0; i < 8; ++i)
      a[i] = 2 * i < K ? _mm512_add_ps(_mm512_shuffle_f32x4(x(2 * i), x(2 * i + 1), _MM_SHUFFLE(1, 0, 1, 0)),
                                       _mm512_shuffle_f32x4(x(2 * i), x(2 * i + 1), _MM_SHUFFLE(3, 2, 3, 2)))
                       : _mm512_setzero_ps();
    // b[j]: 128-bit lane q holds four partial sums of v[4j + q].
    __m512 b[4];
    for (int j = 0; j < 4; ++j)
      b[j] = 4 * j < K ? _mm512_add_ps(_mm512_shuffle_f32x4(a[2 * j], a[2 * j + 1], _MM_SHUFFLE(2, 0, 2, 0)),
                                       _mm512_shuffle_f32x4(a[2 * j], a[2 * j + 1], _MM_SHUFFLE(3, 1, 3, 1)))
                       : _mm512_setzero_ps();
    const __m512 s01 = _mm512_add_ps(_mm512_unpacklo_ps(b[0], b[1]), _mm512_unpackhi_ps(b[0], b[1]));
    const __m512 s23 = _mm512_add_ps(_mm512_unpacklo_ps(b[2], b[3]), _mm512_unpackhi_ps(b[2], b[3]));
    // r[4q + j] = sum of v[4j + q].
    const __m512 r = _mm512_add_ps(_mm512_shuffle_ps(s01, s23, _MM_SHUFFLE(1, 0, 1, 0)),
                                   _mm512_shuffle_ps(s01, s23, _MM_SHUFFLE(3, 2, 3, 2)));
    alignas(64) float t[16];
    _mm512_store_ps(t, r);
    for (int i = 0; i < K; ++i) out[i] = t[4 * (i & 3) + (i >> 2)];
    return;
  }
#endif
#if DIBRGS_VBYTES == 32 && defined(__AVX__)
  if constexpr (std::is_same<V, VF>::value && K > 8) {
    hsums<8>(v, out);
    hsums<K - 8>(v + 8, out + 8);
    return;
  } else if constexpr (std::is_same<V, VF>::value) {
    __m256 x[8];
    for (int i = 0; i < 8; ++i) x[i] = i < K ? (__m256)v[i] : _mm256_setzero_ps();
    const __m256 a0 = _mm256_hadd_ps(x[0], x[1]), a1 = _mm256_hadd_ps(x[2], x[3]);
    const __m256 a2 = _mm256_hadd_ps(x[4], x[5]), a3 = _mm256_hadd_ps(x[6], x[7]);
    const __m256 b0 = _mm256_hadd_ps(a0, a1), b1 = _mm256_hadd_ps(a2, a3);
    const __m256 r = _mm256_add_ps(_mm256_permute2f128_ps(b0, b1, 0x20), _mm256_permute2f128_ps(b0, b1, 0x31));
    alignas(32) float t[8];
    _mm256_store_ps(t, r);
    for (int i = 0; i < K; ++i) out[i] = t[i];
    return;
  }
#endif
  for (int i = 0; i < K; ++i) {
    T s = v[i][0];
    for (int l = 1; l < static_cast<int>(sizeof(V) / sizeof(T)); ++l) s += v[i][l];
    out[i] = s;
  }
}

template <typename V>
inline auto hsum(V v) {
  constexpr int L = sizeof(V) / sizeof(v[0]);
  auto s = v[0];
  for (int i = 1; i < L; ++i) s += v[i];
  return s;
}

// c[0] + f (c[1] + f (c[2] + ...)) by Horner's scheme, one FMA a coefficient.
template <int N>
inline VF horner(VF f, const float (&c)[N]) {
  VF p = splat<VF>(c[N - 1]);
  for (int i = N - 2; i >= 0; --i) p = fmadd(p, f, splat<VF>(c[i]));
  return p;
}

// The kernels evaluate exp on power scaled by kscale: float uses 2^t with
// t = log2(e) power (folded into the conic), double calls std::exp.
template <typename T>
struct Exp;
template <>
struct Exp<float> {
  static constexpr float kscale = 1.44269504088896341f;
  static constexpr float tlow = -125.0f;  // 2^-125 is normal
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__) && defined(__AVX512DQ__)
  // 2^t for t >= tlow (t <= hi not needed), else a value below 2^(tlow + 1), or NaN: t = n + f
  // with n = floor(t) and 0 <= f < 1 by one vreduceps, 2^f by a degree-6 minimax polynomial on
  // [0, 1) (relative error 7.6e-8 in float), times 2^n by scalef, which floors its exponent
  // itself (any n: large ones give inf). The clamp to tlow (no denormal results) feeds scalef
  // only, off the polynomial's dependency chain.
  static VF eval(VF t, VF) {
    static constexpr float c[7] = {1.0f, 6.931470037e-1f, 2.402298301e-1f, 5.548334122e-2f, 9.678840637e-3f,
                                   1.243969309e-3f, 2.170223888e-4f};
    const VF f = (VF)_mm512_reduce_ps((__m512)t, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    return (VF)_mm512_scalef_ps((__m512)horner(f, c), (__m512)vmax(t, splat<VF>(tlow)));
  }
#else
  // 2^t for tlow <= t <= hi <= 0, else 2^clamp(t, tlow, hi): t = n + f with n = round(t) and
  // |f| <= 1/2 (rounding by adding and subtracting 1.5 2^23), 2^f by a degree-6 minimax polynomial
  // (relative error 1.1e-7 in float), times 2^n by adding n to the exponent.
  static VF eval(VF t, VF hi) {
    t = vmax(vmin(t, hi), splat<VF>(tlow));
    static constexpr float c[7] = {1.0f, 6.931472029e-1f, 2.402264791e-1f, 5.550332471e-2f, 9.618437358e-3f,
                                   1.339887442e-3f, 1.535336188e-4f};
    const VF tn = t + 12582912.0f;  // n in the low mantissa bits of t + 1.5 2^23
    const VF f = t - (tn - 12582912.0f);
    return (VF)((VIF)horner(f, c) + ((VIF)tn << 23));
  }
#endif
};
template <>
struct Exp<double> {
  static constexpr double kscale = 1.0;
  static constexpr double tlow = -745.0;
  // exp(clamp(t, tlow, hi)).
  static VD eval(VD t, VD hi) {
    t = vmax(vmin(t, hi), splat<VD>(tlow));
    for (int i = 0; i < VBYTES / 8; ++i) t[i] = std::exp(t[i]);
    return t;
  }
};

// Tile geometry for element type T: NS vectors of L lanes per row, grouped in
// MS mask segments of VPM vectors each (MS <= 4, so that a tile's segments
// fit 64 bits: bit row * MS + segment).
template <typename T>
struct Geo {
  static constexpr int L = VBYTES / static_cast<int>(sizeof(T));
  static constexpr int NS = TILE / L;
  static constexpr int MS = NS < 4 ? NS : 4;
  static constexpr int LMS = MS == 1 ? 0 : (MS == 2 ? 1 : 2);  // log2(MS)
  static constexpr int VPM = NS / MS;
  static constexpr int NV = TILE * NS;  // vectors in a tile
};


// A Gaussian's record (R = G_F + C values of type T): mean, opacity,
// conic scaled for the kernels' exp (A = -a k / 2, B = -b k, Cq = -c k / 2,
// k = Exp<T>::kscale, so that A dx^2 + B dx dy + Cq dy^2 = k power), LO =
// k ln(opacity) (o exp(power) = Exp(k power + LO)), raw conic, then C features.
enum { G_MX, G_MY, G_O, G_A, G_B, G_C, G_LO, G_RA, G_RB, G_RC, G_F };

// Records of Gaussians [i0, i1) (rec: N * (G_F + C)); lop = ln(max(opacity,
// 1e-30)), computed by the caller over the whole array at once (vectorised). The C features are
// feat's Cf columns, then, when depth is not null, the Gaussian's depth and a one (C = Cf + 2: the
// renderer's depth and alpha channels, without a concatenated copy of its features).
template <typename T>
void make_records(const T* m2, const T* con, const T* op, const T* lop, const T* feat, const T* depth, int64_t i0,
                  int64_t i1, int64_t Cf, T* rec) {
  const int64_t C = depth != nullptr ? Cf + 2 : Cf, R = G_F + C;
  const T k = Exp<T>::kscale;
  for (int64_t g = i0; g < i1; ++g) {
    T* r = rec + g * R;
    const T ca = con[3 * g], cb = con[3 * g + 1], cc = con[3 * g + 2];
    r[G_MX] = m2[2 * g], r[G_MY] = m2[2 * g + 1], r[G_O] = op[g];
    r[G_A] = T(-0.5) * k * ca, r[G_B] = -k * cb, r[G_C] = T(-0.5) * k * cc;
    r[G_LO] = lop[g] * k;  // listed Gaussians have o >= 1/255; others get a finite value (never read)
    r[G_RA] = ca, r[G_RB] = cb, r[G_RC] = cc;
    for (int64_t ch = 0; ch < Cf; ++ch) r[G_F + ch] = feat[g * Cf + ch];
    if (depth != nullptr) r[G_F + Cf] = depth[g], r[G_F + Cf + 1] = T(1);
  }
}

// The culling ellipse q(d) <= lvl of a Gaussian (q = a dx^2 + 2 b dx dy + c
// dy^2, d = mean - pixel centre) as chords: S dy +- sqrt(P - Q dy^2) at row
// offset dy, |dy| <= Y; a degenerate conic reaches every pixel (P = Y = inf).
struct Chords {
  float P = 0, Q = 0, S = 0, Y = -1;  // default: reaches nothing
  float pad = 0;  // segment_mask's rounding allowance, less its part from the mean's position
  Chords() = default;
  Chords(double a, double b, double c, double lvl) {
    const double det = a * c - b * b;
    auto fl = [](double v) { return static_cast<float>(std::min(std::max(v, -1e30), 1e30)); };
    if (a > 0 && det > 0 && std::isfinite(det) && std::isfinite(lvl) && lvl >= 0) {
      const double p = lvl / a, s = -b / a, y = std::sqrt(lvl * a / det);
      P = fl(p), Q = fl(det / (a * a)), S = fl(s), Y = fl(y);
      pad = fl(0.01 + 5e-4 * std::sqrt(p) + 1e-6 * (1.0 + std::fabs(s)) * y);
    } else {
      P = Y = pad = std::numeric_limits<float>::infinity(), Q = S = 0.0f;
    }
  }
};

// spread<MS>[x]: bit i of the byte x moved to bit i * MS.
template <int MS>
struct Spread {
  uint32_t t[256];
  constexpr Spread() : t() {
    for (int x = 0; x < 256; ++x)
      for (int i = 0; i < 8; ++i)
        if ((x >> i) & 1) t[x] |= 1u << (i * MS);
  }
};
template <int MS>
constexpr Spread<MS> kSpread{};
// Bit i of a 16-bit row set -> bit i * MS.
template <int MS>
inline uint64_t spread_rows(uint64_t x) {
  if (MS == 1) return x;
  constexpr int M = MS == 1 ? 2 : MS;
  return kSpread<M>.t[x & 0xFF] | (uint64_t(kSpread<M>.t[(x >> 8) & 0xFF]) << (8 * MS));
}

// Row segments of a tile (bit row * MS + segment, for element type T) that a
// Gaussian's culling ellipse reaches, given its mean relative to the tile's
// corner: rows whose centre lies within Y + pad of the mean, and there the
// pixel centres that the ellipse's chord at the row centre (at its nearest
// point for rows just outside it), widened by pad, holds; pad covers this
// float arithmetic's rounding (0.01 px, a millionth of the lengths, and near
// the ellipse's ends, where P - Q dy^2 cancels, sqrt(2 eps P)). A
// segment is hit when it has such a pixel, so any segment width gives the
// same tiles. Like the binning culls it only skips pixels with alpha < 1/255
// (the level is bin_tiles' inflated one).
template <typename T>
inline uint64_t segment_mask(const Chords& e, float mxr, float myr) {
  typedef Geo<T> G;
  constexpr int LF = VBYTES / 4;
  const float pad = e.pad + 1e-6f * (std::fabs(mxr) + std::fabs(myr));
  const float Y1 = e.Y + pad;
  VF lane;
  for (int i = 0; i < LF; ++i) lane[i] = static_cast<float>(i);
  uint64_t hit[G::MS] = {};
  for (int j = 0; j < TILE / LF; ++j) {
    if (myr + Y1 < j * LF + 0.5f || myr - Y1 > j * LF + LF - 0.5f) continue;  // no row of this vector
    const VF dy = myr - (lane + (j * LF + 0.5f));
    const VIF rowok = (dy <= Y1) & (dy >= -Y1);
    const VF dyc = vmax(vmin(dy, splat<VF>(e.Y)), splat<VF>(-e.Y));
    const VF disc = vmax(e.P - e.Q * dyc * dyc, VF{});
    const VF hw = vsqrt(disc) + pad;
    const VF cen = mxr - e.S * dyc;
    // First and last pixel (centre i + 0.5) inside the chord; none when lo > hi.
    const VF lo = -vfloor((hw - cen) + 0.5f), hi = vfloor((cen + hw) - 0.5f);
    const VIF some = rowok & (lo <= hi);
    for (int ms = 0; ms < G::MS; ++ms) {
      const float s0 = ms * G::VPM * G::L, s1 = s0 + (G::VPM * G::L - 1);
      hit[ms] |= uint64_t(lanes(some & (lo <= s1) & (hi >= s0))) << (j * LF);
    }
  }
  uint64_t m = 0;
  for (int ms = 0; ms < G::MS; ++ms) m |= spread_rows<G::MS>(hit[ms]) << ms;
  return m;
}

// Global inputs of the compositing: screen-space Gaussians and tile lists.
template <typename T>
struct Scene {
  const T* rec;          // (N, G_F + C) Gaussian records (make_records)
  const int64_t* off;    // (tiles + 1) list offsets
  const int32_t* ids;    // Gaussian ids of the tile lists
  const uint64_t* mask;  // segments of its tile that each list entry reaches (segment_mask)
  int64_t C, W, H, tx;
};

// A pixel's C channels over up to four (H, W, n_b) buffers of consecutive channel ranges
// [first[b], first[b + 1]): the renderer keeps colour, depth and alpha apart, so that none of
// them is a strided slice downstream (a slice's copies and its backward's scatter cost more than
// the compositing's own writes). A null buffer reads as zeros: a gradient nobody asked for.
template <typename P>
struct Planes {
  P* buf[4] = {nullptr, nullptr, nullptr, nullptr};
  int64_t first[5] = {0, 0, 0, 0, 0};
  int n = 0;
};

// Event counters of the instrumented kernels (STATS = true).
struct Stats {
  int64_t vectors = 0;    // (Gaussian, vector) pairs evaluated
  int64_t lanes = 0;      // (Gaussian, pixel) pairs evaluated: lanes of those vectors inside the image
  int64_t contrib = 0;    // pairs that composited (forward) / carried a gradient (backward)
  int64_t gaussians = 0;  // (tile, Gaussian) list entries that reached at least one vector
  int64_t entries = 0;    // list entries of the tiles
  void add(const Stats& o) {
    vectors += o.vectors, lanes += o.lanes, contrib += o.contrib, gaussians += o.gaussians, entries += o.entries;
  }
};

// Records are read in place (a tile's list is in depth order, the records in
// index order); the kernels prefetch the record AHEAD list entries on, whose
// arrival the work of the Gaussians in between (tens of vectors) hides.
constexpr int AHEAD = 4;
template <typename T>
inline void prefetch_record(const T* r, int64_t R) {
  __builtin_prefetch(r);
  __builtin_prefetch(r + R - 1);
}

// dst[0, n) = the first n lanes of v, converted to P (all of them, of P's size: one unaligned
// vector store).
template <typename P, typename W>
inline void store_lanes(P* dst, W v, int n) {
  constexpr int L = static_cast<int>(sizeof(W) / sizeof(v[0]));
  if (sizeof(v[0]) == sizeof(P) && n == L) {
    std::memcpy(dst, &v, sizeof(W));
  } else {
    for (int l = 0; l < n; ++l) dst[l] = static_cast<P>(v[l]);
  }
}

// A lane mask kept in a state vector's slot (memcpy: the slot's type is V's).
template <typename M, typename V>
inline M get_mask(const V* slot) {
  static_assert(sizeof(M) <= sizeof(V), "mask wider than its slot");
  M m;
  std::memcpy(&m, slot, sizeof(M));
  return m;
}
template <typename M, typename V>
inline void set_mask(V* slot, M m) {
  std::memcpy(slot, &m, sizeof(M));
}

// Prefetches the cache lines of a[0, n) for writing.
template <typename P>
inline void prefetch_lines(P* a, int64_t n) {
  const char* c = reinterpret_cast<const char*>(a);
  const char* e = reinterpret_cast<const char*>(a + n);
  for (const char* q = c - (reinterpret_cast<uintptr_t>(c) & 63); q < e; q += 64) __builtin_prefetch(q, 1);
}

// Per-thread scratch: the state of a tile's pixel vectors and one Gaussian's
// first pass.
template <typename T>
struct Workspace {
  typedef typename Vec<T>::V V;
  typedef typename Vec<T>::I I;
  typedef typename Vec<T>::M M;
  typedef Geo<T> G;
  std::vector<V> st;           // per vector of the tile: a record of state vectors
  // One Gaussian's pass over its vectors: values of the first pass
  // (independent per vector, so they overlap in the pipeline) for the second
  // (which carries the pixel state).
  std::vector<V> pv;
  std::vector<T> pdy;
  std::vector<int32_t> pgv;
  V xs[G::NS];      // pixel centre columns
  I inside[G::NS];  // lanes whose column lies inside the image
  V yc[TILE / G::L];  // pixel centre rows, L rows a vector
  V rdy[TILE / G::L], rb[TILE / G::L], rc[TILE / G::L];  // first_pass's per-row terms

  Workspace() : pv(G::NV), pdy(G::NV), pgv(G::NV) {}

  // Pixel centres of the tile at (tx0, ty0).
  void columns(int tx0, int ty0, int64_t W) {
    for (int s = 0; s < G::NS; ++s)
      for (int l = 0; l < G::L; ++l) {
        xs[s][l] = T(tx0 + s * G::L + l) + T(0.5);
        inside[s][l] = tx0 + s * G::L + l < W ? -1 : 0;
      }
    for (int j = 0; j < TILE / G::L; ++j)
      for (int l = 0; l < G::L; ++l) yc[j][l] = T(ty0 + j * G::L + l) + T(0.5);
  }

  // First pass of Gaussian g over the tile's vectors in segment mask m:
  // pv = o exp(power) where power <= 0 and o exp(power) >= 1/255 (and, in
  // the backward, k < n_contrib), else 0; pgv = vector index (backward) or
  // the byte offset of its state record in st (forward: no index arithmetic
  // in its second pass), pdy (in the backward) = row offset my - y. Returns
  // the vector count.
  template <bool BACKWARD>
  int first_pass(const T* g, uint64_t m, const V* st, int64_t FS, I kv) {
    const T mx = g[G_MX], my = g[G_MY], LO = g[G_LO];
    const V A = splat<V>(g[G_A]), lo = splat<V>(LO);
    const V amin = splat<V>(T(ALPHA_MIN));
    // Per row: dy = my - y, B dy and Cq dy^2 + LO, all rows at once.
    {
      const V B = splat<V>(g[G_B]), Cq = splat<V>(g[G_C]);
      for (int j = 0; j < TILE / G::L; ++j) {
        const V dy = my - yc[j];
        if (BACKWARD) rdy[j] = dy;
        rb[j] = B * dy;
        rc[j] = fmadd(Cq * dy, dy, lo);
      }
    }
    const T* const dyr = reinterpret_cast<const T*>(rdy);
    const T* const bdyr = reinterpret_cast<const T*>(rb);
    const T* const cdyr = reinterpret_cast<const T*>(rc);
    V* __restrict out = pv.data();
    T* __restrict dys = pdy.data();
    int32_t* __restrict gvs = pgv.data();
    int nv = 0;
    // [hot] first pass
    do {
      const int bit = __builtin_ctzll(m);
      m &= m - 1;
      const int r = bit >> G::LMS, ms = bit & (G::MS - 1);
      const V bdy = splat<V>(bdyr[r]), cdy2 = splat<V>(cdyr[r]);
#pragma GCC unroll 4
      for (int v = 0; v < G::VPM; ++v) {
        const int s = ms * G::VPM + v, gv = r * G::NS + s;
        const V dx = mx - xs[s];
        const V t = fmadd(dx, fmadd(A, dx, bdy), cdy2);  // k power + LO
        const V oG = Exp<T>::eval(t, lo);
        auto ok = mand(cmp_le(t, lo), cmp_ge(oG, amin));  // power <= 0, alpha >= 1/255
        if (BACKWARD) ok = mand(ok, cmp_lt(kv, (I)st[gv * FS + 1]));
        out[nv] = keep(ok, oG);
        if (BACKWARD) dys[nv] = dyr[r];
        gvs[nv] = BACKWARD ? gv : gv * static_cast<int32_t>(FS * sizeof(V));
        ++nv;
      }
    } while (m);
    // [/hot]
    return nv;
  }
};

// Forward compositing of one tile: writes its pixels of out (C channels), tfin
// (H, W) and ncon (H, W) (1 + list position of the last Gaussian composited).
// CT > 0 fixes the channel count at compile time.
template <typename T, int CT, bool STATS>
void forward_tile(const Scene<T>& sc, int64_t tile, Workspace<T>& ws, const Planes<T>& out, T* tfin, int32_t* ncon,
                  Stats* stats) {
  typedef typename Vec<T>::V V;
  typedef typename Vec<T>::I I;
  typedef typename Vec<T>::IS IS;
  typedef typename Vec<T>::M M;
  typedef Geo<T> G;
  const int64_t C = CT > 0 ? CT : sc.C, GS = G_F + C, FS = 3 + C;  // state: T, last, acc[C], done (a mask)
  const int64_t DONE = FS - 1;  // the record's slot of its done mask
  const int32_t RB = static_cast<int32_t>(FS * sizeof(V));  // bytes a record (first_pass's offsets)
  const int ty0 = static_cast<int>((tile / sc.tx) * TILE), tx0 = static_cast<int>((tile % sc.tx) * TILE);
  const int nrows = static_cast<int>(std::min<int64_t>(TILE, sc.H - ty0));
  ws.columns(tx0, ty0, sc.W);
  ws.st.assign(G::NV * FS, V{});
  V* const st = ws.st.data();
  uint64_t alive = 0;
  for (int r = 0; r < TILE; ++r)
    for (int s = 0; s < G::NS; ++s) {
      st[(r * G::NS + s) * FS] = splat<V>(T(1));
      set_mask(st + (r * G::NS + s) * FS + DONE, r < nrows ? M(~mask_of(ws.inside[s])) : M(~M{}));
      if (r < nrows && lanes(ws.inside[s])) alive |= uint64_t(1) << (r * G::MS + s / G::VPM);
    }
  // The tile's output rows are written at its end: fetch them now (for writing), so
  // that those stores find their lines in cache instead of missing one by one.
  for (int r = 0; r < nrows; ++r) {
    const int64_t pix = (ty0 + r) * sc.W + tx0, np = std::min<int64_t>(TILE, sc.W - tx0);
    for (int b = 0; b < out.n; ++b) {
      const int64_t nb = out.first[b + 1] - out.first[b];
      prefetch_lines(out.buf[b] + pix * nb, np * nb);
    }
    prefetch_lines(tfin + pix, np);
    prefetch_lines(ncon + pix, np);
  }
  const int64_t s0 = sc.off[tile], n = sc.off[tile + 1] - s0;
  const int32_t* const ids = sc.ids + s0;
  const uint64_t* const mask = sc.mask + s0;
  const V* const pv = ws.pv.data();
  const int32_t* const pgv = ws.pgv.data();
  const V amax = splat<V>(T(ALPHA_MAX)), tmin = splat<V>(T(T_MIN)), zero = V{};
  Stats stt;
  if (STATS) stt.entries = n;
  for (int64_t k = 0; k < n && alive; ++k) {
    const uint64_t m = mask[k] & alive;
    if (!m) continue;
    if (STATS) ++stt.gaussians;
    if (k + AHEAD < n) prefetch_record(sc.rec + ids[k + AHEAD] * GS, GS);
    const T* __restrict g = sc.rec + ids[k] * GS;
    const int nv = ws.template first_pass<false>(g, m, st, FS, I{});
    const V kv = (V)splat<I>(static_cast<IS>(k + 1));
    V fv[CT > 0 ? CT : 1];  // the features, broadcast once per Gaussian
    if constexpr (CT > 0)
      for (int ch = 0; ch < CT; ++ch) fv[ch] = splat<V>(g[G_F + ch]);
    // [hot] second pass: transmittance and accumulated features
    const V* __restrict pvi = pv;
    for (const int32_t *q = pgv, *qe = pgv + nv; q != qe; ++q, ++pvi) {
      V* __restrict p = reinterpret_cast<V*>(reinterpret_cast<char*>(st) + *q);
      const V oG = *pvi;
      const V al = vmin(oG, amax);
      const M cand = mandnot(get_mask<M>(p + DONE), cmp_gt(oG, zero));
      const V Tg = p[0];
      const V aT = al * Tg;
      const V testT = Tg - aT;
      const M stop = mand(cand, cmp_lt(testT, tmin));
      const M valid = mandnot(stop, cand);
      const V w = keep(valid, aT);
      store_where(valid, p, testT);
      store_where(valid, p + 1, kv);
      if (STATS) {
        ++stt.vectors;
        stt.lanes += __builtin_popcount(lanes(ws.inside[((*q / RB) & (G::NS - 1))]));
        stt.contrib += __builtin_popcount(lanes(valid));
      }
      V* acc = p + 2;
      if constexpr (CT > 0) {
        for (int ch = 0; ch < CT; ++ch) acc[ch] = fmadd(w, fv[ch], acc[ch]);
      } else {
        for (int64_t ch = 0; ch < C; ++ch) acc[ch] = fmadd(w, splat<V>(g[G_F + ch]), acc[ch]);
      }
      if (__builtin_expect(lanes(stop) != 0, 0)) {
        set_mask(p + DONE, mor(get_mask<M>(p + DONE), stop));
        const int gv = *q / RB;
        const int r = gv / G::NS, s = gv & (G::NS - 1), ms = s / G::VPM;
        bool all = true;
        for (int v = 0; v < G::VPM; ++v)
          all = all && all_lanes(get_mask<M>(st + (r * G::NS + ms * G::VPM + v) * FS + DONE));
        if (all) alive &= ~(uint64_t(1) << (r * G::MS + ms));
      }
    }
    // [/hot]
  }
  for (int r = 0; r < nrows; ++r)
    for (int s = 0; s < G::NS; ++s) {
      const V* p = st + (r * G::NS + s) * FS;
      const int64_t x0 = tx0 + s * G::L, pix = (ty0 + r) * sc.W + x0;
      const int nl = static_cast<int>(std::min<int64_t>(G::L, sc.W - x0));  // lanes inside the image
      if (nl <= 0) break;
      for (int b = 0; b < out.n; ++b) {
        const int64_t c0 = out.first[b], nb = out.first[b + 1] - c0;
        T* o = out.buf[b] + pix * nb;
        if (nb == 1) {
          store_lanes(o, p[2 + c0], nl);
        } else {
          for (int l = 0; l < nl; ++l)
            for (int64_t ch = 0; ch < nb; ++ch) o[l * nb + ch] = p[2 + c0 + ch][l];
        }
      }
      store_lanes(tfin + pix, p[0], nl);
      store_lanes(ncon + pix, (I)p[1], nl);  // int64 lanes (double) narrowed one by one
    }
  if (STATS) stats->add(stt);
}

// Backward of one tile: for list entry s0 + k of the tile, writes NG = 6 + C
// partial gradients to buf[(s0 + k) * NG + j] (mx, my, a, b, c, opacity,
// features), zeros for Gaussians that reach no pixel, from gout (the C channels'
// gradients).
template <typename T, int CT, bool STATS>
void backward_tile(const Scene<T>& sc, int64_t tile, Workspace<T>& ws, const Planes<const T>& gout, const T* tfin,
                   const int32_t* ncon, T* buf, Stats* stats) {
  typedef typename Vec<T>::V V;
  typedef typename Vec<T>::I I;
  typedef typename Vec<T>::IS IS;
  typedef typename Vec<T>::M M;
  typedef Geo<T> G;
  const int64_t C = CT > 0 ? CT : sc.C, GS = G_F + C, NG = 6 + C, FS = 2 + 2 * C;  // state: T, last, S[C], D[C]
  const int64_t s0 = sc.off[tile], n = sc.off[tile + 1] - s0;
  if (n == 0) return;
  const int ty0 = static_cast<int>((tile / sc.tx) * TILE), tx0 = static_cast<int>((tile % sc.tx) * TILE);
  const int nrows = static_cast<int>(std::min<int64_t>(TILE, sc.H - ty0));
  ws.columns(tx0, ty0, sc.W);
  ws.st.assign(G::NV * FS, V{});
  V* const st = ws.st.data();
  // A segment joins once k drops below the largest n_contrib of its pixels.
  int segmax[64] = {0};
  for (int r = 0; r < TILE; ++r)
    for (int s = 0; s < G::NS; ++s) {
      V* p = st + (r * G::NS + s) * FS;
      p[0] = splat<V>(T(1));
      if (r >= nrows) continue;
      I last{};
      int mx = 0;
      for (int l = 0; l < G::L; ++l) {
        const int64_t x = tx0 + s * G::L + l;
        if (x >= sc.W) break;
        const int64_t pix = (ty0 + r) * sc.W + x;
        p[0][l] = tfin[pix];
        last[l] = ncon[pix];
        mx = std::max(mx, static_cast<int>(ncon[pix]));
        for (int b = 0; b < gout.n; ++b) {
          const int64_t c0 = gout.first[b], nb = gout.first[b + 1] - c0;
          const T* gb = gout.buf[b] == nullptr ? nullptr : gout.buf[b] + pix * nb;
          for (int64_t ch = 0; ch < nb; ++ch) p[2 + C + c0 + ch][l] = gb == nullptr ? T(0) : gb[ch];
        }
      }
      p[1] = (V)last;
      int& sm = segmax[r * G::MS + s / G::VPM];
      sm = std::max(sm, mx);
    }
  int order[64], nseg = 0, maxnc = 0;
  for (int i = 0; i < 64; ++i)
    if (segmax[i] > 0) order[nseg++] = i, maxnc = std::max(maxnc, segmax[i]);
  std::sort(order, order + nseg, [&](int x, int y) { return segmax[x] > segmax[y]; });
  T* const bk = buf + s0 * NG;
  std::fill(bk + maxnc * NG, bk + n * NG, T(0));  // entries behind every pixel's last one
  const int32_t* const ids = sc.ids + s0;
  const uint64_t* const mask = sc.mask + s0;
  V* const pv = ws.pv.data();
  const T* const pdy = ws.pdy.data();
  const int32_t* const pgv = ws.pgv.data();
  const V* const xs = ws.xs;
  const V amax = splat<V>(T(ALPHA_MAX)), one = splat<V>(T(1)), zero = V{};
  uint64_t active = 0;
  int ev = 0;
  Stats stt;
  if (STATS) stt.entries = n;
  std::vector<V> gfd(CT > 0 ? 0 : C);
  for (int64_t k = maxnc - 1; k >= 0; --k) {
    while (ev < nseg && segmax[order[ev]] > k) active |= uint64_t(1) << order[ev++];
    const uint64_t m = mask[k] & active;
    T* const out = bk + k * NG;
    if (!m) {
      std::fill(out, out + NG, T(0));
      continue;
    }
    if (STATS) ++stt.gaussians;
    if (k >= AHEAD) prefetch_record(sc.rec + ids[k - AHEAD] * GS, GS);
    const T* __restrict g = sc.rec + ids[k] * GS;
    const int nv = ws.template first_pass<true>(g, m, st, FS, splat<I>(static_cast<IS>(k)));
    const T mx = g[G_MX];
    V M1 = zero, My = zero, Mxx = zero, Mxy = zero, Myy = zero, M0 = zero;
    // Second pass: transmittance, colour behind, dL/dpower and its moments;
    // leaves the weights in pv for the feature gradients (a third pass keeps
    // every accumulator in a register on 16-register targets).
    // [hot]
    for (int i = 0; i < nv; ++i) {
      const int gv = pgv[i];
      V* __restrict p = st + gv * FS;
      const V oG = pv[i];
      const V al = vmin(oG, amax);
      const M valid = cmp_gt(oG, zero);
      if (STATS) {
        ++stt.vectors;
        stt.lanes += __builtin_popcount(lanes(ws.inside[(gv & (G::NS - 1))]));
        stt.contrib += __builtin_popcount(lanes(valid));
      }
      // T before this Gaussian, from the one after it.
      const V Tg = div_where(valid, p[0], one - al);
      p[0] = Tg;
      const V va = keep(valid, al);
      pv[i] = va * Tg;  // this Gaussian's weight at each pixel
      // dL/dalpha = T sum_ch D (f - S), S = what lies behind it.
      V dsum = zero;
      V* S = p + 2;
      const V* D = p + 2 + C;
      for (int64_t ch = 0; ch < C; ++ch) {
        const V Sr = S[ch];
        // (broadcast from the record each time: kept in registers, the
        // features would push the accumulators out to the stack)
        const V diff = splat<V>(g[G_F + ch]) - Sr;
        dsum = fmadd(D[ch], diff, dsum);
        S[ch] = fmadd(va, diff, Sr);
      }
      // No gradient through the 0.99 clamp (as torch.clamp).
      const V dla = keep(mand(valid, cmp_le(oG, amax)), dsum * Tg);
      const V dp = oG * dla;  // dL/dpower
      M0 += dp;
      const V dx = mx - xs[(gv & (G::NS - 1))];
      const V dyv = splat<V>(pdy[i]);
      const V pdx = dp * dx;
      const V pdy_ = dp * dyv;
      M1 += pdx;
      My += pdy_;
      Mxx = fmadd(pdx, dx, Mxx);
      Mxy = fmadd(pdx, dyv, Mxy);
      Myy = fmadd(pdy_, dyv, Myy);
    }
    // [/hot]
    // Third pass: feature gradients sum_pixels weight * dL/dout; then the
    // lanes' sums of the moments (h[0..5]) and of these (h[6..]) in one reduction.
    T h[6 + (CT > 0 ? CT : 0)];
    if constexpr (CT > 0) {
      V sums[6 + CT] = {M1, My, Mxx, Mxy, Myy, M0};
      V* const gf = sums + 6;
      // [hot]
      for (int ch = 0; ch < CT; ++ch) gf[ch] = zero;
      for (int i = 0; i < nv; ++i) {
        const V wgt = pv[i];
        const V* D = st + pgv[i] * FS + 2 + C;
        for (int ch = 0; ch < CT; ++ch) gf[ch] = fmadd(wgt, D[ch], gf[ch]);
      }
      // [/hot]
      hsums<6 + CT>(sums, h);
      for (int ch = 0; ch < CT; ++ch) out[6 + ch] = h[6 + ch];
    } else {
      V* const gf = gfd.data();
      for (int64_t ch = 0; ch < C; ++ch) gf[ch] = zero;
      for (int i = 0; i < nv; ++i) {
        const V wgt = pv[i];
        const V* D = st + pgv[i] * FS + 2 + C;
        for (int64_t ch = 0; ch < C; ++ch) gf[ch] = fmadd(wgt, D[ch], gf[ch]);
      }
      for (int64_t ch = 0; ch < C; ++ch) out[6 + ch] = hsum(gf[ch]);
      const V mom[6] = {M1, My, Mxx, Mxy, Myy, M0};
      hsums<6>(mom, h);
    }
    // power = -(a dx^2 + c dy^2) / 2 - b dx dy with d = mean - pixel.
    const T a = g[G_RA], b = g[G_RB], c = g[G_RC];
    out[0] = -(a * h[0] + b * h[1]);
    out[1] = -(c * h[1] + b * h[0]);
    out[2] = T(-0.5) * h[2];
    out[3] = -h[3];
    out[4] = T(-0.5) * h[4];
    out[5] = h[5] / g[G_O];  // sum exp(power) dL/dalpha (listed Gaussians have o >= 1/255)
  }
  if (STATS) stats->add(stt);
}

}  // namespace dibrgs
