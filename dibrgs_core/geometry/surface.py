"""A 2.5D surface (height field, a DSM) of the dense cloud, for completing pseudo-view depth.

Near-nadir aerial scenes are, to first order, a height field: one surface
height per horizontal position, with vertical walls where it jumps. Depth
completion in the image (nearest valid pixel) fills a street hidden between
two towers with a roof's depth; the same hole filled in the height field
takes the height of the ground around it, and ray casting the field gives
walls and ground where the cloud has no points.

Conventions: heights are measured along the scene's up axis in the local
frame ``F @ (X - origin)`` (``F = cameras.up_frame(up)``, rows e1, e2, up;
``up`` from :func:`cameras.estimate_up`); world units throughout; depth is
z-depth along the camera's optical axis (OpenCV cameras, 0 = no surface).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import ndimage

from ..camera.frame import estimate_up, near_nadir, up_frame
from ..camera.pinhole import Camera
from .pointcloud import point_spacing


def applies(cams: Sequence[Camera]) -> tuple[bool, str]:
    """Whether a height field describes the scene these cameras see, and why: the geometry
    stage's near-nadir test (:func:`~dibrgs_core.camera.frame.near_nadir` with its default thresholds)."""
    return near_nadir(cams)


def decide(mode: str, cams: Sequence[Camera]) -> tuple[bool, str]:
    """Use a height field for pseudo-view depth? ``mode`` auto (:func:`applies`), on or off."""
    if mode == "auto":
        return applies(cams)
    if mode not in ("on", "off"):
        raise ValueError(f"height-field mode must be auto, on or off, got {mode!r}")
    return mode == "on", f"switched {mode}"


