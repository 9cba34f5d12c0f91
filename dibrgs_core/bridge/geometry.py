"""Height map as a mesh for display in Blender (numpy only)."""
from __future__ import annotations

import numpy as np

from ..geometry.height_map import HeightMap


def height_map_mesh(hm: HeightMap) -> tuple[np.ndarray, np.ndarray]:
    """A grid mesh of a height map: one vertex per cell centre at the cell's bound.

    Returns (vertices (nx*ny, 3) world coordinates, quads (M, 4) vertex
    indices between neighbouring cells). A local point ``(a, b, h)`` in the
    map's up frame (rows e1, e2, up) is ``origin + a*e1 + b*e2 + h*up``.
    Cells with a non-finite bound are left out with their quads.
    """
    nx, ny = hm.bounds.shape
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    ok = np.isfinite(hm.bounds)
    index = np.full((nx, ny), -1, dtype=np.int64)
    index[ok] = np.arange(int(ok.sum()))
    local = np.stack([hm.x0 + (ii[ok] + 0.5) * hm.cell, hm.y0 + (jj[ok] + 0.5) * hm.cell, hm.bounds[ok]], axis=1)
    verts = hm.origin + local @ np.asarray(hm.up_frame, np.float64)
    quads = np.stack([index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]], axis=-1).reshape(-1, 4)
    return verts, quads[(quads >= 0).all(axis=1)]
