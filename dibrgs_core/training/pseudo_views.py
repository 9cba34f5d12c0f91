"""Pseudo views by progressive depth-image-based rendering (paper: "Pseudo View Supervision
through Progressive DIBR").

For each pseudo camera sampled on the acquisition orbit (or taken from a path
the caller gives):

1. depth: z-buffer projection of the dense point cloud (:func:`zbuffer_depth`),
   then depth completion (:func:`complete_depth`): small gaps from their
   neighbours; large holes, for near-nadir scenes, by ray casting a height
   field of the cloud (:class:`surface.HeightField`), else from the nearest
   valid pixel;
2. colour: every target pixel is back-projected with that depth and looked up
   in the training images, nearest source camera first; a source fills only
   pixels that are still empty and that it sees (occlusion test against the
   source's own depth map of the same cloud) (:func:`warp_progressive`);
3. what no source sees is padded and flagged, so the trainer can mask it;
4. warped pixels that two sources see but colour differently (wrong depth, most
   likely) are rejected from supervision (:func:`source_disagreement`).

Conventions: OpenCV cameras from :mod:`dibrgs_core.camera.pinhole`, pixel centres at
+0.5, z-depth in world units along the camera axis, 0 marks "no depth".
Everything here is NumPy on the CPU.
"""
from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy import ndimage

from ..camera.pinhole import Camera
from ..camera.orbit import fit_orbit
from ..common.fileio import atomic_path, write_json
from ..geometry.pointcloud import point_spacing, zbuffer

log = logging.getLogger("dibrgs.pseudo_views")

EMPTY = -1  #: ``filled_by`` value of pixels nothing could fill
PADDED = -2  #: ``filled_by`` value of padded pixels
_CACHE_VERSION = "pseudo-v3"


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


# ---------------------------------------------------------------------------
# Poses
# ---------------------------------------------------------------------------
def sample_orbit_poses(train_cams: Sequence[Camera], n: int, seed: int,
                       path: Sequence[Camera] | None = None) -> list[Camera]:
    """Pseudo cameras: ``n`` random angles on the training cameras' orbit.

    The circle comes from :func:`cameras.fit_orbit`; the cameras look at the
    orbit's target with the first training camera's intrinsics and are named
    ``pseudo_000``... Angles are uniform on the whole circle (seeded). If
    ``path`` is given (e.g. cameras from a Blender curve) those cameras are
    returned as they are and ``n``/``seed`` are ignored.
    """
    if path is not None:
        return list(path)
    if n <= 0:
        return []
    if len(train_cams) < 2:
        raise ValueError("pseudo views on the orbit need at least 2 training cameras")
    orbit = fit_orbit(train_cams)
    thetas = np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi, size=n)
    cams = orbit.cameras(thetas, like=train_cams[0])
    for i, c in enumerate(cams):
        c.name = f"pseudo_{i:03d}"
    return cams


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


def _neighbours(a: np.ndarray, radius: int, fill: float) -> np.ndarray:
    """Stack of ``a`` shifted by every offset in a (2r+1)^2 window except (0,0)."""
    H, W = a.shape
    p = np.pad(a, radius, mode="constant", constant_values=fill)
    out = [p[radius + dy:radius + dy + H, radius + dx:radius + dx + W]
           for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1) if dy or dx]
    return np.stack(out)


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
    valid = d > 0
    nb = _neighbours(d, radius, 0.0)
    nvalid = (nb > 0).sum(0)
    closer = ((nb > 0) & (nb < d * (1.0 - rtol))).sum(0)
    leak = valid & (nvalid >= 4) & (closer > frac * nvalid)
    d[leak] = 0.0
    return d


