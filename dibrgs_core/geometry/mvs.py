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
from dataclasses import asdict
from pathlib import Path
from typing import Sequence

import numpy as np

from ..camera.frame import span_factor
from ..camera.pinhole import Camera
from ..common.digest import Digest
from ..common.fileio import atomic_path
from .config import MvsConfig
from .depth_filters import MvsResult, consistency_filter, speckle_mask
from .sgm import semi_global
from .sweep_range import depth_range_for, scene_heights, sweep_up
from .view_selection import select_sources

log = logging.getLogger("dibrgs.mvs")


def _gray(img: np.ndarray):
    """(1, 1, H, W) luminance; NaN (no data) stays NaN."""
    import torch

    g = np.asarray(img, np.float32)
    if g.ndim == 3:
        g = g[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    return torch.from_numpy(np.ascontiguousarray(g))[None, None]


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

    Images may hold NaN where they have no data: a reference pixel whose window touches one gets
    no depth, and a source whose window does counts as not seeing the pixel at that plane.
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
        # a window touching no data matches nothing; the NaN must not reach the aggregation
        ref_ok = torch.isfinite(mu_r)[0, 0]
        r, mu_r = torch.nan_to_num(r), torch.nan_to_num(mu_r)
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
                c = torch.where(inside.reshape(n, H, W) & torch.isfinite(c), c, torch.full_like(c, float("inf")))
                per_src.append(c)
            stack = torch.stack(per_src, 0)  # (S, n, H, W)
            best = torch.sort(stack, dim=0).values[:n_keep]
            finite = torch.isfinite(best)
            cnt = finite.sum(0)
            agg = torch.where(finite, best, torch.zeros_like(best)).sum(0) / cnt.clamp_min(1)
            cost[k0:k0 + n] = torch.where((cnt > 0) & ref_ok, agg, torch.full_like(agg, 2.0))
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
        texture = sd_r[0, 0] >= cfg.min_texture_rel * sd_r[0, 0][ref_ok].median() if ref_ok.any() else ref_ok
        valid = (ncc_best >= cfg.min_ncc) & (conf >= cfg.min_confidence) & texture & ref_ok
        valid &= torch.isfinite(depth) & (c1 < 2) & (depth >= near * 0.99) & (depth <= far * 1.01)
        depth = torch.where(valid, depth, torch.full_like(depth, float("nan")))
        conf = torch.where(valid, conf, torch.zeros_like(conf))
    return MvsResult(depth.numpy().astype(np.float32), conf.numpy().astype(np.float32),
                     ncc_best.clamp(-1, 1).numpy().astype(np.float32))


class SweepCheckpoint:
    """Each view's sweep kept in ``folder`` as it finishes (one ``.npz`` a view, named by a digest
    of everything the sweep read: options, cameras, images, sources, range, planes), so that an
    initialisation stopped part way (killed, out of time) goes on from the next view. Files no
    sweep of the latest run used are removed at its end."""

    def __init__(self, folder: Path, cfg: MvsConfig, cams: Sequence[Camera], images: Sequence[np.ndarray],
                 up: np.ndarray | None, heights: tuple[float, float] | None) -> None:
        self.folder = Path(folder)
        self.used: set[Path] = set()
        self._base = Digest("mvs-sweep-1").json(asdict(cfg)).json(None if up is None else [float(v) for v in up]) \
            .json(None if heights is None else [float(v) for v in heights]).hex()
        self._views = [Digest("view").array(c.K).array(c.w2c).json([c.width, c.height]).array(im).hex()
                       for c, im in zip(cams, images)]

    def path(self, i: int, sources: Sequence[int], near: float, far: float) -> Path:
        key = Digest(self._base).json([self._views[i], [self._views[j] for j in sources],
                                             float(near), float(far)]).hex()
        return self.folder / f"{key}.npz"

    def load(self, path: Path) -> MvsResult | None:
        self.used.add(path)
        if not path.is_file():
            return None
        try:
            with np.load(path) as d:
                return MvsResult(d["depth"], d["confidence"], d["ncc"])
        except Exception as e:  # a damaged file is swept again, never fatal
            log.warning("%s unreadable (%s); sweeping again", path, e)
            return None

    def save(self, path: Path, res: MvsResult) -> None:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, depth=res.depth, confidence=res.confidence, ncc=res.ncc)

    def prune(self) -> None:
        for p in self.folder.glob("*.npz"):
            if p not in self.used:
                p.unlink(missing_ok=True)


