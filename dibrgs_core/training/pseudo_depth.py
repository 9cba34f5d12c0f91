"""Depth of a pseudo view: the dense cloud z-buffered into it, see-through points removed, and the
gaps completed (small ones from their neighbours, large ones from the scene's height field in
near-nadir scenes, else from the nearest valid pixel).

OpenCV cameras, pixel centres at +0.5, z-depth in world units along the camera axis, 0 = no depth.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..camera.pinhole import Camera
from ..geometry.pointcloud import point_spacing, zbuffer


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
    wp = a.shape[1] + 2 * radius
    offs = [dy * wp + dx for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1) if dy or dx] + [0]
    # One gather at flat indices (3-4x faster than a 2D index per offset).
    return p.ravel()[((ys + radius) * wp + xs + radius)[None, :] + np.array(offs)[:, None]]


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