def complete_depth(depth: np.ndarray, iters: int = 4, min_neighbours: int = 3,
                   fill: np.ndarray | None = None) -> np.ndarray:
    """Fill the holes (0 or non-finite) of a z-buffer depth map; returns float32 (H,W).

    Steps: remove see-through speckles (:func:`remove_see_through`); fill
    small gaps with the median of valid 8-neighbours for a few passes (only
    where at least ``min_neighbours`` are valid, so gaps close from inside
    rather than smearing edges); give the remaining holes the depth in
    ``fill`` (H,W, e.g. a ray-cast height field; used where finite and > 0)
    and what is still empty the depth of the nearest valid pixel (Euclidean
    distance transform); then a 3x3 median filter over the filled pixels to
    smooth the seams. A map with no valid pixel and no ``fill`` comes back
    as all zeros.
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
        hole = d <= 0
        if not hole.any():
            break
        nb = _neighbours(d, 1, 0.0)
        cnt = (nb > 0).sum(0)
        can = hole & (cnt >= min_neighbours)
        if not can.any():
            break
        vals = np.where(nb[:, can] > 0, nb[:, can], np.nan)
        d[can] = np.nanmedian(vals, axis=0)
    if fill is not None:
        take = (d <= 0) & (fill > 0)
        d[take] = fill[take]
    hole = d <= 0
    if hole.any():
        idx = ndimage.distance_transform_edt(hole, return_distances=False, return_indices=True)
        d = d[idx[0], idx[1]]
    if hole0.any():
        med = ndimage.median_filter(d, size=3, mode="nearest")
        d[hole0] = med[hole0]
    return d.astype(np.float32)


# ---------------------------------------------------------------------------
# Warping
# ---------------------------------------------------------------------------
def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample (H,W,C) at pixel coordinates (pixel centres at +0.5), edges clamped."""
    H, W = img.shape[:2]
    x = np.clip(u - 0.5, 0.0, W - 1.0)
    y = np.clip(v - 0.5, 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 1)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 1)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    ax, ay = (x - x0)[:, None], (y - y0)[:, None]
    top = img[y0, x0] * (1 - ax) + img[y0, x1] * ax
    bot = img[y1, x0] * (1 - ax) + img[y1, x1] * ax
    return top * (1 - ay) + bot * ay


