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
