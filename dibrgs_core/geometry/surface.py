"""A 2.5D surface (height field, a DSM) of the dense cloud, for completing pseudo-view depth.

Near-nadir aerial scenes are, to first order, a height field: one surface
height per horizontal position, with vertical walls where it jumps. Depth
completion in the image (nearest valid pixel) fills a street hidden between
two towers with a roof's depth; the same hole filled in the height field
takes the height of the ground around it, and rasterising the field (a flat
top per cell, vertical walls between cells; :meth:`HeightField.depth`) gives
walls and ground where the cloud has no points.

Conventions: heights are measured along the scene's up axis in the local
frame ``F @ (X - origin)`` (``F = cameras.up_frame(up)``, rows e1, e2, up;
``up`` from :func:`cameras.estimate_up`); world units throughout; depth is
z-depth along the camera's optical axis (OpenCV cameras, 0 = no surface).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np
from scipy import ndimage

from ..camera.frame import estimate_up, near_nadir, up_frame
from ..camera.pinhole import Camera
from .pointcloud import point_spacing

if TYPE_CHECKING:
    from ..render import Backend


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
        # Stray points (a few MVS outliers kilometres off) would stretch the grid and its
        # rendering; the field covers the bulk of the cloud: 1st-99th percentile, widened.
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

    def depth(self, cam: Camera) -> np.ndarray:
        """Z-depth (H,W) float32 of the first surface each pixel's ray meets; 0 where none.

        The field is drawn as a mesh - a flat square top per cell, vertical walls where
        neighbouring cells differ - whose triangles are rasterised into a z-buffer
        (:func:`rasterise_depth`). Only the cells under the image's footprint are drawn, and
        where cells are smaller than a pixel at the field's top they are max-pooled first
        (the highest point stays the visible one). Descending rays that miss the grid meet
        the plane at its border cells' median height, so the ground goes on past the grid
        (as the edge cells would, extended outward).
        """
        H, W = cam.height, cam.width
        M = cam.R @ self.frame.T  # local (e1, e2, up) -> camera axes
        b = cam.R @ self.origin + cam.t  # camera coordinates of the local origin
        cl = (cam.center - self.origin) @ self.frame.T
        heights, lo, cell = self.heights, self.lo, self.cell
        top, bottom = float(heights.max()), float(heights.min())
        f = 0.5 * (cam.fx + cam.fy)
        above = cl[2] - top
        if above > 0:  # cells far smaller than a pixel at the nearest surface: pool them
            # No coarser than the whole field: a camera far above (a satellite, a pose off in
            # another frame) would otherwise pad the field to k x k cells (12 GiB at 4e6 units).
            k = int(min(np.floor(above / max(f, 1e-12) / cell), max(heights.shape)))
            if k >= 2:
                heights, cell = _max_pool(heights, k), cell * k
        n1, n2 = heights.shape
        i0, i1, j0, j1 = 0, n1, 0, n2
        corners = np.array([[0.0, 0.0], [W, 0.0], [0.0, H], [W, H]])
        dl_c = (np.c_[corners, np.ones(4)] @ np.linalg.inv(cam.K).T) @ M  # rays (camera z 1), local axes
        if (dl_c[:, 2] < 0).all() and above > 0:
            # Footprint of the image on the field's top and bottom planes: draw only those cells.
            xy = np.concatenate([cl[:2] + ((h - cl[2]) / dl_c[:, 2])[:, None] * dl_c[:, :2] for h in (top, bottom)])
            ij_lo = np.floor((xy.min(0) - lo) / cell).astype(np.int64) - 1
            ij_hi = np.floor((xy.max(0) - lo) / cell).astype(np.int64) + 2
            i0, j0 = (int(v) for v in np.clip(ij_lo, 0, [n1, n2]))
            i1, j1 = (int(v) for v in np.clip(ij_hi, 0, [n1, n2]))
        zbuf = np.zeros((H, W))
        if i1 > i0 and j1 > j0:
            hs = heights[i0:i1, j0:j1]
            xs = lo[0] + cell * np.arange(i0, i1 + 1)
            ys = lo[1] + cell * np.arange(j0, j1 + 1)
            zbuf = rasterise_depth(_mesh(hs, xs, ys, cl), M, b, cam.K, H, W)
        # Rays past the grid: the plane of the border's median height.
        border = np.concatenate([self.heights[0], self.heights[-1], self.heights[:, 0], self.heights[:, -1]])
        hb = float(np.median(border))
        # Vertical component of each pixel's ray (camera-z 1): linear in the pixel coordinates.
        c = self.frame[2] @ cam.R.T @ np.linalg.inv(cam.K)
        dz = (c[0] * (np.arange(W) + 0.5)[None, :] + c[1] * (np.arange(H) + 0.5)[:, None] + c[2]).ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            zp = np.where(dz < -1e-12, (hb - cl[2]) / dz, 0.0)
        zp = np.where(np.isfinite(zp) & (zp > 0), zp, 0.0).reshape(H, W)
        out = np.where(zbuf > 0, zbuf, zp)
        return out.astype(np.float32)


def _max_pool(h: np.ndarray, k: int) -> np.ndarray:
    """``k`` x ``k`` max pooling (the last block may be partial)."""
    n1, n2 = h.shape
    p1, p2 = -n1 % k, -n2 % k
    hp = np.pad(h, ((0, p1), (0, p2)), mode="edge")
    return hp.reshape((n1 + p1) // k, k, (n2 + p2) // k, k).max(axis=(1, 3))


def _mesh(hs: np.ndarray, xs: np.ndarray, ys: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """The quads of a height field that face a viewer at ``eye`` (local coordinates): (3,4,Q),
    the x, y, h of each quad's four corners in order round it.

    Cell (i, j) spans ``xs[i]..xs[i+1]`` x ``ys[j]..ys[j+1]`` at height ``hs[i, j]``: its top,
    and a vertical wall to each neighbour of another height. The field is a closed surface
    seen from one side, so quads facing away from the viewer (tops seen from below, walls
    seen from the higher cell's side) are always hidden and are left out.
    """
    X0, Y0 = np.meshgrid(xs[:-1], ys[:-1], indexing="ij")
    X1, Y1 = np.meshgrid(xs[1:], ys[1:], indexing="ij")
    parts = []

    def add(m, *corners):
        if m.any():
            parts.append(np.array([[c[m] for c in axis] for axis in zip(*corners)]))

    h = hs
    add(h < eye[2], (X0, Y0, h), (X1, Y0, h), (X1, Y1, h), (X0, Y1, h))
    # Walls between (i, j) and (i+1, j) on x = xs[i+1]: seen from the lower side.
    ha, hb = h[:-1], h[1:]
    x, y0, y1 = X1[:-1], Y0[:-1], Y1[:-1]
    add(((ha > hb) & (eye[0] > x)) | ((ha < hb) & (eye[0] < x)), (x, y0, ha), (x, y1, ha), (x, y1, hb), (x, y0, hb))
    ha, hb = h[:, :-1], h[:, 1:]
    y, x0, x1 = Y1[:, :-1], X0[:, :-1], X1[:, :-1]
    add(((ha > hb) & (eye[1] > y)) | ((ha < hb) & (eye[1] < y)), (x0, y, ha), (x1, y, ha), (x1, y, hb), (x0, y, hb))
    return np.concatenate(parts, axis=2) if parts else np.zeros((3, 4, 0))


def rasterise_depth(quads: np.ndarray, M: np.ndarray, b: np.ndarray, K: np.ndarray, H: int, W: int,
                    backend: Backend | None = None) -> np.ndarray:
    """Z-buffer (H,W) float64 of planar convex quads; 0 where none covers a pixel centre.

    ``quads`` (3,4,Q) are the coordinates of each quad's corners, in order round it, in a
    frame that ``X -> M X + b`` takes to OpenCV camera axes; ``K`` the intrinsics (pixel
    centres at +0.5). Scanline rasterisation: each quad's rows, each row's span of pixel
    centres (edges included on both sides, so neighbours sharing an edge leave no gap), the
    depth from the quad's plane (1/z is affine in the image plane); the nearest quad wins.
    Quads with a corner behind the camera, or seen edge-on, are left out.

    Two paths with the same rules: the rasterizer's C++ extension (``render/csrc/zbuffer.h``)
    when ``backend`` (None: the process default) resolves to it, else
    :func:`rasterise_depth_reference` in numpy (about 20x slower). They differ only where a
    pixel centre lies on a quad's edge to rounding (``tests/geometry/test_surface.py``).
    """
    import torch

    from ..render import uses_fast

    if quads.shape[2] and uses_fast(backend, torch.empty(0)):
        from ..render.fast import extension

        t = [torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64)) for a in (quads, M, b, K)]
        return extension().zbuffer_quads(*t, int(H), int(W)).numpy()
    return rasterise_depth_reference(quads, M, b, K, H, W)


def rasterise_depth_reference(quads: np.ndarray, M: np.ndarray, b: np.ndarray, K: np.ndarray, H: int, W: int
                              ) -> np.ndarray:
    """:func:`rasterise_depth` in numpy (and one torch scatter)."""
    import torch

    Q = quads.shape[2]
    if Q == 0:
        return np.zeros((H, W))
    cx_, cy_, cz_ = (M[k, 0] * quads[0] + M[k, 1] * quads[1] + M[k, 2] * quads[2] + b[k] for k in range(3))
    zmin = np.minimum(np.minimum(cz_[0], cz_[1]), np.minimum(cz_[2], cz_[3]))
    finite = np.isfinite(cz_)
    keep = zmin > 1e-9 * max(float(np.abs(cz_[finite]).max()) if finite.any() else 0.0, 1e-300)
    keep &= np.isfinite(cx_).all(0) & np.isfinite(cy_).all(0)  # a NaN corner drops its quad only
    iz = 1.0 / np.where(keep, cz_, 1.0)
    cx_, cy_ = np.where(keep, cx_, 0.0), np.where(keep, cy_, 0.0)
    u = (K[0, 0] * cx_ + K[0, 1] * cy_) * iz + K[0, 2]
    v = K[1, 1] * cy_ * iz + K[1, 2]
    vmin = np.minimum(np.minimum(v[0], v[1]), np.minimum(v[2], v[3]))
    vmax = np.maximum(np.maximum(v[0], v[1]), np.maximum(v[2], v[3]))
    umin = np.minimum(np.minimum(u[0], u[1]), np.minimum(u[2], u[3]))
    umax = np.maximum(np.maximum(u[0], u[1]), np.maximum(u[2], u[3]))
    y0 = np.clip(np.ceil(vmin - 0.5), 0, H).astype(np.int64)
    ny = np.clip(np.floor(vmax - 0.5), -1, H - 1).astype(np.int64) - y0 + 1
    # 1/z = A u + B v + C over each quad, from three of its corners (the fourth is coplanar).
    du1, dv1, dw1 = u[1] - u[0], v[1] - v[0], iz[1] - iz[0]
    du2, dv2, dw2 = u[2] - u[0], v[2] - v[0], iz[2] - iz[0]
    det = du1 * dv2 - du2 * dv1
    keep &= (ny > 0) & (umax >= 0) & (umin <= W)
    keep &= np.abs(det) > 1e-12 * (np.abs(du1) + np.abs(dv1) + np.abs(du2) + np.abs(dv2)) ** 2
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return np.zeros((H, W))
    u, v, det, y0, ny = u[:, idx], v[:, idx], det[idx], y0[idx], ny[idx]
    du1, dv1, dw1, du2, dv2, dw2 = du1[idx], dv1[idx], dw1[idx], du2[idx], dv2[idx], dw2[idx]
    A = (dw1 * dv2 - dw2 * dv1) / det
    B = (du1 * dw2 - du2 * dw1) / det
    C = iz[0, idx] - A * u[0] - B * v[0]
    # Per quad and edge: the lower end (v, then u) first, so two quads sharing an edge compute
    # the same crossings; horizontal edges never cross a row.
    cols = []
    for e in range(4):
        pu, pv, qu, qv = u[e], v[e], u[(e + 1) % 4], v[(e + 1) % 4]
        swap = (qv < pv) | ((qv == pv) & (qu < pu))
        lu, lv, hv = np.where(swap, qu, pu), np.where(swap, qv, pv), np.where(swap, pv, qv)
        hu = np.where(swap, pu, qu)
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = np.where(hv > lv, (hu - lu) / (hv - lv), 0.0)
        cols += [lu, lv, np.where(hv > lv, hv, -np.inf), slope]
    # Pixel-level work in float32 (coordinates of a few thousand pixels: 1e-4 px).
    per_quad = np.stack(cols, 1).astype(np.float32)  # (Q', 16)
    # One row of pixels of one quad per entry.
    q = np.repeat(np.arange(len(idx)), ny)
    yr = y0[q] + (np.arange(len(q)) - np.repeat(np.cumsum(ny) - ny, ny))
    yc = yr.astype(np.float32) + np.float32(0.5)
    g = per_quad[q]
    lo = np.full(len(q), np.inf, np.float32)
    hi = np.full(len(q), -np.inf, np.float32)
    for e in range(4):
        lu, lv, hv, slope = g[:, 4 * e], g[:, 4 * e + 1], g[:, 4 * e + 2], g[:, 4 * e + 3]
        cross = (lv <= yc) & (yc <= hv)
        x = lu + (yc - lv) * slope
        np.minimum(lo, x, out=lo, where=cross)
        np.maximum(hi, x, out=hi, where=cross)
    x0 = np.clip(np.ceil(lo - 0.5), 0, W)
    nx = np.where(np.isfinite(lo), np.clip(np.floor(hi - 0.5), -1, W - 1) - x0 + 1, 0).clip(0).astype(np.int64)
    r = np.repeat(np.arange(len(q)), nx)
    xp = x0.astype(np.int64)[r] + (np.arange(len(r)) - np.repeat(np.cumsum(nx) - nx, nx))
    qq = q[r]
    izp = A[qq] * (xp + 0.5) + B[qq] * (yr[r] + 0.5) + C[qq]
    good = izp > 0
    zbuf = torch.full((H * W,), float("inf"), dtype=torch.float64)
    zbuf.scatter_reduce_(0, torch.from_numpy(yr[r][good] * W + xp[good]), torch.from_numpy(1.0 / izp[good]),
                         reduce="amin")
    out = zbuf.numpy().reshape(H, W)
    return np.where(np.isfinite(out), out, 0.0)


__all__ = ["HeightField", "applies", "decide", "rasterise_depth", "rasterise_depth_reference"]
