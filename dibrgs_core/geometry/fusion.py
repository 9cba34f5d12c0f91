"""Fusing per-view depth maps into one point cloud, and removing stacked layers.

All geometry here is done in a *local up frame*: ``F @ (X - origin)`` with
``F = cameras.up_frame(up)`` (rows e1, e2, up), so the first two coordinates
are horizontal and the third is the height; the up axis comes from the
cameras (not assumed +Z) and the local origin keeps float precision for
georeferenced coordinates.

Refinements (the paper's "Refine" column):

* ``none``: every back-projected pixel (plain z-buffer fusion).
* ``reproject``: per view, the farthest depth any view puts on each pixel
  (multi-view maximum depth), back-projected.
* ``no-ovlp``: ours. In horizontal cells whose heights the dip test finds
  multimodal (p < alpha), pairs closer than ``eps_xy`` horizontally and
  farther than ``eps_z`` vertically are overlaps; the higher point of each
  pair is dropped ("keep lower").
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..data.images import to_uint8
from .pointcloud import zbuffer

log = logging.getLogger("dibrgs.fusion")



def to_frame(points: np.ndarray, frame: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """World (N,3) -> local up-frame coordinates (e1, e2, height)."""
    return (np.asarray(points, np.float64) - origin) @ np.asarray(frame).T


def backproject_views(cameras: Sequence[Camera], depths: Sequence[np.ndarray], images: Sequence[np.ndarray]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project every finite, positive depth pixel (paper eq. 3).

    Returns (points (N,3) float64 world, colors (N,3) uint8, view index (N,)).
    """
    P, C, V = [], [], []
    for i, (cam, d, im) in enumerate(zip(cameras, depths, images)):
        d = np.asarray(d, np.float64).reshape(-1)
        ok = np.isfinite(d) & (d > 0)
        if not ok.any():
            continue
        X = cam.backproject(np.where(ok, d, 0).reshape(cam.height, cam.width))[ok]
        col = to_uint8(np.asarray(im)[..., :3])
        P.append(X)
        C.append(col.reshape(-1, 3)[ok])
        V.append(np.full(ok.sum(), i, np.int32))
    if not P:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32)
    return np.concatenate(P), np.concatenate(C), np.concatenate(V)


def reproject_max_depth(cameras: Sequence[Camera], depths: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The "Reproject" refinement: per view and pixel, the farthest depth of all views' points."""
    pts, _, _ = backproject_views(cameras, depths, [np.zeros((c.height, c.width, 3)) for c in cameras])
    out = []
    for cam, d in zip(cameras, depths):
        far = zbuffer(cam, pts, farthest=True)
        own = np.asarray(d, np.float64)
        # Only pixels the view itself observed keep a depth (no new coverage).
        out.append(np.where(np.isfinite(own) & (own > 0), np.fmax(far, own), np.nan))
    return out


@dataclass
class DipResult:
    """Per-point flag of lying in a multimodal cell, and cell statistics."""

    in_multimodal: np.ndarray
    n_cells: int
    n_tested: int
    n_multimodal: int


def _cell_ids(xy: np.ndarray, cell: float) -> np.ndarray:
    ij = np.floor(xy / cell).astype(np.int64)
    ij -= ij.min(axis=0) if len(ij) else 0
    return ij[:, 0] * (int(ij[:, 1].max()) + 1 if len(ij) else 1) + ij[:, 1]


def dip_cells(local: np.ndarray, cell: float, alpha: float = 0.05, min_points: int = 4) -> DipResult:
    """Hartigan's dip test on the heights of every horizontal cell with >= ``min_points`` points.

    ``local`` is in up-frame coordinates. Cells with fewer points (the test is
    invalid for n <= 3) are treated as unimodal. A cell whose heights are all
    equal has dip 0 and is unimodal.
    """
    import warnings

    import diptest

    n = len(local)
    flags = np.zeros(n, bool)
    if n == 0:
        return DipResult(flags, 0, 0, 0)
    ids = _cell_ids(local[:, :2], cell)
    order = np.argsort(ids, kind="stable")
    sid = ids[order]
    starts = np.flatnonzero(np.r_[True, sid[1:] != sid[:-1]])
    ends = np.r_[starts[1:], n]
    tested = multi = 0
    h = local[order, 2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for s, e in zip(starts, ends):
            if e - s < max(min_points, 4):
                continue
            tested += 1
            z = h[s:e]
            if np.ptp(z) <= 0:
                continue
            _, p = diptest.diptest(z)
            if p < alpha:
                multi += 1
                flags[order[s:e]] = True
    return DipResult(flags, len(starts), tested, multi)


def neighbour_pairs_estimate(xy: np.ndarray, eps: float) -> float:
    """About how many pairs of the points ``xy`` (N, 2) lie closer than ``eps``: a grid of side
    ``eps`` holding n points in a square expects pi n neighbours of each, so (pi / 2) sum n^2
    (uniform density within a square; within a factor of about 2 on real clouds)."""
    if len(xy) == 0:
        return 0.0
    _, counts = np.unique(_cell_ids(xy, eps), return_counts=True)
    return float(np.pi / 2 * np.sum(counts.astype(np.float64) ** 2))


def overlap_pairs_drop(local: np.ndarray, candidates: np.ndarray, cell: float, eps_xy: float, eps_z: float) -> np.ndarray:
    """Mask of points to drop: the higher point of every overlapping pair (paper eq. 5).

    Pairs are searched with a cKDTree on the horizontal coordinates of the
    ``candidates`` (points in multimodal cells), within the same cell.
    """
    from scipy.spatial import cKDTree

    drop = np.zeros(len(local), bool)
    idx = np.flatnonzero(candidates)
    if len(idx) < 2:
        return drop
    sub = local[idx]
    cells = _cell_ids(sub[:, :2], cell)
    tree = cKDTree(sub[:, :2])
    pairs = tree.query_pairs(eps_xy, output_type="ndarray")
    if len(pairs) == 0:
        return drop
    i, j = pairs[:, 0], pairs[:, 1]
    keep = (cells[i] == cells[j]) & (np.abs(sub[i, 2] - sub[j, 2]) > eps_z)
    i, j = i[keep], j[keep]
    higher = np.where(sub[i, 2] > sub[j, 2], i, j)
    drop[idx[np.unique(higher)]] = True
    return drop
