"""Weight-free plane-sweep multi-view stereo in torch.

For each reference view, fronto-parallel depth planes (uniform in inverse
depth) warp the other training views into the reference; the photometric
cost is ``1 - NCC`` over a square window, averaged over the best half of the
source views (robust to occlusion in one of them). Semi-global aggregation
along image paths (SGM, Hirschmueller 2008) regularises the cost volume,
winner-take-all picks the best plane, a parabola through its neighbours
refines it below one plane, and the confidence comes from the cost curve: how much lower the best
minimum is than the best one away from it (peak ratio).

Photographs and mapping flights: zero-mean NCC ignores gain and offset
between photos (exposure, vignetting over a window), the texture test is
relative to the image's own contrast, a pixel only one other view sees is
matched against that view alone, and the consistency check asks for one
confirming view. Near-nadir sweeps use horizontal planes around the ground;
on a mapping grid the camera axes are nearly parallel and do not define a
ground point, so the SfM points do (:func:`scene_ground`). Small isolated
patches of depth (tree crowns, water, moving cars) are dropped
(:func:`speckle_mask`): two views can agree on a false match, a third rarely.

Depths are z-depths in world units along the reference camera's +z axis.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .cameras import Camera

log = logging.getLogger("dibrgs.mvs")


@dataclass
class MvsConfig:
    """Plane-sweep options.

    Attributes:
        num_depths: depth planes between near and far (uniform in 1/depth).
        window: NCC window side in pixels (odd).
        min_ncc: pixels whose best NCC is lower are marked invalid.
        min_confidence: pixels whose peak-ratio confidence is lower are invalid.
        min_texture_rel: minimum reference-window standard deviation for NCC
            to be meaningful, as a fraction of the image's median window
            standard deviation (a fixed level in image units would reject
            more of a darker photo: not gain-invariant).
        consistency_tol: geometric check between views: a depth is kept when
            it agrees, within this relative tolerance, with the depth another
            view estimated at its reprojection.
        min_consistent_views: how many other views must agree (0 disables
            the check).
        max_reproj_px: forward-backward reprojection error (pixels of the
            swept resolution) allowed by the consistency check.
        max_size: views whose longer side exceeds this are swept at a
            reduced resolution (speed on CPU) and the depth is upsampled
            (nearest) to the full size; 0 = always full size.
        plane_chunk: planes evaluated per batch (memory / speed trade-off).
        planes: ``height`` (horizontal planes in the up frame the cameras give),
            ``fronto`` (fronto-parallel) or ``auto`` (height planes for
            near-nadir cameras, see :func:`sweep_up`).
        prefilter: 3x3 box blur of the images before matching (anti-aliasing;
            wide baselines see fine ground texture at very different scales).
        height_below, height_above: height planes span from ``height_below``
            below to ``height_above`` above the ground (the cameras' look-at
            point), in units of the flying height above it (0 = the range the
            cameras' depth ranges allow).
        max_nadir_deg: ``auto`` uses height planes when the mean view
            direction is within this angle of straight down.
        sgm_paths: semi-global aggregation of the cost volume along 4 or 8
            image directions before the winner-take-all (0 = off; other
            values are refused); see
            :func:`semi_global`. On the generated 128x128 LEVIR-like city it
            lifts DIBR-GS held-out PSNR by 0.7 dB over the plain sweep.
        sgm_p1, sgm_p2: its penalties (in 1 - NCC units) for moving to a
            neighbouring plane and for jumping to any plane.
        speckle_px: after the sweep, connected regions of fewer pixels (of the
            swept resolution) whose neighbouring depths agree within
            ``speckle_tol`` are dropped (0 = off): tree crowns, water and
            moving objects match by chance in small scattered patches that a
            two-view consistency check lets through.
        speckle_tol: relative depth step that still connects two neighbouring pixels.
    """

    num_depths: int = 96
    window: int = 7
    min_ncc: float = 0.6
    min_confidence: float = 0.1
    min_texture_rel: float = 0.15
    plane_chunk: int = 8
    consistency_tol: float = 0.02
    min_consistent_views: int = 1
    max_reproj_px: float = 1.0
    max_size: int = 256
    planes: str = "auto"
    height_below: float = 0.1
    height_above: float = 0.6
    prefilter: bool = True
    max_nadir_deg: float = 60.0
    sgm_paths: int = 4
    sgm_p1: float = 0.1
    sgm_p2: float = 1.0
    speckle_px: int = 50
    speckle_tol: float = 0.01


@dataclass
class MvsResult:
    """Per-view depth (HxW float32, NaN where invalid) and confidence (HxW float32 in [0,1])."""

    depth: np.ndarray
    confidence: np.ndarray
    ncc: np.ndarray


def _gray(img: np.ndarray):
    import torch

    g = np.asarray(img, np.float32)
    if g.ndim == 3:
        g = g[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    return torch.from_numpy(np.nan_to_num(g, nan=0.0).copy())[None, None]


def _blur(x):
    """3x3 box prefilter: suppresses texture finer than a pixel that aliases differently in each view."""
    import torch.nn.functional as F

    return F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


def _box(x, w: int):
    import torch.nn.functional as F

    return F.avg_pool2d(x, w, stride=1, padding=w // 2, count_include_pad=False)


def plane_sweep(ref: Camera, ref_img: np.ndarray, sources: Sequence[tuple[Camera, np.ndarray]], near: float, far: float,
                config: MvsConfig | None = None, up: np.ndarray | None = None,
                height_range: tuple[float, float] | None = None) -> MvsResult:
    """Depth of ``ref`` by plane sweeping against ``sources`` between ``near`` and ``far`` (world units).

    With ``up`` (a world unit vector) the planes are horizontal, ``up . X = h``
    for heights ``h`` spaced uniformly over ``height_range`` (default: every
    height a pixel ray reaches between ``near`` and ``far``); a pixel whose
    plane intersection falls outside ``[near, far]`` gets no cost there.
    Without ``up`` the planes are fronto-parallel, uniform in inverse depth.
    """
    import torch
    import torch.nn.functional as F

    cfg = config or MvsConfig()
    H, W = ref.height, ref.width
    w = cfg.window | 1
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise ValueError(f"plane_sweep: bad depth range ({near}, {far})")
    if not sources:
        nan = np.full((H, W), np.nan, np.float32)
        return MvsResult(nan, np.zeros((H, W), np.float32), np.zeros((H, W), np.float32))
    with torch.no_grad():
        r = _gray(ref_img)
        if cfg.prefilter:
            r = _blur(r)
        mu_r = _box(r, w)
        var_r = (_box(r * r, w) - mu_r ** 2).clamp_min(0)
        sd_r = var_r.sqrt()
        # Pixel-centre rays of the reference camera (camera frame, z = 1).
        v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                              indexing="ij")
        pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
        rays = pix @ torch.from_numpy(np.linalg.inv(ref.K)).T
        if up is None:
            params = torch.linspace(1.0 / near, 1.0 / far, cfg.num_depths, dtype=torch.float64)

            def depth_of(p: "torch.Tensor") -> "torch.Tensor":  # (n,) inverse depths -> (n, HW) depths
                return (1.0 / p)[:, None].expand(-1, H * W)
        else:
            n_up = np.asarray(up, np.float64) / np.linalg.norm(up)
            slope = rays @ torch.from_numpy(ref.R @ n_up)  # d(height)/d(z) along each ray
            h0 = float(n_up @ ref.center)
            if height_range is None:
                hs = torch.cat([h0 + near * slope, h0 + far * slope])
                height_range = (float(hs.min()), float(hs.max()))
            params = torch.linspace(height_range[1], height_range[0], cfg.num_depths, dtype=torch.float64)
            safe = torch.where(slope.abs() > 1e-9, slope, torch.full_like(slope, 1e-9))

            def depth_of(p: "torch.Tensor") -> "torch.Tensor":  # (n,) heights -> (n, HW) depths
                z = (p[:, None] - h0) / safe[None]
                return torch.where((z >= near) & (z <= far), z, torch.full_like(z, float("nan")))
        src_data = []
        for cam, img in sources:
            R_rel = cam.R @ ref.R.T
            t_rel = cam.t - R_rel @ ref.t
            A = (rays @ torch.from_numpy(cam.K @ R_rel).T).float()  # (HW,3): direction part
            B = torch.from_numpy(cam.K @ t_rel).float()  # (3,)
            g = _gray(img)
            src_data.append((A, B, _blur(g) if cfg.prefilter else g, cam.width, cam.height))
        n_keep = max(1, math.ceil(len(sources) / 2))
        cost = torch.empty(cfg.num_depths, H, W)
        for k0 in range(0, cfg.num_depths, cfg.plane_chunk):
            ds = depth_of(params[k0:k0 + cfg.plane_chunk]).float()  # (n, HW), NaN = plane out of range
            n = len(ds)
            in_range = torch.isfinite(ds)
            ds = torch.nan_to_num(ds, nan=1.0)
            per_src = []
            for A, B, s, sw, sh in src_data:
                p = ds[:, :, None] * A[None] + B[None, None]  # (n, HW, 3)
                z = p[..., 2]
                zs = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
                gx = (p[..., 0] / zs) / sw * 2 - 1
                gy = (p[..., 1] / zs) / sh * 2 - 1
                inside = in_range & (z > 0) & (gx.abs() <= 1) & (gy.abs() <= 1)
                grid = torch.stack([gx, gy], -1).reshape(n, H, W, 2)
                grid = torch.nan_to_num(grid, nan=-2.0, posinf=-2.0, neginf=-2.0).clamp(-2, 2)
                warped = F.grid_sample(s.expand(n, 1, -1, -1), grid, mode="bilinear", padding_mode="border",
                                       align_corners=False)
                mu_s = _box(warped, w)
                var_s = (_box(warped * warped, w) - mu_s ** 2).clamp_min(0)
                cov = _box(warped * r, w) - mu_s * mu_r
                ncc = cov / (var_s * var_r + 1e-10).sqrt()
                c = (1 - ncc.clamp(-1, 1))[:, 0]
                c = torch.where(inside.reshape(n, H, W), c, torch.full_like(c, float("inf")))
                per_src.append(c)
            stack = torch.stack(per_src, 0)  # (S, n, H, W)
            best = torch.sort(stack, dim=0).values[:n_keep]
            finite = torch.isfinite(best)
            cnt = finite.sum(0)
            agg = torch.where(finite, best, torch.zeros_like(best)).sum(0) / cnt.clamp_min(1)
            cost[k0:k0 + n] = torch.where(cnt > 0, agg, torch.full_like(agg, 2.0))
        raw = cost
        if cfg.sgm_paths:
            cost = semi_global(cost, cfg.sgm_p1, cfg.sgm_p2, cfg.sgm_paths) / cfg.sgm_paths
        c1, k1 = cost.min(0)
        # Sub-plane refinement: parabola through the neighbouring costs in the plane parameter.
        km = (k1 - 1).clamp(0, cfg.num_depths - 1)
        kp = (k1 + 1).clamp(0, cfg.num_depths - 1)
        cm = cost.gather(0, km[None])[0]
        cp = cost.gather(0, kp[None])[0]
        denom = cm - 2 * c1 + cp
        off = torch.where(denom > 1e-6, 0.5 * (cm - cp) / denom.clamp_min(1e-6), torch.zeros_like(denom))
        off = torch.where((k1 > 0) & (k1 < cfg.num_depths - 1) & (cm < 2) & (cp < 2), off.clamp(-0.5, 0.5),
                          torch.zeros_like(off))
        step = (params[1] - params[0]).item() if cfg.num_depths > 1 else 0.0
        best_param = params[k1.reshape(-1)] + off.reshape(-1).double() * step
        if up is None:
            depth = (1.0 / best_param.clamp_min(1.0 / (far * 4))).reshape(H, W).float()
        else:
            depth = ((best_param - h0) / safe).reshape(H, W).float()
        # Confidence: the best minimum against the lowest cost two planes or more away.
        idx = torch.arange(cfg.num_depths)[:, None, None]
        away = (idx - k1[None]).abs() >= 2
        c2 = torch.where(away, cost, torch.full_like(cost, 2.0)).min(0).values
        conf = ((c2 - c1) / c2.clamp_min(1e-6)).clamp(0, 1)
        ncc_best = 1 - raw.gather(0, k1[None])[0]
        valid = (ncc_best >= cfg.min_ncc) & (conf >= cfg.min_confidence) & (sd_r[0, 0] >= cfg.min_texture_rel * sd_r.median())
        valid &= torch.isfinite(depth) & (c1 < 2) & (depth >= near * 0.99) & (depth <= far * 1.01)
        depth = torch.where(valid, depth, torch.full_like(depth, float("nan")))
        conf = torch.where(valid, conf, torch.zeros_like(conf))
    return MvsResult(depth.numpy().astype(np.float32), conf.numpy().astype(np.float32),
                     ncc_best.clamp(-1, 1).numpy().astype(np.float32))


def semi_global(cost, p1: float, p2: float, paths: int = 4):
    """Semi-global aggregation of a (D,H,W) plane-sweep cost along ``paths`` (4 or 8) image directions.

    Each path adds, per pixel and plane, the cost plus the cheapest way to arrive from the
    previous pixel on the path: the same plane for free, a neighbouring plane for ``p1``, any
    plane for ``p2`` (costs are 1 - NCC, in [0, 2]). With height planes "the same plane" means
    the same height, so flat roofs and ground are favoured and height jumps at walls stay
    possible. The per-path minimum is subtracted at every step, so values stay bounded.
    Returns the sum over the paths (D,H,W).
    """
    import torch

    if paths not in (4, 8):
        raise ValueError(f"semi_global: paths must be 4 or 8, got {paths}")
    D, H, W = cost.shape
    total = torch.zeros_like(cost)
    inf = torch.tensor(float("inf"))

    def run(c):  # c: (D, N, L), aggregate along the last axis, all N lines at once
        out = torch.empty_like(c)
        prev = c[:, :, 0]
        out[:, :, 0] = prev
        pad = inf.expand(1, c.shape[1])
        for x in range(1, c.shape[2]):
            m = prev.min(0).values
            step = torch.minimum(torch.cat([pad, prev[:-1]]), torch.cat([prev[1:], pad])) + p1
            best = torch.minimum(torch.minimum(prev, step), (m + p2)[None])
            prev = c[:, :, x] + best - m[None]
            out[:, :, x] = prev
        return out

    # Horizontal and vertical paths, both ways.
    total += run(cost)
    total += run(cost.flip(2)).flip(2)
    total += run(cost.transpose(1, 2)).transpose(1, 2)
    total += run(cost.transpose(1, 2).flip(2)).flip(2).transpose(1, 2)
    if paths == 8:
        # Diagonals: shear the volume so that diagonals become rows, aggregate, shear back.
        for flip in (False, True):
            c = cost.flip(2) if flip else cost
            sheared, idx = _shear(c)
            for rev in (False, True):
                a = run(sheared.flip(2)).flip(2) if rev else run(sheared)
                back = _unshear(a, idx, H, W)
                total += back.flip(2) if flip else back
    return total


def _shear(c):
    """(D,H,W) -> (D, H+W-1, min(H,W)-ish) lines along the main diagonals, padded with the max cost."""
    import torch

    D, H, W = c.shape
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    diag = (xs - ys + H - 1).reshape(-1)  # which diagonal
    pos = torch.minimum(ys, xs).reshape(-1)  # position along it
    L = min(H, W)
    out = torch.full((D, H + W - 1, L), 2.0, dtype=c.dtype)
    out[:, diag, pos] = c.reshape(D, -1)
    return out, (diag, pos)


def _unshear(a, idx, H: int, W: int):
    diag, pos = idx
    return a[:, diag, pos].reshape(a.shape[0], H, W)


def depth_range_for(cam: Camera, sparse_points: np.ndarray | None, fallback_distance: float,
                    margin: float = 1.25) -> tuple[float, float]:
    """Plane-sweep range for ``cam``: SfM point depths (2nd-98th percentile, widened by ``margin``)
    when at least 10 project in front of it, else the camera's ``depth_range``, else
    ``[d/2, 2d]`` around ``fallback_distance`` (distance to the scene's look-at point)."""
    if sparse_points is not None and len(sparse_points) >= 10:
        uv, z = cam.project(sparse_points)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if ok.sum() >= 10:
            lo, hi = np.percentile(z[ok], [2, 98])
            near, far = lo / margin, hi * margin
            if cam.depth_range is not None:  # the camera's range is a hard bound when given
                near = max(near, cam.depth_range[0])
                far = min(far, cam.depth_range[1])
            if 0 < near < far:
                return float(near), float(far)
    if cam.depth_range is not None and 0 < cam.depth_range[0] < cam.depth_range[1]:
        return float(cam.depth_range[0]), float(cam.depth_range[1])
    d = max(float(fallback_distance), 1e-6)
    return d / 2, d * 2


def mvs_depths(cameras: Sequence[Camera], images: Sequence[np.ndarray], sparse_points: np.ndarray | None,
               fallback_distance: float, config: MvsConfig | None = None, progress: bool = True) -> list[MvsResult]:
    """Plane-sweep depth for every view against all the others.

    Camera translations are re-expressed relative to the mean camera centre
    (precision with georeferenced coordinates); depths do not change.
    """
    from tqdm import tqdm

    cfg = config or MvsConfig()
    full = list(cameras)
    longest = max(max(c.width, c.height) for c in full)
    f = cfg.max_size / longest if cfg.max_size and longest > cfg.max_size else 1.0
    if f < 1.0:
        images = [_resize(im, c.scaled(f)) for im, c in zip(images, full)]
        cameras = [c.scaled(f) for c in full]
    cams = [_recentred(c, np.mean([c.center for c in cameras], axis=0)) for c in cameras]
    pts = None
    if sparse_points is not None and len(sparse_points):
        pts = np.asarray(sparse_points, np.float64) - np.mean([c.center for c in cameras], axis=0)
    up = sweep_up(cams, cfg)
    ranges = [depth_range_for(c, pts, fallback_distance) for c in cams]
    heights = None
    if up is not None and cfg.height_above > 0:
        heights = _scene_heights(cams, up, cfg, pts)
        log.info("MVS height planes: %s", "every height the depth ranges allow (ground unknown)" if heights is None
                 else f"{cfg.height_below:g} below to {cfg.height_above:g} above the ground, in flying heights")
    out = []
    for i in tqdm(range(len(cams)), desc="mvs", disable=not progress):
        near, far = ranges[i]
        srcs = [(cams[j], images[j]) for j in range(len(cams)) if j != i]
        res = plane_sweep(cams[i], images[i], srcs, near, far, cfg, up=up, height_range=heights)
        log.info("MVS view %s: range [%.3g, %.3g], %s planes, %.1f%% valid", cams[i].name, near, far,
                 "height" if up is not None else "fronto-parallel", 100.0 * np.isfinite(res.depth).mean())
        out.append(res)
    if cfg.speckle_px > 0:
        out = [MvsResult(*(np.where(keep, a, np.nan if k == 0 else 0).astype(np.float32) if k < 2 else a
                           for k, a in enumerate((r.depth, r.confidence, r.ncc))))
               for r in out for keep in [speckle_mask(r.depth, cfg.speckle_tol, cfg.speckle_px)]]
    if cfg.min_consistent_views > 0 and len(cams) > 1:
        out = _consistency_filter(cams, out, cfg.consistency_tol, cfg.min_consistent_views, cfg.max_reproj_px)
    if f < 1.0:
        out = [MvsResult(*(_upsample(a, c) for a in (r.depth, r.confidence, r.ncc))) for r, c in zip(out, full)]
    return out


def converging_target(cams: Sequence[Camera], min_spread_deg: float = 5.0) -> np.ndarray | None:
    """The point the cameras' optical axes converge on (:func:`cameras.look_at_target`), or None when
    it is not determined.

    Axes that are nearly parallel (a nadir mapping grid, a corridor of parallel
    oblique photos) meet anywhere: the least-squares point then moves tens of
    flying heights, in front of or behind the cameras, with tilts of a degree.
    It counts only when the axes spread by at least ``min_spread_deg`` around
    its direction (the smallest eigenvalue of ``sum(I - d d^T)`` over the
    cameras, per camera, is at least ``sin^2(min_spread_deg)``) and it lies in
    front of every camera.
    """
    from .cameras import look_at_target

    cams = list(cams)
    if len(cams) < 2:
        return None
    A = sum(np.eye(3) - np.outer(c.view_dir, c.view_dir) for c in cams)
    if np.linalg.eigvalsh(A)[0] / len(cams) < np.sin(np.radians(min_spread_deg)) ** 2:
        return None
    target = look_at_target(cams)
    if not np.all(np.isfinite(target)):
        return None
    if any(float((target - c.center) @ c.view_dir) <= 0 for c in cams):
        return None
    return target


def scene_ground(cams: Sequence[Camera], up: np.ndarray, sparse_points: np.ndarray | None = None,
                 min_points: int = 10) -> tuple[float, float, str] | None:
    """``(ground height, flying height above it, source)`` along ``up`` (world units), or None.

    The ground is the cameras' convergence point (:func:`converging_target`)
    when their axes determine one, else the 5th percentile of the heights of
    the SfM points the cameras see (at least ``min_points``); the flying height
    is the median camera height above it. None when neither exists or the
    cameras are not above that ground.
    """
    n_up = np.asarray(up, np.float64) / np.linalg.norm(up)
    cam_h = float(np.median([n_up @ c.center for c in cams]))
    target = converging_target(cams)
    if target is not None and cam_h - float(n_up @ target) > 0:
        ground = float(n_up @ target)
        return ground, cam_h - ground, "look-at"
    if sparse_points is not None and len(sparse_points) >= min_points:
        P = np.asarray(sparse_points, np.float64)
        seen = np.zeros(len(P), bool)
        for c in cams:
            uv, z = c.project(P)
            seen |= (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        if seen.sum() >= min_points:
            ground = float(np.percentile(P[seen] @ n_up, 5.0))
            if cam_h - ground > 0:
                return ground, cam_h - ground, "sfm"
    return None


def speckle_mask(depth: np.ndarray, tol: float, min_px: int) -> np.ndarray:
    """True where a finite depth belongs to a connected region of at least ``min_px`` pixels; two
    4-neighbours connect when their depths differ by at most ``tol`` times the smaller one."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    d = np.asarray(depth, np.float64)
    H, W = d.shape
    ok = np.isfinite(d)
    idx = np.arange(H * W).reshape(H, W)
    rows, cols = [], []
    for a, b, da, db in ((idx[:, :-1], idx[:, 1:], d[:, :-1], d[:, 1:]), (idx[:-1], idx[1:], d[:-1], d[1:])):
        link = np.isfinite(da) & np.isfinite(db) & (np.abs(da - db) <= tol * np.fmin(np.abs(da), np.abs(db)))
        rows.append(a[link])
        cols.append(b[link])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(H * W, H * W))
    _, lab = connected_components(g, directed=False)
    size = np.bincount(lab)
    return ok & (size[lab] >= min_px).reshape(H, W)


def _scene_heights(cams: Sequence[Camera], up: np.ndarray, cfg: MvsConfig,
                   sparse_points: np.ndarray | None = None) -> tuple[float, float] | None:
    """Heights to sweep: from ``height_below`` to ``height_above`` times the flying height above the
    ground (:func:`scene_ground`: the cameras' convergence point, else the SfM points).

    The cameras' depth ranges allow every height from far below the ground up
    to the cameras; sweeping all of it spreads the planes thin and, on
    repetitive texture (street grids), finds spurious matches far from the
    scene. None (full range) when the ground is unknown or not below the cameras.
    """
    g = scene_ground(cams, up, sparse_points)
    if g is None:
        return None
    ground, alt, _ = g
    return ground - cfg.height_below * alt, ground + cfg.height_above * alt


def sweep_up(cams: Sequence[Camera], config: MvsConfig) -> np.ndarray | None:
    """The up axis for horizontal (height) planes, or None for fronto-parallel planes.

    ``planes="auto"`` sweeps heights when the cameras look down (mean view
    direction within ``max_nadir_deg`` of the up axis estimated from them, with
    an unambiguous up): ground and roofs are then planes of the sweep, so the
    NCC windows match exactly even across wide baselines, where a fronto-parallel
    plane cuts the tilted ground at one depth only.
    """
    from .cameras import estimate_up, nadir_angle_deg

    if config.planes == "fronto":
        return None
    up, conf = estimate_up(cams)
    if config.planes == "height":
        return up
    if config.planes != "auto":
        raise ValueError(f"unknown MVS plane family {config.planes!r} (auto, height, fronto)")
    if conf < 0.5 or nadir_angle_deg(cams, up) > config.max_nadir_deg:
        return None
    return up


def _resize(img: np.ndarray, cam: Camera) -> np.ndarray:
    """Area-average an HxWxC image to the size of ``cam``."""
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.nan_to_num(np.asarray(img, np.float32))).permute(2, 0, 1)[None]
    return F.interpolate(t, size=(cam.height, cam.width), mode="area")[0].permute(1, 2, 0).numpy()


def _upsample(a: np.ndarray, cam: Camera) -> np.ndarray:
    """Nearest-neighbour upsampling to ``cam``'s size (keeps NaN holes as holes)."""
    h, w = a.shape
    rows = np.minimum((np.arange(cam.height) + 0.5) * h / cam.height, h - 1).astype(np.int64)
    cols = np.minimum((np.arange(cam.width) + 0.5) * w / cam.width, w - 1).astype(np.int64)
    return a[rows][:, cols]


def _consistency_filter(cams: Sequence[Camera], results: list[MvsResult], tol: float, min_views: int,
                        max_reproj_px: float = 1.0) -> list[MvsResult]:
    """Keep depths that at least ``min_views`` other views confirm (forward-backward check).

    A pixel's 3D point is projected into view j, lifted again with j's own
    depth there and projected back: j confirms it when that round trip lands
    within ``max_reproj_px`` pixels of where it started and the two depths
    agree within the relative tolerance ``tol``. Comparing depths alone lets
    chance agreements between two wrong depth maps through (depth differences
    along j's ray are insensitive to sideways errors). A point that lies in
    front of the surface some other view sees along the same line of sight
    (a free-space violation) is dropped as well: two views matching each other
    on repetitive texture agree with each other, but such a floating point
    contradicts the third.
    """
    filtered = []
    for i, (ci, ri) in enumerate(zip(cams, results)):
        d = ri.depth.reshape(-1)
        ok = np.isfinite(d)
        X = ci.backproject(np.where(ok, d, 1.0).reshape(ci.height, ci.width))
        uv0, _ = ci.project(X)
        votes = np.zeros(d.size, np.int32)
        blocks = np.zeros(d.size, bool)
        for j, (cj, rj) in enumerate(zip(cams, results)):
            if j == i:
                continue
            uv, z = cj.project(X)
            u = np.floor(uv[:, 0]).astype(np.int64)
            v = np.floor(uv[:, 1]).astype(np.int64)
            inside = ok & (z > 0) & (u >= 0) & (u < cj.width) & (v >= 0) & (v < cj.height)
            idx = np.flatnonzero(inside)
            dj = rj.depth[v[idx], u[idx]].astype(np.float64)
            good = np.isfinite(dj)
            idx, dj = idx[good], dj[good]
            # Free-space violation: the point would float in front of the surface j sees there.
            blocks[idx[z[idx] < dj * (1.0 - 2.0 * tol)]] = True
            if not len(idx):
                continue
            # Lift j's depth at the pixel (sub-pixel position kept) and project it back into i.
            rays = np.stack([uv[idx, 0], uv[idx, 1], np.ones(len(idx))], 1) @ np.linalg.inv(cj.K).T
            Xj = (rays * dj[:, None] - cj.t) @ cj.R  # camera j -> world
            uvb, zb = ci.project(Xj)
            err = np.linalg.norm(uvb - uv0[idx], axis=1)
            agree = (err <= max_reproj_px) & (np.abs(zb - d[idx]) <= tol * np.abs(d[idx]))
            votes[idx[agree]] += 1
        keep = (ok & (votes >= min_views) & ~blocks).reshape(ci.height, ci.width)
        filtered.append(MvsResult(np.where(keep, ri.depth, np.nan).astype(np.float32),
                                  np.where(keep, ri.confidence, 0).astype(np.float32), ri.ncc))
        log.info("MVS view %s: %.1f%% pass the %d-view consistency check", ci.name, 100.0 * keep.mean(), min_views)
    return filtered


def _recentred(cam: Camera, origin: np.ndarray) -> Camera:
    """The same camera in a frame translated by ``-origin``."""
    from dataclasses import replace

    w2c = cam.w2c.copy()
    w2c[:3, 3] = cam.t + cam.R @ origin
    return replace(cam, w2c=w2c)