def mvs_depths(cameras: Sequence[Camera], images: Sequence[np.ndarray], sparse_points: np.ndarray | None,
               fallback_distance: float, config: MvsConfig | None = None, progress: bool = True,
               checkpoint: Path | None = None) -> list[MvsResult]:
    """Plane-sweep depth for every view against the others (at most ``config.max_sources`` of them);
    ``images`` may hold NaN where a photo has no data (:func:`plane_sweep`).

    Camera translations are re-expressed relative to the mean camera centre
    (precision with georeferenced coordinates); depths do not change. With ``checkpoint`` (a
    folder) each view's sweep is kept there and reused (:class:`SweepCheckpoint`).
    """
    from tqdm import tqdm

    cfg = config or MvsConfig()
    full = list(cameras)
    longest = max(max(c.width, c.height) for c in full)
    f = cfg.max_size / longest if cfg.max_size and longest > cfg.max_size else 1.0
    if f < 1.0:
        images = [area_resize(im, c.scaled(f)) for im, c in zip(images, full)]
        cameras = [c.scaled(f) for c in full]
    cams = [_recentred(c, np.mean([c.center for c in cameras], axis=0)) for c in cameras]
    pts = None
    if sparse_points is not None and len(sparse_points):
        pts = np.asarray(sparse_points, np.float64) - np.mean([c.center for c in cameras], axis=0)
    up = sweep_up(cams, cfg)
    ranges = [depth_range_for(c, pts, fallback_distance) for c in cams]
    # Relief and depth tolerances in proportion to the ground a view covers, not to its distance.
    span = span_factor(cams)
    heights = None
    if up is not None and cfg.height_above > 0:
        heights = scene_heights(cams, up, cfg, pts, span)
        log.info("MVS height planes: %s", "every height the depth ranges allow (ground unknown)" if heights is None
                 else f"{cfg.height_below:g} below to {cfg.height_above:g} above the ground, in flying heights"
                 + ("" if abs(span - 1.0) < 0.01 else f" x the lens's span {span:.3g}"))
    sources = select_sources(cams, pts, ranges, cfg.max_sources)
    if any(len(s) < len(cams) - 1 for s in sources):
        log.info("MVS sources: each of %d views against at most %d others (those that see most of it from a "
                 "useful angle)", len(cams), cfg.max_sources)
    store = None if checkpoint is None else SweepCheckpoint(checkpoint, cfg, cams, images, up, heights)
    out = []
    for i in tqdm(range(len(cams)), desc="mvs", disable=not progress):
        near, far = ranges[i]
        path = None if store is None else store.path(i, sources[i], near, far)
        res = None if store is None else store.load(path)
        kept = res is not None
        if res is None:
            srcs = [(cams[j], images[j]) for j in sources[i]]
            res = plane_sweep(cams[i], images[i], srcs, near, far, cfg, up=up, height_range=heights)
            if store is not None:
                store.save(path, res)
        log.info("MVS view %s: range [%.3g, %.3g], %s planes, %.1f%% valid%s", cams[i].name, near, far,
                 "height" if up is not None else "fronto-parallel", 100.0 * np.isfinite(res.depth).mean(),
                 " (from the checkpoint)" if kept else "")
        out.append(res)
    if store is not None:
        store.prune()
    if cfg.speckle_px > 0:
        out = [MvsResult(*(np.where(keep, a, np.nan if k == 0 else 0).astype(np.float32) if k < 2 else a
                           for k, a in enumerate((r.depth, r.confidence, r.ncc))))
               for r in out for keep in [speckle_mask(r.depth, cfg.speckle_tol * span, cfg.speckle_px)]]
    if cfg.min_consistent_views > 0 and len(cams) > 1:
        out = consistency_filter(cams, out, cfg.consistency_tol * span, cfg.min_consistent_views, cfg.max_reproj_px,
                                 sources)
    if f < 1.0:
        out = [MvsResult(*(_upsample(a, c) for a in (r.depth, r.confidence, r.ncc))) for r, c in zip(out, full)]
    return out


def area_resize(img: np.ndarray, cam: Camera) -> np.ndarray:
    """Area-average an HxWxC image to the size of ``cam``; a pixel drawn from any NaN is NaN."""
    import torch
    import torch.nn.functional as F

    a = np.asarray(img, np.float32)
    t = torch.from_numpy(np.nan_to_num(a)).permute(2, 0, 1)[None]
    out = F.interpolate(t, size=(cam.height, cam.width), mode="area")[0].permute(1, 2, 0).numpy()
    nan = np.isnan(a).any(axis=2)
    if nan.any():
        share = F.interpolate(torch.from_numpy(nan.astype(np.float32))[None, None], size=(cam.height, cam.width),
                              mode="area")[0, 0].numpy()
        out[share > 1e-4] = np.nan
    return out


def _upsample(a: np.ndarray, cam: Camera) -> np.ndarray:
    """Nearest-neighbour upsampling to ``cam``'s size (keeps NaN holes as holes)."""
    h, w = a.shape
    rows = np.minimum((np.arange(cam.height) + 0.5) * h / cam.height, h - 1).astype(np.int64)
    cols = np.minimum((np.arange(cam.width) + 0.5) * w / cam.width, w - 1).astype(np.int64)
    return a[rows][:, cols]


def _recentred(cam: Camera, origin: np.ndarray) -> Camera:
    """The same camera in a frame translated by ``-origin``."""
    from dataclasses import replace

    w2c = cam.w2c.copy()
    w2c[:3, 3] = cam.t + cam.R @ origin
    return replace(cam, w2c=w2c)