@dataclass
class HeightField:
    """Surface height per square cell of the horizontal plane.

    Attributes:
        frame: 3x3 world -> (e1, e2, up) rotation.
        origin: (3,) world point at local coordinate 0.
        lo: (2,) local (e1, e2) coordinate of the grid's lower corner.
        cell: cell side in world units.
        heights: (n1, n2) float64 local height of each cell (every cell filled).
        measured: (n1, n2) bool, cells that held cloud points (the rest were filled).
    """

    frame: np.ndarray
    origin: np.ndarray
    lo: np.ndarray
    cell: float
    heights: np.ndarray
    measured: np.ndarray

    @classmethod
    def build(cls, points: np.ndarray, cams: Sequence[Camera], cell: float | None = None,
              hole_percentile: float = 10.0, margin: float = 0.25, smooth: int = 3) -> "HeightField":
        """Height field of ``points`` (N,3 world, N >= 1) seen by ``cams``.

        Each cell holds the highest point in it (the visible surface from
        above). A hole - a connected region of empty cells - takes the
        ``hole_percentile``-th height of the filled cells around it: holes in
        aerial clouds are mostly ground hidden by or between buildings, so the
        low end of the rim is the better guess; a hole inside a roof is
        ringed by roof and keeps the roof's height. ``cell`` defaults to the
        larger of the ground sampling distance (distance from the first
        camera to the cloud's centre over its focal length) and the cloud's
        median point spacing. The grid reaches ``margin`` times the cloud's
        extent past it on each side (ground the cameras see beyond the cloud).
        Points far outside the cloud's 1st-99th percentile box (by more than
        half its size) are ignored. Last, a ``smooth`` x ``smooth`` median
        filter (1 = none) removes single-cell spikes: a cell keeps its
        highest point, so one floating MVS outlier would raise it.
        """

        pts = np.asarray(points, np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(1)]
        if len(pts) == 0:
            raise ValueError("a height field needs at least one finite point")
        up, _ = estimate_up(cams)
        F = up_frame(up)
        loc = pts @ F.T
        # Stray points (a few MVS outliers kilometres off) would stretch the grid and the
        # ray march; the field covers the bulk of the cloud: 1st-99th percentile, widened.
        if len(loc) >= 20:
            q1, q99 = np.percentile(loc, [1.0, 99.0], axis=0)
            wide = 0.5 * (q99 - q1) + 1e-9 * (1.0 + np.abs(q1))
            keep = ((loc >= q1 - wide) & (loc <= q99 + wide)).all(1)
            pts, loc = pts[keep], loc[keep]
        o = pts.mean(0)
        loc = loc - o @ F.T
        if cell is None:
            c0 = cams[0]
            gsd = float(np.linalg.norm(c0.center - o)) / max(c0.fx, 1e-12)
            cell = max(gsd, point_spacing(pts))
        cell = float(cell) if cell and np.isfinite(cell) and cell > 0 else 1.0
        lo, hi = loc[:, :2].min(0), loc[:, :2].max(0)
        pad = margin * float((hi - lo).max()) + cell
        lo, hi = lo - pad, hi + pad
        n = (np.ceil((hi - lo) / cell).astype(np.int64) + 1).clip(1, 4096)
        ij = np.clip(np.floor((loc[:, :2] - lo) / cell).astype(np.int64), 0, n - 1)
        heights = np.full((int(n[0]), int(n[1])), -np.inf)
        np.maximum.at(heights, (ij[:, 0], ij[:, 1]), loc[:, 2])
        measured = np.isfinite(heights)
        hole = ~measured
        if hole.any():
            lab, nl = ndimage.label(hole)
            rim = ndimage.binary_dilation(hole) & measured
            # A rim cell's hole: the largest label among its 3x3 neighbours.
            rim_lab = ndimage.grey_dilation(lab, size=(3, 3))[rim]
            rim_h = heights[rim]
            fill = np.full(nl + 1, np.percentile(loc[:, 2], 2.0))
            order = np.argsort(rim_lab, kind="stable")
            rl, rh = rim_lab[order], rim_h[order]
            bounds = np.searchsorted(rl, np.arange(nl + 2))
            for k in range(1, nl + 1):
                a, b = bounds[k], bounds[k + 1]
                if b > a:
                    fill[k] = np.percentile(rh[a:b], hole_percentile)
            heights[hole] = fill[lab[hole]]
        if smooth > 1:
            heights = ndimage.median_filter(heights, size=int(smooth), mode="nearest")
        return cls(F, o, lo, cell, heights, measured)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Height of the cell under local horizontal coordinates ``xy`` (...,2); edge cells outside."""
        n = np.array(self.heights.shape)
        ij = np.floor((np.asarray(xy) - self.lo) / self.cell)
        i = np.clip(np.nan_to_num(ij[..., 0], nan=0.0), 0, n[0] - 1).astype(np.int64)
        j = np.clip(np.nan_to_num(ij[..., 1], nan=0.0), 0, n[1] - 1).astype(np.int64)
        return self.heights[i, j]

    def depth(self, cam: Camera, chunk: int = 4096, refine: int = 8) -> np.ndarray:
        """Z-depth (H,W) float32 of the first surface each pixel's ray meets; 0 where none.

        Rays are marched from the field's top to its bottom in steps of at most
        half a cell horizontally, then the crossing is refined by bisection.
        Rays that do not descend (horizon and above) get 0.
        """
        H, W = cam.height, cam.width
        _, rays = cam.pixel_rays()  # camera-z 1: the ray parameter is the z-depth
        dl = rays @ self.frame.T
        cl = (cam.center - self.origin) @ self.frame.T
        out = np.zeros(H * W)
        top, bottom = float(self.heights.max()), float(self.heights.min())
        down = dl[:, 2] < -1e-9
        if not down.any():
            return out.reshape(H, W).astype(np.float32)
        dz = np.where(down, dl[:, 2], -1.0)
        z0 = np.maximum((top + 1e-6 - cl[2]) / dz, 0.0)
        z1 = np.maximum((bottom - 1e-6 - cl[2]) / dz, z0)
        hor = np.linalg.norm(dl[:, :2], axis=1)
        span = ((z1 - z0) * hor)[down]
        # Half a cell per step; the cap bounds the cost of a field far taller than wide.
        steps = int(min(np.ceil(span.max() / (0.5 * self.cell)), 1024)) + 2
        ts = np.linspace(0.0, 1.0, steps)
        for s in range(0, H * W, chunk):
            idx = np.arange(s, min(s + chunk, H * W))
            idx = idx[down[idx]]
            if len(idx) == 0:
                continue
            z = z0[idx, None] + (z1[idx] - z0[idx])[:, None] * ts[None, :]
            P = cl + z[..., None] * dl[idx, None, :]
            below = P[..., 2] <= self.height(P[..., :2])
            first = np.argmax(below, axis=1)
            r = np.arange(len(idx))
            hit = below[r, first]
            lo_z = np.where(first > 0, z[r, np.maximum(first - 1, 0)], z0[idx])
            hi_z = z[r, first]
            for _ in range(refine):
                mid = 0.5 * (lo_z + hi_z)
                Pm = cl + mid[:, None] * dl[idx]
                b = Pm[:, 2] <= self.height(Pm[:, :2])
                hi_z = np.where(b, mid, hi_z)
                lo_z = np.where(b, lo_z, mid)
            out[idx] = np.where(hit, hi_z, 0.0)
        return out.reshape(H, W).astype(np.float32)


__all__ = ["HeightField", "applies", "decide"]
