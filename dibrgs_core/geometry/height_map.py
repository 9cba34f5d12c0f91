"""The coarse height map that limits anchor growth (paper section "Height-constrained Anchor Growth").

Heights are measured along the scene's up axis in the local up frame
``F @ (X - origin)`` (``F = cameras.up_frame(up)``, rows e1, e2, up). The
horizontal plane is cut into square cells of side ``cell``; each cell's bound
is the ``percentile``-th height of the dense cloud's points in it, relaxed::

    bound = ground + relax * (p_cell - ground) + margin

``ground`` is a low percentile (2nd) of all heights, so "multiplied by a
factor" scales the height *above the ground* and is well defined whatever
the sign of the raw heights (a raw-height factor would tighten the bound
where heights are negative). ``margin`` keeps a flat cell (all heights
equal) from rejecting points a hair above it. Empty cells take the bound of
the nearest filled cell; points outside the grid use the nearest edge cell.
``allows(points)`` is True where ``height <= bound`` (growth allowed).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class HeightMap:
    """A per-cell upper height bound.

    Attributes:
        up_frame: 3x3 world -> (e1, e2, up) rotation.
        origin: (3,) world point at local coordinate 0.
        cell: cell side in world units.
        x0, y0: local (e1, e2) coordinate of the grid's lower corner.
        bounds: (nx, ny) float64 height bound per cell (local heights).
        ground, relax, margin, percentile: how the bounds were made.
    """

    up_frame: np.ndarray
    origin: np.ndarray
    cell: float
    x0: float
    y0: float
    bounds: np.ndarray
    ground: float = 0.0
    relax: float = 1.1
    margin: float = 0.0
    percentile: float = 95.0

    @classmethod
    def build(cls, points: np.ndarray, up_frame: np.ndarray, origin: np.ndarray, cell: float,
              percentile: float = 95.0, relax: float = 1.1, margin: float = 0.0,
              ground_percentile: float = 2.0) -> "HeightMap":
        """Height map of ``points`` (N,3 world). Needs at least one finite point."""
        from scipy.ndimage import distance_transform_edt

        F = np.asarray(up_frame, np.float64)
        o = np.asarray(origin, np.float64)
        loc = (np.asarray(points, np.float64) - o) @ F.T
        loc = loc[np.isfinite(loc).all(1)]
        if len(loc) == 0:
            raise ValueError("HeightMap.build: no finite points")
        if not cell > 0:
            raise ValueError(f"HeightMap.build: cell must be positive, got {cell}")
        x0, y0 = loc[:, 0].min(), loc[:, 1].min()
        ij = np.floor((loc[:, :2] - [x0, y0]) / cell).astype(np.int64)
        nx, ny = int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1
        flat = ij[:, 0] * ny + ij[:, 1]
        order = np.lexsort((loc[:, 2], flat))
        fs, hs = flat[order], loc[order, 2]
        starts = np.flatnonzero(np.r_[True, fs[1:] != fs[:-1]])
        ends = np.r_[starts[1:], len(fs)]
        # Percentile per cell from the sorted heights (linear interpolation).
        q = percentile / 100.0
        pos = starts + q * (ends - starts - 1)
        lo = np.floor(pos).astype(np.int64)
        hi = np.minimum(lo + 1, ends - 1)
        pval = hs[lo] + (hs[hi] - hs[lo]) * (pos - lo)
        ground = float(np.percentile(loc[:, 2], ground_percentile))
        grid = np.full(nx * ny, np.nan)
        grid[fs[starts]] = ground + relax * (pval - ground) + margin
        grid = grid.reshape(nx, ny)
        empty = np.isnan(grid)
        if empty.any():
            _, (ii, jj) = distance_transform_edt(empty, return_indices=True)
            grid = grid[ii, jj]
        return cls(F, o, float(cell), float(x0), float(y0), grid, ground, float(relax), float(margin), float(percentile))

    # -- queries -------------------------------------------------------------
    def bound_at(self, points: np.ndarray) -> np.ndarray:
        """Height bound (local heights) at the horizontal position of each world point (numpy)."""
        loc = (np.asarray(points, np.float64) - self.origin) @ self.up_frame.T
        nx, ny = self.bounds.shape
        i = np.clip(np.floor((np.nan_to_num(loc[:, 0]) - self.x0) / self.cell), 0, nx - 1).astype(np.int64)
        j = np.clip(np.floor((np.nan_to_num(loc[:, 1]) - self.y0) / self.cell), 0, ny - 1).astype(np.int64)
        return self.bounds[i, j]

    def allows(self, points: Any):
        """Growth mask: True where a point's height is at most its cell's bound.

        Accepts (N,3) numpy arrays (returns a numpy bool array) or torch
        tensors (returns a torch bool tensor on the same device; computed in
        float64 so georeferenced coordinates keep their precision). Non-finite
        points are never allowed.
        """
        if isinstance(points, np.ndarray) or not hasattr(points, "device"):
            P = np.asarray(points, np.float64).reshape(-1, 3)
            loc = (P - self.origin) @ self.up_frame.T
            ok = np.isfinite(loc).all(1)
            return ok & (np.nan_to_num(loc[:, 2], nan=np.inf) <= self.bound_at(P))
        import torch

        P = points.detach().reshape(-1, 3).to(torch.float64)
        dev = P.device
        F = torch.as_tensor(self.up_frame, dtype=torch.float64, device=dev)
        o = torch.as_tensor(self.origin, dtype=torch.float64, device=dev)
        B = torch.as_tensor(self.bounds, dtype=torch.float64, device=dev)
        loc = (P - o) @ F.T
        ok = torch.isfinite(loc).all(1)
        loc = torch.nan_to_num(loc, nan=0.0, posinf=0.0, neginf=0.0)
        nx, ny = B.shape
        i = torch.floor((loc[:, 0] - self.x0) / self.cell).clamp(0, nx - 1).long()
        j = torch.floor((loc[:, 1] - self.y0) / self.cell).clamp(0, ny - 1).long()
        return ok & (loc[:, 2] <= B[i, j])

    # -- persistence ---------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write an .npz atomically."""
        from ..common.fileio import atomic_path

        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, up_frame=self.up_frame, origin=self.origin, cell=self.cell, x0=self.x0, y0=self.y0,
                         bounds=self.bounds, ground=self.ground, relax=self.relax, margin=self.margin,
                         percentile=self.percentile)

    @classmethod
    def load(cls, path: str | Path) -> "HeightMap":
        """Read a height map written by :meth:`save`; InputError when the file is not one."""
        from ..common.errors import InputError

        try:
            with np.load(path) as z:
                return cls(np.array(z["up_frame"], np.float64), np.array(z["origin"], np.float64), float(z["cell"]),
                           float(z["x0"]), float(z["y0"]), np.array(z["bounds"], np.float64), float(z["ground"]),
                           float(z["relax"]), float(z["margin"]), float(z["percentile"]))
        except (OSError, KeyError, ValueError) as e:
            raise InputError(path, f"not a DIBR-GS height map ({e})") from None


