"""Pseudo views by progressive depth-image-based rendering (paper: "Pseudo View Supervision
through Progressive DIBR").

For each pseudo camera sampled along the training cameras' acquisition trajectory
(:mod:`dibrgs_core.camera.trajectory`: on an orbit, along flight strips, or between
neighbouring cameras) or taken from a path the caller gives:

1. depth: z-buffer projection of the dense point cloud (:func:`zbuffer_depth`),
   then depth completion (:func:`complete_depth`): small gaps from their
   neighbours; large holes, for near-nadir scenes, from the rasterised height
   field of the cloud (:class:`~dibrgs_core.geometry.surface.HeightField`), else
   from the nearest valid pixel;
2. colour: every target pixel is back-projected with that depth and projected
   once into each training view (:func:`sample_sources`); a source fills only
   pixels that are still empty and that it sees (occlusion test against the
   source's own depth map of the same cloud), nearest source first
   (:func:`fill_progressive`);
3. what no source sees is padded and flagged, so the trainer can mask it;
4. warped pixels that two sources see but colour differently (wrong depth, most
   likely) are rejected from supervision (:func:`disagreement`); with the
   height field, each pixel takes whichever of the two depths the sources agree
   on better.

Sampled poses are kept only where the cloud covers the view, and a view whose
warped share is too small is dropped (:func:`build_pseudo_views`).

Conventions: OpenCV cameras from :mod:`dibrgs_core.camera.pinhole`, pixel centres at
+0.5, z-depth in world units along the camera axis, 0 marks "no depth".
Whole-image NumPy / torch on the CPU.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from scipy import ndimage

from ..camera.pinhole import Camera
from ..camera.trajectory import Trajectory, classify, sample_poses
from ..common.fileio import atomic_path, write_json
from ..geometry.pointcloud import point_spacing, zbuffer

log = logging.getLogger("dibrgs.pseudo_views")

EMPTY = -1  #: ``filled_by`` value of pixels nothing could fill
PADDED = -2  #: ``filled_by`` value of padded pixels
RTOL = 0.02  #: relative depth tolerance of the occlusion test (:func:`sample_sources`)
_CACHE_VERSION = "pseudo-v4"


@dataclass
class PseudoView:
    """A synthesised supervision view.

    Attributes:
        camera: the pseudo camera.
        image: float32 (H,W,3) in [0,1].
        valid: bool (H,W), pixels warped from a training view that sees them.
        padded: bool (H,W), pixels filled by padding (less reliable); never
            also ``valid``. Pixels neither valid nor padded are black holes.
        depth: float32 (H,W) completed z-depth used for warping (0 = none).
        rejected: bool (H,W), warped pixels left out of supervision because
            the sources that see them disagree on their colour; neither
            ``valid`` nor ``padded``.
    """

    camera: Camera
    image: np.ndarray
    valid: np.ndarray
    padded: np.ndarray
    depth: np.ndarray | None = None
    rejected: np.ndarray | None = None


@dataclass
class PseudoBuild:
    """What :func:`build_pseudo_views` made, and how.

    Attributes:
        views: the kept pseudo views.
        trajectory: the training cameras' trajectory (None with a user path).
        tried: sampled poses built or rejected before ``len(views)`` were kept.
        dropped_cloud: poses left out because the dense cloud covers too little of the view.
        dropped_warped: views dropped because too little of them is warped.
        cpu_s: process CPU seconds the build took (0 when loaded from the cache).
        cached: loaded from the cache.
    """

    views: list[PseudoView]
    trajectory: Trajectory | None = None
    tried: int = 0
    dropped_cloud: int = 0
    dropped_warped: int = 0
    cpu_s: float = 0.0
    cached: bool = False

    def mean_fractions(self) -> dict[str, float]:
        """Mean warped / padded / rejected share of the kept views' pixels (0 without views)."""
        def mean(key: str) -> float:
            xs = [getattr(v, key).mean() for v in self.views if getattr(v, key) is not None]
            return float(np.mean(xs)) if xs else 0.0

        return {"warped": mean("valid"), "padded": mean("padded"), "rejected": mean("rejected")}


