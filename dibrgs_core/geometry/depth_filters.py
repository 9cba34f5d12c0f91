"""Filters of per-view depth maps: small isolated patches (speckles) and the multi-view geometric
consistency check. Depth is z-depth in world units, NaN or 0 = none."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..camera.pinhole import Camera

log = logging.getLogger("dibrgs.mvs")


@dataclass
class MvsResult:
    """Per-view depth (HxW float32, NaN where invalid) and confidence (HxW float32 in [0,1])."""

    depth: np.ndarray
    confidence: np.ndarray
    ncc: np.ndarray


def speckle_mask(depth: np.ndarray, tol: float, min_px: int) -> np.ndarray:
    """True where a finite depth belongs to a connected region of at least ``min_px`` pixels; two
    4-neighbours connect when their depths differ by at most ``tol`` times the smaller one."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    d = np.asarray(depth, np.float64)
    H, W = d.shape
    ok = np.isfinite(d)
    idx = np.arange(H * W).reshape(H, W)
    rows, cols = [], []
    for a, b, da, db in ((idx[:, :-1], idx[:, 1:], d[:, :-1], d[:, 1:]), (idx[:-1], idx[1:], d[:-1], d[1:])):
        link = np.isfinite(da) & np.isfinite(db) & (np.abs(da - db) <= tol * np.fmin(np.abs(da), np.abs(db)))
        rows.append(a[link])
        cols.append(b[link])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(H * W, H * W))
    _, lab = connected_components(g, directed=False)
    size = np.bincount(lab)
    return ok & (size[lab] >= min_px).reshape(H, W)


def consistency_filter(cams: Sequence[Camera], results: list[MvsResult], tol: float, min_views: int,
                        max_reproj_px: float = 1.0, sources: Sequence[Sequence[int]] | None = None
                        ) -> list[MvsResult]:
    """Keep depths that at least ``min_views`` other views confirm (forward-backward check);
    ``sources[i]``: the views that may confirm view i's (default: all others).

    A pixel's 3D point is projected into view j, lifted again with j's own
    depth there and projected back: j confirms it when that round trip lands
    within ``max_reproj_px`` pixels of where it started and the two depths
    agree within the relative tolerance ``tol``. Comparing depths alone lets
    chance agreements between two wrong depth maps through (depth differences
    along j's ray are insensitive to sideways errors). A point that lies in
    front of the surface some other view sees along the same line of sight
    (a free-space violation) is dropped as well: two views matching each other
    on repetitive texture agree with each other, but such a floating point
    contradicts the third.
    """
    filtered = []
    for i, (ci, ri) in enumerate(zip(cams, results)):
        d = ri.depth.reshape(-1)
        ok = np.isfinite(d)
        X = ci.backproject(np.where(ok, d, 1.0).reshape(ci.height, ci.width))
        uv0, _ = ci.project(X)
        votes = np.zeros(d.size, np.int32)
        blocks = np.zeros(d.size, bool)
        for j in (sources[i] if sources is not None else range(len(cams))):
            if j == i:
                continue
            cj, rj = cams[j], results[j]
            uv, z = cj.project(X)
            u = np.floor(uv[:, 0]).astype(np.int64)
            v = np.floor(uv[:, 1]).astype(np.int64)
            inside = ok & (z > 0) & (u >= 0) & (u < cj.width) & (v >= 0) & (v < cj.height)
            idx = np.flatnonzero(inside)
            dj = rj.depth[v[idx], u[idx]].astype(np.float64)
            good = np.isfinite(dj)
            idx, dj = idx[good], dj[good]
            # Free-space violation: the point would float in front of the surface j sees there.
            blocks[idx[z[idx] < dj * (1.0 - 2.0 * tol)]] = True
            if not len(idx):
                continue
            # Lift j's depth at the pixel (sub-pixel position kept) and project it back into i.
            Xj = cj.unproject(uv[idx], dj)
            uvb, zb = ci.project(Xj)
            err = np.linalg.norm(uvb - uv0[idx], axis=1)
            agree = (err <= max_reproj_px) & (np.abs(zb - d[idx]) <= tol * np.abs(d[idx]))
            votes[idx[agree]] += 1
        keep = (ok & (votes >= min_views) & ~blocks).reshape(ci.height, ci.width)
        filtered.append(MvsResult(np.where(keep, ri.depth, np.nan).astype(np.float32),
                                  np.where(keep, ri.confidence, 0).astype(np.float32), ri.ncc))
        log.info("MVS view %s: %.1f%% pass the %d-view consistency check", ci.name, 100.0 * keep.mean(), min_views)
    return filtered
