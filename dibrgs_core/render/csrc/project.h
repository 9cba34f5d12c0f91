// Projection (EWA splatting), fused forward and backward. Same maths as projection.py (see
// there); every per-Gaussian quantity is computed in double whatever the tensor dtype, because
// squared covariances of large or very close Gaussians overflow float32 and det = a c - b^2
// cancels catastrophically for thin ones. cam: float64 (16,) = R (row-major 3x3), t (3), fx,
// fy, cx, cy.
//
// One Gaussian's maths is written once over a type D: a native vector of doubles (composite.h
// VD: 8 Gaussians a step with AVX-512, 4 with AVX2), with masks for its conditions, for whole
// blocks, and double for the rest. Branch-free: every condition is a select, so a lane's
// result is what the scalar code gives.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>

#include "composite.h"

namespace dibrgs {
namespace proj {

constexpr double EPS2D = 0.3;
constexpr double MAX_RADIUS = 1.0e9;
constexpr double QUAT_EPS2 = 1.0e-30;
constexpr int LD = VBYTES / 8;  // Gaussians a vector step

// The operations the maths needs, for double (bool conditions) and VD (VID masks).
inline double sel(bool m, double a, double b) { return m ? a : b; }
inline VD sel(VID m, VD a, VD b) { return m ? a : b; }
inline double vmin(double a, double b) { return std::min(a, b); }
inline VD vmin(VD a, VD b) { return b < a ? b : a; }  // std::min's choice, NaN included
inline double vmax(double a, double b) { return std::max(a, b); }
inline VD vmax(VD a, VD b) { return a < b ? b : a; }
using dibrgs::vsqrt;  // VD (composite.h)
inline double vsqrt(double x) { return std::sqrt(x); }
inline double vceil(double x) { return std::ceil(x); }
inline VD vceil(VD x) {
#if DIBRGS_VBYTES == 64 && defined(__AVX512F__)
  return (VD)_mm512_roundscale_pd((__m512d)x, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC);
#elif DIBRGS_VBYTES == 32
  return (VD)_mm256_ceil_pd((__m256d)x);
#else
  for (int l = 0; l < LD; ++l) x[l] = std::ceil(x[l]);
  return x;
#endif
}
inline bool finite(double x) { return std::isfinite(x); }
inline VID finite(VD x) { return (x - x) == (x - x); }  // inf - inf and NaN compare unequal
template <typename D>
inline D splat(double v) {
  return D{} + v;
}
template <>
inline double splat<double>(double v) {
  return v;
}
// Value k of element i + lane of rows of `stride` values (the block's Gaussians, lane by lane).
template <typename D, typename T>
inline D load(const T* p, int64_t stride, int64_t i, int k) {
  if constexpr (std::is_same<D, double>::value) {
    return double(p[stride * i + k]);
  } else {
    D v;
    for (int l = 0; l < LD; ++l) v[l] = double(p[stride * (i + l) + k]);
    return v;
  }
}
template <typename D>
constexpr int width() {
  return std::is_same<D, double>::value ? 1 : LD;
}
inline double lane(double x, int) { return x; }
inline double lane(VD x, int l) { return x[l]; }
inline bool lane(bool m, int) { return m; }
inline bool lane(VID m, int l) { return m[l] != 0; }

struct Cam {
  double R[9], t[3], fx, fy, cx, cy, lim_xn, lim_xp, lim_yn, lim_yp;
  Cam(const double* c, int64_t W, int64_t H) {
    std::copy(c, c + 9, R);
    std::copy(c + 9, c + 12, t);
    fx = c[12], fy = c[13], cx = c[14], cy = c[15];
    // Jacobian clamp: field of view widened by 30 % of its half-width.
    const double tfx = 0.5 * W / fx, tfy = 0.5 * H / fy;
    lim_xp = (W - cx) / fx + 0.3 * tfx;
    lim_xn = cx / fx + 0.3 * tfx;
    lim_yp = (H - cy) / fy + 0.3 * tfy;
    lim_yn = cy / fy + 0.3 * tfy;
  }
};

// Everything the forward computes for a Gaussian (a lane) that the backward needs.
template <typename D>
struct State {
  typedef decltype(D{} > D{}) M;
  D p[3];          // camera-space mean
  D zs;            // z, or 1 when culled by depth
  M in_depth, ok_q, ok_det;
  D qn[4], inv_qn;  // normalised quaternion, 1 / |q|
  D Rq[9], Mc[9];   // rotation, camera-space factor Mc = Rw R S (row-major)
  D txz, tyz;
  M clx, cly;  // x/z, y/z inside the clamp
  D u[3], v[3];
  D a, b, c, det, det_s;
};

template <typename D, typename T>
inline void project_one(const Cam& cam, const T* m, const T* q, const T* s, int64_t i, double near, double far,
                        State<D>& st) {
  const D mx = load<D>(m, 3, i, 0), my = load<D>(m, 3, i, 1), mz = load<D>(m, 3, i, 2);
  for (int r = 0; r < 3; ++r) st.p[r] = cam.R[3 * r] * mx + cam.R[3 * r + 1] * my + cam.R[3 * r + 2] * mz + cam.t[r];
  const D z = st.p[2];
  st.in_depth = (z > splat<D>(near)) & (z < splat<D>(far));
  st.zs = sel(st.in_depth, z, splat<D>(1.0));
  D qq[4];
  for (int k = 0; k < 4; ++k) qq[k] = load<D>(q, 4, i, k);
  const D n2 = qq[0] * qq[0] + qq[1] * qq[1] + qq[2] * qq[2] + qq[3] * qq[3];
  st.ok_q = n2 > splat<D>(QUAT_EPS2);
  qq[0] = sel(st.ok_q, qq[0], splat<D>(1.0));
  for (int k = 1; k < 4; ++k) qq[k] = sel(st.ok_q, qq[k], splat<D>(0.0));
  st.inv_qn = sel(st.ok_q, 1.0 / vsqrt(n2), splat<D>(1.0));
  for (int k = 0; k < 4; ++k) st.qn[k] = qq[k] * st.inv_qn;
  const D w = st.qn[0], x = st.qn[1], y = st.qn[2], zq = st.qn[3];
  D* R = st.Rq;
  R[0] = 1.0 - 2.0 * (y * y + zq * zq), R[1] = 2.0 * (x * y - w * zq), R[2] = 2.0 * (x * zq + w * y);
  R[3] = 2.0 * (x * y + w * zq), R[4] = 1.0 - 2.0 * (x * x + zq * zq), R[5] = 2.0 * (y * zq - w * x);
  R[6] = 2.0 * (x * zq - w * y), R[7] = 2.0 * (y * zq + w * x), R[8] = 1.0 - 2.0 * (x * x + y * y);
  D sc[3];
  for (int j = 0; j < 3; ++j) sc[j] = load<D>(s, 3, i, j);
  for (int r = 0; r < 3; ++r)
    for (int j = 0; j < 3; ++j)
      st.Mc[3 * r + j] = (cam.R[3 * r] * R[j] + cam.R[3 * r + 1] * R[3 + j] + cam.R[3 * r + 2] * R[6 + j]) * sc[j];
  const D xz = st.p[0] / st.zs, yz = st.p[1] / st.zs;
  st.txz = vmin(vmax(xz, splat<D>(-cam.lim_xn)), splat<D>(cam.lim_xp));
  st.tyz = vmin(vmax(yz, splat<D>(-cam.lim_yn)), splat<D>(cam.lim_yp));
  st.clx = (xz > splat<D>(-cam.lim_xn)) & (xz < splat<D>(cam.lim_xp));
  st.cly = (yz > splat<D>(-cam.lim_yn)) & (yz < splat<D>(cam.lim_yp));
  const D ku = cam.fx / st.zs, kv = cam.fy / st.zs;
  for (int j = 0; j < 3; ++j) {
    st.u[j] = ku * (st.Mc[j] - st.txz * st.Mc[6 + j]);
    st.v[j] = kv * (st.Mc[3 + j] - st.tyz * st.Mc[6 + j]);
  }
  st.a = st.u[0] * st.u[0] + st.u[1] * st.u[1] + st.u[2] * st.u[2] + EPS2D;
  st.b = st.u[0] * st.v[0] + st.u[1] * st.v[1] + st.u[2] * st.v[2];
  st.c = st.v[0] * st.v[0] + st.v[1] * st.v[1] + st.v[2] * st.v[2] + EPS2D;
  st.det = st.a * st.c - st.b * st.b;
  st.ok_det = st.det > splat<D>(0.0);
  st.det_s = sel(st.ok_det, st.det, splat<D>(1.0));
}

// Forward of the Gaussians [i, i + width<D>()): means2d, conics, depths, radii (0 = culled).
template <typename D, typename T>
inline void forward(const Cam& cam, const T* m, const T* q, const T* s, int64_t i, double near, double far,
                    int64_t W, int64_t H, T* om, T* oc, T* od, int32_t* orad) {
  State<D> st;
  project_one<D>(cam, m, q, s, i, near, far, st);
  const D mx = cam.fx * st.p[0] / st.zs + cam.cx, my = cam.fy * st.p[1] / st.zs + cam.cy;
  const D c0 = st.c / st.det_s, c1 = -st.b / st.det_s, c2 = st.a / st.det_s;
  // 3DGS radius: 3 sigma along the major axis.
  const D mid = 0.5 * (st.a + st.c);
  const D lam = mid + vsqrt(vmax(mid * mid - st.det, splat<D>(0.1)));
  const D radius = vmin(vceil(3.0 * vsqrt(lam)), splat<D>(MAX_RADIUS));
  const D zero = splat<D>(0.0);
  const typename State<D>::M ok = st.in_depth & st.ok_det & finite(radius) & (mx + radius > zero) &
                                  (mx - radius < splat<D>(double(W))) & (my + radius > zero) &
                                  (my - radius < splat<D>(double(H)));
  for (int l = 0; l < width<D>(); ++l) {
    const int64_t g = i + l;
    om[2 * g] = static_cast<T>(lane(mx, l)), om[2 * g + 1] = static_cast<T>(lane(my, l));
    oc[3 * g] = static_cast<T>(lane(c0, l)), oc[3 * g + 1] = static_cast<T>(lane(c1, l));
    oc[3 * g + 2] = static_cast<T>(lane(c2, l));
    od[g] = static_cast<T>(lane(st.p[2], l));
    orad[g] = lane(ok, l) ? static_cast<int32_t>(lane(radius, l)) : 0;
  }
}

// Backward of the Gaussians [i, i + width<D>()): gradients of means, quats, scales from those
// of means2d, conics, depths (the depths' gradient gd read every gd_stride values: a column of
// the compositing's feature gradient, not copied first). A Gaussian without incoming gradient (none
// of its tiles listed it) gets exact zeros whatever its projection computes.
template <typename D, typename T>
inline void backward(const Cam& cam, const T* m, const T* q, const T* s, int64_t i, double near, double far,
                     const T* gm2, const T* gc, const T* gd, int64_t gd_stride, T* om, T* oq, T* os) {
  State<D> st;
  project_one<D>(cam, m, q, s, i, near, far, st);
  const D g0 = load<D>(gc, 3, i, 0), g1 = load<D>(gc, 3, i, 1), g2 = load<D>(gc, 3, i, 2);
  const D gmx = load<D>(gm2, 2, i, 0), gmy = load<D>(gm2, 2, i, 1), gdep = load<D>(gd, gd_stride, i, 0);
  const D zero = splat<D>(0.0);
  const typename State<D>::M none =
      (g0 == zero) & (g1 == zero) & (g2 == zero) & (gmx == zero) & (gmy == zero) & (gdep == zero);
  const D ids = 1.0 / st.det_s;
  // conic = (c, -b, a) / det_s, det_s = a c - b^2 where positive.
  const D gdet = sel(st.ok_det, -(g0 * st.c - g1 * st.b + g2 * st.a) * ids * ids, splat<D>(0.0));
  const D gA = g2 * ids + gdet * st.c;
  const D gB = -g1 * ids - 2.0 * gdet * st.b;
  const D gC = g0 * ids + gdet * st.a;
  const D ku = cam.fx / st.zs, kv = cam.fy / st.zs;
  D gMc[9];
  D gtx = splat<D>(0.0), gty = splat<D>(0.0), gku = splat<D>(0.0), gkv = splat<D>(0.0);
  for (int j = 0; j < 3; ++j) {
    const D gu = 2.0 * gA * st.u[j] + gB * st.v[j];
    const D gv = 2.0 * gC * st.v[j] + gB * st.u[j];
    gMc[j] = ku * gu;
    gMc[3 + j] = kv * gv;
    gMc[6 + j] = -(ku * st.txz * gu + kv * st.tyz * gv);
    gtx -= ku * gu * st.Mc[6 + j];
    gty -= kv * gv * st.Mc[6 + j];
    gku += gu * (st.Mc[j] - st.txz * st.Mc[6 + j]);
    gkv += gv * (st.Mc[3 + j] - st.tyz * st.Mc[6 + j]);
  }
  const D izs = 1.0 / st.zs;
  // x/z and y/z feed the clamp (Jacobian) and the projected mean.
  const D gxz = sel(st.clx, gtx, splat<D>(0.0)) + gmx * cam.fx;
  const D gyz = sel(st.cly, gty, splat<D>(0.0)) + gmy * cam.fy;
  D gp[3];
  gp[0] = gxz * izs;
  gp[1] = gyz * izs;
  const D gzs = -(gxz * st.p[0] + gyz * st.p[1]) * izs * izs - (gku * cam.fx + gkv * cam.fy) * izs * izs;
  gp[2] = gdep + sel(st.in_depth, gzs, splat<D>(0.0));
  D gmean[3];
  for (int k = 0; k < 3; ++k) gmean[k] = cam.R[k] * gp[0] + cam.R[3 + k] * gp[1] + cam.R[6 + k] * gp[2];
  // Mc = Rw (R S): gradient of R S is Rw^T gMc.
  D gRS[9];
  for (int r = 0; r < 3; ++r)
    for (int j = 0; j < 3; ++j)
      gRS[3 * r + j] = cam.R[r] * gMc[j] + cam.R[3 + r] * gMc[3 + j] + cam.R[6 + r] * gMc[6 + j];
  D gscale[3], gR[9];
  for (int j = 0; j < 3; ++j) {
    const D sj = load<D>(s, 3, i, j);
    gscale[j] = gRS[j] * st.Rq[j] + gRS[3 + j] * st.Rq[3 + j] + gRS[6 + j] * st.Rq[6 + j];
    for (int r = 0; r < 3; ++r) gR[3 * r + j] = gRS[3 * r + j] * sj;
  }
  const D w = st.qn[0], x = st.qn[1], y = st.qn[2], z = st.qn[3];
  D gn[4];
  gn[0] = 2.0 * (-z * gR[1] + y * gR[2] + z * gR[3] - x * gR[5] - y * gR[6] + x * gR[7]);
  gn[1] = 2.0 * (y * gR[1] + z * gR[2] + y * gR[3] - 2.0 * x * gR[4] - w * gR[5] + z * gR[6] + w * gR[7] -
                 2.0 * x * gR[8]);
  gn[2] = 2.0 * (-2.0 * y * gR[0] + x * gR[1] + w * gR[2] + x * gR[3] + z * gR[5] - w * gR[6] + z * gR[7] -
                 2.0 * y * gR[8]);
  gn[3] = 2.0 * (-2.0 * z * gR[0] - w * gR[1] + x * gR[2] + w * gR[3] - 2.0 * z * gR[4] + y * gR[5] + x * gR[6] +
                 y * gR[7]);
  // qn = q / |q|: project out the radial part.
  const D dot = w * gn[0] + x * gn[1] + y * gn[2] + z * gn[3];
  D gquat[4];
  for (int k = 0; k < 4; ++k) gquat[k] = sel(st.ok_q, (gn[k] - st.qn[k] * dot) * st.inv_qn, splat<D>(0.0));
  for (int l = 0; l < width<D>(); ++l) {
    const int64_t g = i + l;
    const bool skip = lane(none, l);
    for (int k = 0; k < 3; ++k) om[3 * g + k] = skip ? T(0) : static_cast<T>(lane(gmean[k], l));
    for (int k = 0; k < 4; ++k) oq[4 * g + k] = skip ? T(0) : static_cast<T>(lane(gquat[k], l));
    for (int k = 0; k < 3; ++k) os[3 * g + k] = skip ? T(0) : static_cast<T>(lane(gscale[k], l));
  }
}

}  // namespace proj
}  // namespace dibrgs