# ---------------------------------------------------------------------------
# Depth
# ---------------------------------------------------------------------------
def zbuffer_depth(points: np.ndarray, cam: Camera, spacing: float | None = None,
                  max_radius: int = 4) -> np.ndarray:
    """Depth (H,W) float32 of the nearest point per pixel; 0 where no point lands.

    Each point is splatted as a square of half-size ``round(spacing * f / z / 2)``
    pixels (at most ``max_radius``), so a voxel-downsampled cloud still covers
    the image; ``spacing`` defaults to :func:`point_spacing`.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if spacing is None:
        spacing = point_spacing(pts)
    return zbuffer(cam, pts, footprint=spacing, max_radius=max_radius, empty=0.0).astype(np.float32)


def _neighbours_at(a: np.ndarray, ys: np.ndarray, xs: np.ndarray, radius: int, pad: str = "constant"
                   ) -> np.ndarray:
    """Values of ``a`` (H,W) at every offset of a (2r+1)^2 window round pixels (ys, xs), the
    centre last: ((2r+1)^2, len(ys)). Outside the image: 0 (``pad`` constant) or the edge (edge)."""
    p = np.pad(a, radius, mode=pad)
    offs = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1) if dy or dx]
    return np.stack([p[ys + radius + dy, xs + radius + dx] for dy, dx in offs + [(0, 0)]])


def remove_see_through(depth: np.ndarray, rtol: float = 0.03, radius: int = 2,
                       frac: float = 0.5) -> np.ndarray:
    """Closest-surface consistency: drop depths that lie behind most of their neighbours.

    Background points leak through gaps between splats of a foreground
    surface; such a pixel has a depth larger than most valid neighbours (by
    more than ``rtol`` relative). At a genuine occlusion edge only about half
    the window is foreground, so edges survive with ``frac`` = 0.5. Returns a
    copy with those pixels set to 0.
    """
    d = np.asarray(depth, dtype=np.float32).copy()
    H, W = d.shape
    p = np.pad(d, radius)
    thr = d * np.float32(1.0 - rtol)
    nvalid = np.zeros((H, W), np.int16)
    closer = np.zeros((H, W), np.int16)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy or dx:
                nb = p[radius + dy:radius + dy + H, radius + dx:radius + dx + W]
                ok = nb > 0
                nvalid += ok
                closer += ok & (nb < thr)
    leak = (d > 0) & (nvalid >= 4) & (closer > frac * nvalid)
    d[leak] = 0.0
    return d


def complete_depth(depth: np.ndarray, iters: int = 4, min_neighbours: int = 3,
                   fill: np.ndarray | None = None) -> np.ndarray:
    """Fill the holes (0 or non-finite) of a z-buffer depth map; returns float32 (H,W).

    Steps: remove see-through speckles (:func:`remove_see_through`); fill
    small gaps with the median of valid 8-neighbours for a few passes (only
    where at least ``min_neighbours`` are valid, so gaps close from inside
    rather than smearing edges); give the remaining holes the depth in
    ``fill`` (H,W, e.g. a height field's; used where finite and > 0)
    and what is still empty the depth of the nearest valid pixel (Euclidean
    distance transform); then a 3x3 median (edges repeated) over the filled
    pixels to smooth the seams. A map with no valid pixel and no ``fill``
    comes back as all zeros. Work is done at the holes only.
    """
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    if fill is not None:
        fill = np.where(np.isfinite(fill) & (fill > 0), fill, 0.0).astype(np.float32)
        if fill.shape != d.shape:
            raise ValueError(f"fill depth has shape {fill.shape}, the depth map {d.shape}")
    if not (d > 0).any():
        return np.zeros_like(d) if fill is None else complete_depth(fill, iters, min_neighbours)
    d = remove_see_through(d)
    hole0 = d <= 0
    for _ in range(iters):
        ys, xs = np.nonzero(d <= 0)
        if len(ys) == 0:
            break
        nb = _neighbours_at(d, ys, xs, 1)[:-1]
        ok = nb > 0
        cnt = ok.sum(0)
        can = cnt >= min_neighbours
        if not can.any():
            break
        # Median of the valid neighbours: sorted with the invalid ones (NaN) last.
        vals = np.sort(np.where(ok[:, can], nb[:, can], np.nan), axis=0)
        c, col = cnt[can], np.arange(int(can.sum()))
        d[ys[can], xs[can]] = 0.5 * (vals[(c - 1) // 2, col] + vals[c // 2, col])
    if fill is not None:
        take = (d <= 0) & (fill > 0)
        d[take] = fill[take]
    hole = d <= 0
    if hole.any():
        idx = ndimage.distance_transform_edt(hole, return_distances=False, return_indices=True)
        d = d[idx[0], idx[1]]
    if hole0.any():
        ys, xs = np.nonzero(hole0)
        d[ys, xs] = np.median(_neighbours_at(d, ys, xs, 1, pad="edge"), axis=0)
    return d.astype(np.float32)


# ---------------------------------------------------------------------------
# Warping
# ---------------------------------------------------------------------------
@dataclass
class SourceSamples:
    """One source view seen from the target's pixels at one depth hypothesis (all (H*W,) rows).

    Attributes:
        colour: float32 (N,3) bilinear colour at the projection, coordinates clamped to the
            image (the padding colour where the projection falls outside).
        front: the back-projected point is in front of the source camera.
        inside: ... and projects inside the source image.
        visible: ... and passes the occlusion test against the source depth.
    """

    colour: np.ndarray
    front: np.ndarray
    inside: np.ndarray
    visible: np.ndarray


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colour (N,3) of (h,w,3) ``img`` at pixel coordinates ``uv`` (centres at +0.5),
    coordinates clamped to the outer pixel centres."""
    h, w = img.shape[:2]
    t = torch.from_numpy(np.ascontiguousarray(img[..., :3], dtype=np.float32)).permute(2, 0, 1)[None]
    g = torch.from_numpy(np.stack([uv[:, 0] * (2.0 / w) - 1.0, uv[:, 1] * (2.0 / h) - 1.0], -1)
                         .astype(np.float32))[None, None]
    out = torch.nn.functional.grid_sample(t, g, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T.numpy()


class _Projector:
    """The target's pixels ``p`` projected into each source as ``a_s + d B_s p`` (homogeneous
    source pixels for depth ``d``): ``a_s = K_s (R_s C_t + t_s)``, ``B_s = K_s R_s R_t^T K_t^-1``
    (the paper's ``K_i T_{j->i} D_j K_j^-1 p_j``). Built once a view, so each depth hypothesis
    costs one multiply-add per pixel and source."""

    def __init__(self, target: Camera, sources: Sequence[tuple]):
        j, i = np.meshgrid(np.arange(target.height) + 0.5, np.arange(target.width) + 0.5, indexing="ij")
        self.px, self.py = i.ravel(), j.ravel()
        self.target = target
        to_world = target.R.T @ np.linalg.inv(target.K)  # pixel -> world direction (camera-z 1)
        self.a = [s[0].K @ (s[0].R @ target.center + s[0].t) for s in sources]
        # Elementwise rather than (3,3) @ (3,N): no BLAS threads for a few multiply-adds.
        self.B = [self._apply(s[0].K @ s[0].R @ to_world) for s in sources]
        self.to_world = to_world

    def _apply(self, M: np.ndarray) -> list[np.ndarray]:
        return [M[k, 0] * self.px + M[k, 1] * self.py + M[k, 2] for k in range(3)]

    def sample(self, depth: np.ndarray, sources: Sequence[tuple], rtol: float) -> list[SourceSamples]:
        depth = np.asarray(depth, dtype=np.float64).ravel()
        has_d = np.isfinite(depth) & (depth > 0)
        d = np.where(has_d, depth, 1.0)
        out = []
        for src, a, B in zip(sources, self.a, self.B):
            cam_s, im_s = src[0], np.asarray(src[1])
            d_s = src[2] if len(src) > 2 and src[2] is not None else None
            if d_s is None:
                X = self.target.center + d[:, None] * np.stack(self._apply(self.to_world), 1)
                sp = float(np.median(depth[has_d])) / max(self.target.fx, 1e-12) if has_d.any() else 0.0
                d_s = zbuffer_depth(X[has_d], cam_s, spacing=sp)
            d_s = np.asarray(d_s, dtype=np.float64)
            hs, ws = im_s.shape[:2]
            h0, h1, z = (a[k] + d * B[k] for k in range(3))
            front = has_d & (z > 1e-12 * np.maximum(np.maximum(np.abs(h0), np.abs(h1)), np.abs(z)))
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.where(front, h0 / z, 0.0)
                v = np.where(front, h1 / z, 0.0)
            front &= np.isfinite(u) & np.isfinite(v)
            inside = front & (u >= 0) & (u < ws) & (v >= 0) & (v < hs)
            ds = d_s[np.clip(v, 0, hs - 1).astype(np.int64), np.clip(u, 0, ws - 1).astype(np.int64)]
            visible = inside & (ds > 0) & (z <= ds * (1.0 + rtol))
            out.append(SourceSamples(_sample(im_s, np.stack([u, v], -1)), front, inside, visible))
        return out


def sample_sources(target: Camera, depth: np.ndarray, sources: Sequence[tuple], rtol: float = RTOL
                   ) -> list[SourceSamples]:
    """Project the target's pixels, back-projected at ``depth`` (H,W; 0 = none), once into each source.

    ``sources`` are ``(camera, image (h,w,3))`` or ``(camera, image, depth (h,w))`` tuples. The
    source depth (0 = unknown) is used for the occlusion test: a pixel is visible in a source
    when its depth there is at most ``source_depth * (1 + rtol)``; without it, one is
    z-buffered from the target's own back-projected pixels.
    """
    return _Projector(target, sources).sample(depth, sources, rtol)


def source_order(target: Camera, sources: Sequence[tuple]) -> np.ndarray:
    """Indices of ``sources`` from the nearest camera centre to the target's to the farthest."""
    return np.argsort([np.linalg.norm(s[0].center - target.center) for s in sources], kind="stable")


def fill_progressive(samples: Sequence[SourceSamples], order: Sequence[int], shape: tuple[int, int]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill the target from per-source samples, sources in ``order`` (nearest first).

    Returns ``(image (H,W,3) float32, valid (H,W) bool, filled_by (H,W) int32)``.
    ``filled_by`` holds the index of the source that filled a valid pixel,
    :data:`PADDED` for padded pixels and :data:`EMPTY` for pixels left black (only when
    nothing can be padded). Padding: pixels outside every source's image take the clamped
    colour of the nearest source they are in front of ("warping with padding"); occluded
    pixels and pixels without depth take the colour of the nearest filled pixel.
    """
    H, W = shape
    img = np.zeros((H * W, 3), np.float32)
    valid = np.zeros(H * W, bool)
    filled_by = np.full(H * W, EMPTY, np.int32)
    if not len(samples):
        return img.reshape(H, W, 3), valid.reshape(H, W), filled_by.reshape(H, W)
    seen_inside = np.zeros(H * W, bool)
    padded_from = np.full(H * W, -1, np.int64)
    for k in order:
        s = samples[k]
        new = s.visible & ~valid
        img[new] = s.colour[new]
        valid |= new
        filled_by[new] = k
        seen_inside |= s.inside
        padded_from[(padded_from < 0) & s.front] = k
    out = ~valid & ~seen_inside & (padded_from >= 0)
    for k in np.unique(padded_from[out]):
        m = out & (padded_from == k)
        img[m] = samples[k].colour[m]
        filled_by[m] = PADDED
    done = filled_by != EMPTY
    if done.any() and not done.all():
        ii = ndimage.distance_transform_edt(~done.reshape(H, W), return_distances=False, return_indices=True)
        near = (ii[0] * W + ii[1]).ravel()
        rest = ~done
        img[rest] = img[near[rest]]
        filled_by[rest] = PADDED
    return img.reshape(H, W, 3), valid.reshape(H, W), filled_by.reshape(H, W)


def disagreement(samples: Sequence[SourceSamples], shape: tuple[int, int], min_common: int = 64
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(count (H,W) int32, spread (H,W) float32)``: how many sources see each pixel, and the
    largest mean absolute RGB difference between two of them (0 where fewer than two do).

    With the right depth, sources agree up to shading and exposure; a wrong depth samples
    different surfaces in different views. Photographs differ in exposure, so each pair is
    compared after a gain per channel (the median of the colour ratios over the pixels both
    see, when at least ``min_common`` do; clamped to [0.5, 2]) - exposure is not a depth
    error. (The ratio of the median colours is no estimate: on a generated city, whose views
    share one exposure, it strays to 1.2 where the median ratio stays within 4 % of 1.)
    """
    n = shape[0] * shape[1]
    count = np.zeros(n, np.int32)
    spread = np.zeros(n, np.float32)
    for a in range(len(samples)):
        count += samples[a].visible
        for b in range(a + 1, len(samples)):
            both = samples[a].visible & samples[b].visible
            if not both.any():
                continue
            ca, cb = samples[a].colour[both], samples[b].colour[both]
            gain = np.ones(3, np.float32)
            if len(ca) >= min_common:
                step = max(1, len(ca) // 4096)  # a few thousand ratios pin the median down
                gain = np.clip(np.median((cb[::step] + 0.02) / (ca[::step] + 0.02), 0), 0.5, 2.0).astype(np.float32)
            spread[both] = np.maximum(spread[both], np.abs(ca * gain - cb).mean(-1))
    return count.reshape(shape), spread.reshape(shape)


def warp_progressive(target: Camera, depth: np.ndarray, sources: Sequence[tuple], rtol: float = RTOL
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Synthesise the target view from source images, nearest source first: :func:`sample_sources`
    then :func:`fill_progressive` (see both for the arguments and the result)."""
    shape = (target.height, target.width)
    if not sources:
        return fill_progressive([], [], shape)
    return fill_progressive(sample_sources(target, depth, sources, rtol), source_order(target, sources), shape)


def source_disagreement(target: Camera, depth: np.ndarray, sources: Sequence[tuple]
                        ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`disagreement` of the sources warped into ``target`` at ``depth``."""
    return disagreement(sample_sources(target, depth, sources), (target.height, target.width))


def _merge(a: Sequence[SourceSamples], b: Sequence[SourceSamples], take: np.ndarray) -> list[SourceSamples]:
    """Per pixel, ``b``'s samples where ``take`` (H*W,) else ``a``'s."""
    def pick(x, y):
        return np.where(take[:, None] if x.ndim == 2 else take, y, x)

    return [SourceSamples(pick(x.colour, y.colour), pick(x.front, y.front), pick(x.inside, y.inside),
                          pick(x.visible, y.visible)) for x, y in zip(a, b)]


# ---------------------------------------------------------------------------
# Building and caching
# ---------------------------------------------------------------------------
#: Defaults of :func:`build_pseudo_views`' pose filters (fractions of the view's pixels).
MIN_CLOUD_COVER = 0.5
MIN_WARPED = 0.2
#: At most this many sampled poses per requested view are tried.
CANDIDATES_PER_VIEW = 3


def _hash_inputs(train_views: Sequence, points: np.ndarray, options: dict, path: Sequence[Camera] | None) -> str:
    """Key of a pseudo-view set: the version, every training view (camera, name, image), the
    cloud, every option and the user path."""
    h = hashlib.sha256(_CACHE_VERSION.encode())
    h.update(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    h.update(json.dumps(options, sort_keys=True).encode())

    def cam(c: Camera) -> None:
        h.update(np.ascontiguousarray(c.K).tobytes() + np.ascontiguousarray(c.w2c).tobytes())
        h.update(f"{c.width}x{c.height}:{c.name}".encode())

    h.update(f"views={len(train_views)}".encode())
    for v in train_views:
        cam(v.camera)
        img = np.ascontiguousarray(v.image, dtype=np.float32)
        h.update(f"{img.shape}".encode())
        h.update(img.tobytes())
    h.update(f"path={path is not None}:{len(path or [])}".encode())
    for c in path or []:
        cam(c)
    return h.hexdigest()


def _save_view(p: Path, pv: PseudoView) -> None:
    """One view as an uncompressed ``.npz`` (floats barely compress, and compressing cost more
    than building the view); the image is float16, as :func:`_build_one` rounds it."""
    c = pv.camera
    arrays = {"K": c.K, "w2c": c.w2c, "size": np.array([c.width, c.height]), "name": np.array(c.name),
              "image": pv.image.astype(np.float16), "valid": pv.valid, "padded": pv.padded,
              "depth": np.zeros((0,), np.float32) if pv.depth is None else pv.depth,
              "rejected": np.zeros((0,), bool) if pv.rejected is None else pv.rejected}
    with atomic_path(p) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def _load_view(p: Path) -> PseudoView:
    with np.load(p, allow_pickle=False) as z:
        W, H = (int(v) for v in z["size"])
        cam = Camera(K=z["K"], w2c=z["w2c"], width=W, height=H, name=str(z["name"]))
        depth, rejected = z["depth"], z["rejected"]
        return PseudoView(cam, z["image"].astype(np.float32), z["valid"].astype(bool), z["padded"].astype(bool),
                          depth if depth.size else None, rejected.astype(bool) if rejected.size else None)


def _load_cache(cache_dir: Path, key: str) -> tuple[list[PseudoView], dict] | None:
    man = cache_dir / "manifest.json"
    if not man.is_file():
        return None
    try:
        m = json.loads(man.read_text())
        if m.get("hash") != key:
            return None
        return [_load_view(cache_dir / f) for f in m["files"]], m.get("stats", {})
    except (OSError, ValueError, KeyError, TypeError) as e:
        log.warning("pseudo-view cache in %s unreadable (%s); rebuilding", cache_dir, e)
        return None


def _scene_depth(points: np.ndarray, cams: Sequence[Camera]) -> float | None:
    """Median z-depth of the cloud in front of the cameras (world units), or None."""
    zs = [c.world_to_cam(points[:: max(1, len(points) // 5000)])[:, 2] for c in cams] if len(points) else []
    z = np.concatenate(zs) if zs else np.zeros(0)
    z = z[np.isfinite(z) & (z > 0)]
    return float(np.median(z)) if len(z) else None


def build_pseudo_views(train_views: Sequence, points: np.ndarray, n: int, seed: int, cache_dir: str | Path,
                       path: Sequence[Camera] | None = None, max_gap_px: float = 4.0,
                       surface: bool = False, consistency_tol: float = 0.0,
                       min_cloud_cover: float = MIN_CLOUD_COVER, min_warped: float = MIN_WARPED,
                       jitter: float = 0.1, look_jitter_deg: float = 2.0) -> PseudoBuild:
    """Build (or load from ``cache_dir``) the progressive-DIBR pseudo views.

    Args:
        train_views: :class:`~dibrgs_core.data.scene.View` objects (camera + image), the sources.
        points: (N,3) dense point cloud in world units.
        n: number of pseudo views wanted (ignored when ``path`` is given).
        seed: seed of the pose sampling.
        cache_dir: folder for ``view_NNN.npz`` files and ``manifest.json``; the manifest
            stores a hash of every input (the training cameras, names and images, the
            cloud, every option, the path, the code version), so changed inputs - another
            scene, another split - rebuild and identical ones load (resume). Files are
            written atomically and the manifest last.
        path: cameras to use instead of sampled poses; all are kept, none filtered.
        max_gap_px: warped pixels farther than this (pixels) from any pixel the cloud
            projects to have completed, not measured, depth; they are returned as
            ``padded`` rather than ``valid``.
        surface: complete large depth holes (target and source views) from the
            rasterised :class:`~dibrgs_core.geometry.surface.HeightField` of ``points``
            instead of the nearest valid pixel; for near-nadir scenes.
        consistency_tol: warped pixels that at least two sources see with a mean absolute
            RGB difference above this (image units in [0,1]) are ``rejected``; 0 keeps
            them all. With ``surface`` too, a pixel whose completed-cloud depth and
            height-field depth are both seen by two sources takes the one they agree on
            better (floating MVS points over a street hidden from one view otherwise win
            the z-buffer).
        min_cloud_cover: a sampled pose is skipped when less than this share of its pixels
            lies within ``max_gap_px`` of a pixel the cloud projects to.
        min_warped: a sampled view is dropped when less than this share of its pixels is
            warped (``valid``).
        jitter, look_jitter_deg: pose jitter (:func:`~dibrgs_core.camera.trajectory.sample_poses`).

    Sampled poses come from :func:`~dibrgs_core.camera.trajectory.classify` of the training
    cameras; up to :data:`CANDIDATES_PER_VIEW` x ``n`` are tried, in their seeded order,
    until ``n`` are kept.
    """
    from tqdm import tqdm

    cache_dir = Path(cache_dir)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    options = {"n": n, "seed": seed, "max_gap_px": max_gap_px, "surface": surface,
               "consistency_tol": consistency_tol, "min_cloud_cover": min_cloud_cover, "min_warped": min_warped,
               "jitter": jitter, "look_jitter_deg": look_jitter_deg, "candidates": CANDIDATES_PER_VIEW}
    key = _hash_inputs(train_views, pts, options, path)
    train_cams = [v.camera for v in train_views]
    traj = None if path is not None else classify(train_cams, scene_depth=_scene_depth(pts, train_cams))
    cached = _load_cache(cache_dir, key)
    if cached is not None:
        views, stats = cached
        log.info("loaded %d pseudo views from %s", len(views), cache_dir)
        return PseudoBuild(views, traj, int(stats.get("tried", len(views))), int(stats.get("dropped_cloud", 0)),
                           int(stats.get("dropped_warped", 0)), 0.0, True)
    t0 = time.process_time()
    if path is not None:
        cams, filtered = list(path), False
    elif n > 0 and train_cams:
        cams, filtered = sample_poses(traj, train_cams, CANDIDATES_PER_VIEW * n, seed, jitter, look_jitter_deg), True
    else:
        cams, filtered = [], False
    spacing = point_spacing(pts)
    hfield = None
    if surface and len(pts):
        from ..geometry.surface import HeightField

        hfield = HeightField.build(pts, train_cams)
    sources = []
    for v in train_views:
        fill = None if hfield is None else hfield.depth(v.camera)
        sources.append((v.camera, np.asarray(v.image, np.float32)[..., :3],
                        complete_depth(zbuffer_depth(pts, v.camera, spacing), fill=fill)))
    check = consistency_tol > 0 and len(sources) > 1
    (cache_dir / "manifest.json").unlink(missing_ok=True)  # a crash mid-rebuild must not look complete
    out, files = [], []
    tried = dropped_cloud = dropped_warped = 0
    bar = tqdm(total=len(cams) if not filtered else n, desc="pseudo views", unit="view", leave=False)
    for cam in cams:
        if filtered and len(out) >= n:
            break
        tried += 1
        pv = _build_one(cam, pts, spacing, hfield, sources, check, consistency_tol, max_gap_px,
                        min_cloud_cover if filtered else 0.0)
        if pv is None:
            dropped_cloud += 1
            continue
        if filtered and pv.valid.mean() < min_warped:
            dropped_warped += 1
            continue
        pv.camera.name = f"pseudo_{len(out):03d}" if filtered else cam.name
        fname = f"view_{len(out):03d}.npz"
        _save_view(cache_dir / fname, pv)
        files.append(fname)
        out.append(pv)
        bar.update(1)
        log.info("pseudo view %s: %.1f%% warped, %.1f%% padded, %.1f%% rejected", pv.camera.name,
                 100 * pv.valid.mean(), 100 * pv.padded.mean(), 0.0 if pv.rejected is None else 100 * pv.rejected.mean())
    bar.close()
    stats = {"tried": tried, "dropped_cloud": dropped_cloud, "dropped_warped": dropped_warped}
    write_json(cache_dir / "manifest.json", {"hash": key, "files": files, "count": len(files), "stats": stats})
    return PseudoBuild(out, traj, tried, dropped_cloud, dropped_warped, time.process_time() - t0)


def _build_one(cam: Camera, pts: np.ndarray, spacing: float, hfield, sources: list[tuple], check: bool,
               consistency_tol: float, max_gap_px: float, min_cloud_cover: float) -> PseudoView | None:
    """One pseudo view (None when the cloud covers less than ``min_cloud_cover`` of it)."""
    shape = (cam.height, cam.width)
    raw = zbuffer_depth(pts, cam, spacing)
    # Depth invented far from any projected point (outside the cloud) is a guess: its warped
    # colour is demoted to padding.
    if (raw > 0).any():
        guessed = ndimage.distance_transform_edt(raw <= 0) > max_gap_px
    else:
        guessed = np.ones(shape, bool)
    if min_cloud_cover > 0 and 1.0 - guessed.mean() < min_cloud_cover:
        return None
    surf = None if hfield is None else hfield.depth(cam)
    depth = complete_depth(raw, fill=surf)
    proj = _Projector(cam, sources)
    samples = proj.sample(depth, sources, RTOL)
    count = spread = None
    if check:
        count, spread = disagreement(samples, shape)
        if surf is not None:
            # Two depth hypotheses, the completed cloud and the height field: where both are
            # seen by two sources, keep the one whose colours agree more. Floating MVS points in
            # front of occluded streets lose to the ground.
            s_surf = proj.sample(surf, sources, RTOL)
            c2, s2 = disagreement(s_surf, shape)
            take = (count >= 2) & (c2 >= 2) & (s2 < spread) & (surf > 0)
            if take.any():
                depth = np.where(take, surf, depth).astype(np.float32)
                count, spread = np.where(take, c2, count), np.where(take, s2, spread)
                samples = _merge(samples, s_surf, take.ravel())
    image, valid, filled_by = fill_progressive(samples, source_order(cam, sources), shape)
    image = image.astype(np.float16).astype(np.float32)  # as cached (8-bit sources: far below their step)
    padded = filled_by == PADDED
    padded |= valid & guessed
    valid &= ~guessed
    rejected = None
    if check:
        rejected = (valid | padded) & (count >= 2) & (spread > consistency_tol)
        valid &= ~rejected
        padded &= ~rejected
    return PseudoView(cam, image, valid, padded, depth, rejected)


__all__ = ["PseudoView", "PseudoBuild", "SourceSamples", "EMPTY", "PADDED", "zbuffer_depth", "remove_see_through",
           "complete_depth", "sample_sources", "source_order", "fill_progressive", "disagreement",
           "warp_progressive", "source_disagreement", "build_pseudo_views", "MIN_CLOUD_COVER", "MIN_WARPED"]