def warp_progressive(target: Camera, depth: np.ndarray, sources: Sequence[tuple],
                     rtol: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Synthesise the target view from source images, nearest source first.

    Args:
        target: the pseudo camera.
        depth: (H,W) z-depth of the target (0 = unknown), e.g. completed.
        sources: ``(camera, image (h,w,3))`` or ``(camera, image, depth (h,w))``
            tuples. The source depth (0 = unknown) is used for the occlusion
            test; without it, one is z-buffered from the target's own
            back-projected pixels.
        rtol: relative depth tolerance of the occlusion test: a target pixel
            is visible in a source when its depth there is at most
            ``source_depth * (1 + rtol)``.

    Returns:
        ``(image (H,W,3) float32, valid (H,W) bool, filled_by (H,W) int32)``.
        ``filled_by`` holds the index into ``sources`` of the view that
        filled a valid pixel, :data:`PADDED` for padded pixels and
        :data:`EMPTY` for pixels left black (only when nothing can be padded).
        Padding: pixels outside every source's image are warped from the
        nearest source with clamped coordinates ("warping with padding");
        occluded pixels and pixels without depth take the colour of the
        nearest filled pixel.
    """
    H, W = target.height, target.width
    depth = np.asarray(depth, dtype=np.float64)
    has_d = np.isfinite(depth) & (depth > 0)
    img = np.zeros((H * W, 3), np.float32)
    valid = np.zeros(H * W, bool)
    filled_by = np.full(H * W, EMPTY, np.int32)
    if not sources or not has_d.any():
        return img.reshape(H, W, 3), valid.reshape(H, W), filled_by.reshape(H, W)
    hd = has_d.ravel()
    X = target.backproject(np.where(has_d, depth, 1.0))
    order = np.argsort([np.linalg.norm(s[0].center - target.center) for s in sources], kind="stable")
    seen_inside = np.zeros(H * W, bool)  # inside some source image (maybe occluded there)
    pad_src = np.full(H * W, -1, np.int64)  # nearest source with the pixel in front of it
    for k in order:
        cam_s, im_s = sources[k][0], np.asarray(sources[k][1], dtype=np.float32)
        d_s = sources[k][2] if len(sources[k]) > 2 and sources[k][2] is not None else None
        if d_s is None:
            sp = float(np.median(depth[has_d])) / max(target.fx, 1e-12)
            d_s = zbuffer_depth(X[hd], cam_s, spacing=sp)
        d_s = np.asarray(d_s, dtype=np.float64)
        hs, ws = im_s.shape[:2]
        uv, z = cam_s.project(X)
        front = hd & (z > 1e-9) & np.isfinite(uv).all(1)
        pad_src[(pad_src < 0) & front] = k
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < ws) & (uv[:, 1] >= 0) & (uv[:, 1] < hs)
        seen_inside |= inside
        idx = np.flatnonzero(inside & ~valid)
        if len(idx) == 0:
            continue
        xs = np.minimum(uv[idx, 0].astype(np.int64), ws - 1)
        ys = np.minimum(uv[idx, 1].astype(np.int64), hs - 1)
        ds = d_s[ys, xs]
        vis = (ds > 0) & (z[idx] <= ds * (1.0 + rtol))
        idx = idx[vis]
        img[idx] = _bilinear(im_s, uv[idx, 0], uv[idx, 1])
        valid[idx] = True
        filled_by[idx] = k
    # Padding 1: outside every source image -> clamped warping from the nearest source.
    out = ~valid & ~seen_inside & (pad_src >= 0)
    for k in np.unique(pad_src[out]):
        idx = np.flatnonzero(out & (pad_src == k))
        uv, _ = sources[k][0].project(X[idx])
        img[idx] = _bilinear(np.asarray(sources[k][1], dtype=np.float32), uv[:, 0], uv[:, 1])
        filled_by[idx] = PADDED
    # Padding 2: the rest (occluded everywhere, no depth) -> nearest filled pixel.
    done = filled_by != EMPTY
    if done.any() and not done.all():
        ii = ndimage.distance_transform_edt(~done.reshape(H, W), return_distances=False, return_indices=True)
        near = (ii[0] * W + ii[1]).ravel()
        rest = ~done
        img[rest] = img[near[rest]]
        filled_by[rest] = PADDED
    return img.reshape(H, W, 3), valid.reshape(H, W), filled_by.reshape(H, W)


def source_disagreement(target: Camera, depth: np.ndarray, sources: Sequence[tuple]
                        ) -> tuple[np.ndarray, np.ndarray]:
    """How far apart the sources' colours for each target pixel are.

    Every source is warped into ``target`` on its own (same visibility test
    as :func:`warp_progressive`). Returns ``(count (H,W) int, spread (H,W)
    float32)``: how many sources see the pixel, and the largest mean absolute
    RGB difference between two of them (0 where fewer than two see it). With
    the right depth, sources agree up to shading; a wrong depth samples
    different surfaces in different views.
    """
    H, W = target.height, target.width
    count = np.zeros((H, W), np.int32)
    spread = np.zeros((H, W), np.float32)
    warps = [warp_progressive(target, depth, [s])[:2] for s in sources]
    for a in range(len(warps)):
        count += warps[a][1]
        for b in range(a + 1, len(warps)):
            both = warps[a][1] & warps[b][1]
            diff = np.abs(warps[a][0] - warps[b][0]).mean(-1)
            spread = np.where(both, np.maximum(spread, diff), spread)
    return count, spread


# ---------------------------------------------------------------------------
# Building and caching
# ---------------------------------------------------------------------------
def _hash_inputs(train_views: Sequence, points: np.ndarray, n: int, seed: int,
                 path: Sequence[Camera] | None, max_gap_px: float, surface: bool,
                 consistency_tol: float) -> str:
    h = hashlib.sha256(_CACHE_VERSION.encode())
    h.update(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    h.update(f"surface={surface};tol={consistency_tol!r}".encode())

    def cam(c: Camera) -> None:
        h.update(np.ascontiguousarray(c.K).tobytes() + np.ascontiguousarray(c.w2c).tobytes())
        h.update(f"{c.width}x{c.height}:{c.name}".encode())

    for v in train_views:
        cam(v.camera)
        h.update(np.ascontiguousarray(v.image, dtype=np.float32).tobytes())
    h.update(f"n={n};seed={seed};path={path is not None};gap={max_gap_px}".encode())
    for c in path or []:
        cam(c)
    return h.hexdigest()


def _save_view(p: Path, pv: PseudoView) -> None:
    c = pv.camera
    with atomic_path(p) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, K=c.K, w2c=c.w2c, size=np.array([c.width, c.height]), name=np.array(c.name),
                                image=pv.image.astype(np.float32), valid=pv.valid, padded=pv.padded,
                                depth=np.zeros((0,), np.float32) if pv.depth is None else pv.depth,
                                rejected=np.zeros((0,), bool) if pv.rejected is None else pv.rejected)


def _load_view(p: Path) -> PseudoView:
    with np.load(p, allow_pickle=False) as z:
        W, H = (int(v) for v in z["size"])
        cam = Camera(K=z["K"], w2c=z["w2c"], width=W, height=H, name=str(z["name"]))
        depth, rejected = z["depth"], z["rejected"]
        return PseudoView(cam, z["image"], z["valid"].astype(bool), z["padded"].astype(bool),
                          depth if depth.size else None, rejected.astype(bool) if rejected.size else None)


def _load_cache(cache_dir: Path, key: str) -> list[PseudoView] | None:
    man = cache_dir / "manifest.json"
    if not man.is_file():
        return None
    try:
        m = json.loads(man.read_text())
        if m.get("hash") != key:
            return None
        return [_load_view(cache_dir / f) for f in m["files"]]
    except (OSError, ValueError, KeyError, TypeError) as e:
        log.warning("pseudo-view cache in %s unreadable (%s); rebuilding", cache_dir, e)
        return None


def build_pseudo_views(train_views: Sequence, points: np.ndarray, n: int, seed: int, cache_dir: str | Path,
                       path: Sequence[Camera] | None = None, max_gap_px: float = 4.0,
                       surface: bool = False, consistency_tol: float = 0.0) -> list[PseudoView]:
    """Build (or load from ``cache_dir``) the progressive-DIBR pseudo views.

    Args:
        train_views: :class:`io_levir.View` objects (camera + image) used as sources.
        points: (N,3) dense point cloud in world units.
        n: number of orbit poses (ignored when ``path`` is given).
        seed: seed of the orbit angles.
        cache_dir: folder for ``view_NNN.npz`` files and ``manifest.json``;
            the manifest stores a hash of every input, so changed inputs
            rebuild and identical ones load (resume). Files are written
            atomically and the manifest last.
        path: optional cameras to use instead of orbit samples.
        max_gap_px: warped pixels farther than this (pixels) from any pixel
            the cloud projects to have completed, not measured, depth; they
            are returned as ``padded`` rather than ``valid``.
        surface: complete large depth holes (target and source views) by ray
            casting a :class:`surface.HeightField` of ``points`` instead of
            the nearest valid pixel; for near-nadir scenes
            (:func:`surface.applies`).
        consistency_tol: warped pixels that at least two sources see with a
            mean absolute RGB difference above this (image units in [0,1])
            are ``rejected``; 0 keeps them all. With ``surface`` too, a pixel
            whose completed-cloud depth and height-field depth are both seen by
            two sources takes the one they agree on better (floating MVS points
            over a street hidden from one view otherwise win the z-buffer).
    """
    from tqdm import tqdm

    cache_dir = Path(cache_dir)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    key = _hash_inputs(train_views, pts, n, seed, path, max_gap_px, surface, consistency_tol)
    cached = _load_cache(cache_dir, key)
    if cached is not None:
        log.info("loaded %d pseudo views from %s", len(cached), cache_dir)
        return cached
    cams = sample_orbit_poses([v.camera for v in train_views], n, seed, path)
    spacing = point_spacing(pts)
    field = None
    if surface and len(pts):
        from ..geometry.surface import HeightField

        field = HeightField.build(pts, [v.camera for v in train_views])

    sources = []
    for v in train_views:
        fill = None if field is None else field.depth(v.camera)
        sources.append((v.camera, v.image, complete_depth(zbuffer_depth(pts, v.camera, spacing), fill=fill)))
    check = consistency_tol > 0 and len(sources) > 1
    (cache_dir / "manifest.json").unlink(missing_ok=True)  # a crash mid-rebuild must not look complete
    out, files = [], []
    for i, cam in enumerate(tqdm(cams, desc="pseudo views", unit="view", leave=False)):
        raw = zbuffer_depth(pts, cam, spacing)
        surf = None if field is None else field.depth(cam)
        depth = complete_depth(raw, fill=surf)
        if check:
            count, spread = source_disagreement(cam, depth, sources)
            if surf is not None:
                # Two depth hypotheses, the completed cloud and the height field: where
                # both are seen by two sources, keep the one whose colours agree more.
                # Floating MVS points in front of occluded streets lose to the ground.
                c2, s2 = source_disagreement(cam, surf, sources)
                take = (count >= 2) & (c2 >= 2) & (s2 < spread) & (surf > 0)
                depth = np.where(take, surf, depth).astype(np.float32)
                count, spread = np.where(take, c2, count), np.where(take, s2, spread)
        image, valid, filled_by = warp_progressive(cam, depth, sources)
        padded = filled_by == PADDED
        # Depth invented far from any projected point (outside the cloud) is a
        # guess, so its warped colour is demoted to padding.
        if (raw > 0).any():
            guessed = ndimage.distance_transform_edt(raw <= 0) > max_gap_px
        else:
            guessed = np.ones_like(valid)
        padded |= valid & guessed
        valid &= ~guessed
        rejected = None
        if check:
            rejected = (valid | padded) & (count >= 2) & (spread > consistency_tol)
            valid &= ~rejected
            padded &= ~rejected
        pv = PseudoView(cam, image, valid, padded, depth, rejected)
        fname = f"view_{i:03d}.npz"
        _save_view(cache_dir / fname, pv)
        files.append(fname)
        out.append(pv)
        log.info("pseudo view %s: %.1f%% warped, %.1f%% padded, %.1f%% rejected", cam.name,
                 100 * valid.mean(), 100 * pv.padded.mean(), 0.0 if rejected is None else 100 * rejected.mean())
    write_json(cache_dir / "manifest.json", {"hash": key, "files": files, "count": len(files)})
    return out


__all__ = ["PseudoView", "EMPTY", "PADDED", "sample_orbit_poses", "zbuffer_depth",
           "remove_see_through", "complete_depth", "warp_progressive", "source_disagreement",
           "build_pseudo_views"]