def completion_field(points: np.ndarray, frame: np.ndarray, origin: np.ndarray, cell: float,
                     cover: np.ndarray | None = None, ground_cells: int = 8, ground_percentile: float = 25.0,
                     smooth: int = 3):
    """A 2.5D surface (:class:`surface.HeightField`) of measured ``points`` for completing depth maps.

    Heights are along the up axis of ``frame`` (rows e1, e2, up) relative to
    ``origin``; ``cell`` is the cell side (world units). A cell holding points
    takes their median height (robust to the stray matches a cell collects). An
    empty cell takes the *ground* there: the ``ground_percentile``-th height
    per block of ``ground_cells`` x ``ground_cells`` cells, as a least-squares
    plane (the terrain's slope) plus its residuals spread smoothly into the
    blocks without points (normalised Gaussian convolution, widening until every
    block has a value). Unmatched regions of aerial photos are mostly ground
    (lawn, road, water, streets hidden between buildings) or objects on it; the
    low percentile puts them on the ground, and the plane carries a sloping
    terrain past the cloud's edge. ``cover`` (M,2) local horizontal points the
    grid must reach (the training views' footprints), besides the cloud. Last,
    a ``smooth`` x ``smooth`` median filter (1 = none) removes single-cell spikes.
    """
    from scipy import ndimage

    from .surface import HeightField

    F = np.asarray(frame, np.float64)
    o = np.asarray(origin, np.float64)
    loc = (np.asarray(points, np.float64).reshape(-1, 3) - o) @ F.T
    loc = loc[np.isfinite(loc).all(1)]
    if len(loc) < 3:
        raise ValueError("completion_field: fewer than 3 finite points")
    if not cell > 0:
        raise ValueError(f"completion_field: cell must be positive, got {cell}")
    if len(loc) >= 20:  # stray points far off would stretch the grid
        q1, q99 = np.percentile(loc, [1.0, 99.0], axis=0)
        wide = 0.5 * (q99 - q1) + 1e-9 * (1.0 + np.abs(q1))
        loc = loc[((loc >= q1 - wide) & (loc <= q99 + wide)).all(1)]
    xy = loc[:, :2]
    lo, hi = xy.min(0), xy.max(0)
    if cover is not None and len(cover):
        c = np.asarray(cover, np.float64).reshape(-1, 2)
        c = c[np.isfinite(c).all(1)]
        if len(c):
            lo, hi = np.minimum(lo, c.min(0)), np.maximum(hi, c.max(0))
    block = max(int(ground_cells), 1)
    lo = lo - 2 * cell
    n = (np.ceil((hi + 2 * cell - lo) / cell).astype(np.int64) + 1)
    n = ((n + block - 1) // block * block).clip(block, 4096)
    cell = max(cell, float(((hi - lo) / (n - 1)).max()))  # a grid capped at 4096 cells gets coarser
    ij = np.clip(np.floor((xy - lo) / cell).astype(np.int64), 0, n - 1)
    h = loc[:, 2]
    surf = _cell_quantile(ij, h, n, 50.0)
    # Ground per block: a low percentile, then plane + smoothly spread residuals.
    # Per block, a low percentile of its cells' heights (each cell one vote, so a dense patch of
    # stray matches weighs no more than its area); a block counts when a quarter of its cells hold
    # points (a few stray matches do not make a surface).
    mi, mj = np.nonzero(np.isfinite(surf))
    ground = _cell_quantile(np.stack([mi, mj], 1) // block, surf[mi, mj], n // block, ground_percentile)
    filled_cells = np.isfinite(surf).reshape(n[0] // block, block, n[1] // block, block).sum(axis=(1, 3))
    gm = np.isfinite(ground) & (filled_cells >= block * block / 4)
    # The terrain's trend: a plane through the blocks, blocks off it by > 3 robust sigmas (tree
    # stands, buildings) left out of the fit but not of the surface.
    fit = gm.copy()
    coef = np.array([0.0, 0.0, float(np.median(h))])
    for _ in range(5):
        gi, gj = np.nonzero(fit)
        if len(gi) < 3:
            break
        A = np.stack([gi, gj, np.ones_like(gi)], 1).astype(np.float64)
        coef = np.linalg.lstsq(A, ground[fit], rcond=None)[0]
        r = ground[fit] - A @ coef
        s = 1.4826 * np.median(np.abs(r - np.median(r)))
        off = np.abs(r) > 3 * s + 1e-12 * (1.0 + np.abs(coef[2]))
        if not off.any() or off.all():
            break
        fit[gi[off], gj[off]] = False
    bi, bj = np.meshgrid(np.arange(ground.shape[0]), np.arange(ground.shape[1]), indexing="ij")
    plane = coef[0] * bi + coef[1] * bj + coef[2]
    res = np.where(gm, ground - plane, 0.0)
    filled = np.where(gm, res, np.nan)
    sigma = 1.0
    while np.isnan(filled).any() and sigma < 4 * max(ground.shape):
        num = ndimage.gaussian_filter(res, sigma, mode="nearest")
        den = ndimage.gaussian_filter(gm.astype(np.float64), sigma, mode="nearest")
        fill = np.isnan(filled) & (den > 1e-3)
        filled[fill] = num[fill] / den[fill]
        sigma *= 2
    # Away from the blocks with points the residual fades into the plane (e-folding: one block), so
    # the terrain's trend, not the nearest block, carries the surface past the cloud's edge.
    dist = ndimage.distance_transform_edt(~gm) if gm.any() else np.full(gm.shape, np.inf)
    filled = np.nan_to_num(filled, nan=0.0) * np.exp(-dist) + plane
    # Blocks -> cells (bilinear between block centres).
    ci = (np.arange(n[0]) + 0.5) / block - 0.5
    cj = (np.arange(n[1]) + 0.5) / block - 0.5
    CI, CJ = np.meshgrid(ci, cj, indexing="ij")
    ground_fine = ndimage.map_coordinates(filled, [CI, CJ], order=1, mode="nearest")
    measured = np.isfinite(surf)
    heights = np.where(measured, surf, ground_fine)
    if smooth > 1:
        heights = ndimage.median_filter(heights, size=int(smooth), mode="nearest")
    return HeightField(F, o, lo, float(cell), heights, measured)


def _cell_quantile(ij: np.ndarray, values: np.ndarray, shape, q: float) -> np.ndarray:
    """Per grid cell (``ij`` (N,2) indices into ``shape``) the ``q``-th percentile of ``values``; NaN where empty."""
    ny = int(shape[1])
    flat = ij[:, 0] * ny + ij[:, 1]
    order = np.lexsort((values, flat))
    fs, vs = flat[order], values[order]
    starts = np.flatnonzero(np.r_[True, fs[1:] != fs[:-1]])
    ends = np.r_[starts[1:], len(fs)]
    pos = starts + q / 100.0 * (ends - starts - 1)
    a = np.floor(pos).astype(np.int64)
    b = np.minimum(a + 1, ends - 1)
    out = np.full(int(shape[0]) * ny, np.nan)
    out[fs[starts]] = vs[a] + (vs[b] - vs[a]) * (pos - a)
    return out.reshape(int(shape[0]), ny)
