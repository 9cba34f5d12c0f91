"""Which other views each view is matched against in multi-view stereo.

Sweeping every view against every other one costs time in the square of the view count (a
drone survey of 80 photos: about an hour at 256 px on this project's CPU). Each reference
view is matched against the ``k`` others that see the most of what it sees from a useful
angle, as COLMAP's patch-match stereo (up to 20 sources, ranked by shared points) and MVSNet
(a few, scored by baseline angle) do; with ``k`` or fewer others, all of them.

The score of a source is summed over surface samples of the reference: the SfM points it
sees, or, without enough of them, a grid of its pixels at the middle of its depth range. A
sample counts when the source sees it in front, inside its image, weighted by MVSNet's
preference for the angle between the two rays there (a Gaussian about 5 degrees, narrow
below, wide above; Yao et al. 2018). Rays nearly parallel (below ``min_angle_deg``: the same
viewpoint, no depth information) count nothing.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..camera.pinhole import Camera

#: MVSNet's view-selection angle prior (degrees): peak, spread below it, spread above it.
ANGLE_PEAK_DEG, ANGLE_SIGMA_BELOW, ANGLE_SIGMA_ABOVE = 5.0, 1.0, 10.0


def reference_samples(cam: Camera, sparse_points: np.ndarray | None, depth_range: tuple[float, float],
                      max_points: int = 400, grid: int = 16) -> np.ndarray:
    """World points (N, 3) on the surface ``cam`` sees: up to ``max_points`` SfM points in its
    image (when at least 10 are), else a ``grid`` x ``grid`` raster of its pixels at the
    geometric middle of ``depth_range`` (z-depths, world units)."""
    if sparse_points is not None and len(sparse_points) >= 10:
        uv, z = cam.project(sparse_points)
        ok = cam.in_image(uv, z)
        pts = np.asarray(sparse_points)[ok]
        if len(pts) >= 10:
            return pts[:: max(1, len(pts) // max_points)]
    u = (np.arange(grid) + 0.5) * cam.width / grid
    v = (np.arange(grid) + 0.5) * cam.height / grid
    uu, vv = np.meshgrid(u, v)
    depth = float(np.sqrt(depth_range[0] * depth_range[1]))
    return cam.unproject(np.c_[uu.ravel(), vv.ravel()], np.full(uu.size, depth))


def angle_weight(angle_deg: np.ndarray, min_angle_deg: float) -> np.ndarray:
    """MVSNet's angle prior, 0 below ``min_angle_deg``."""
    a = np.asarray(angle_deg, np.float64)
    sigma = np.where(a < ANGLE_PEAK_DEG, ANGLE_SIGMA_BELOW, ANGLE_SIGMA_ABOVE)
    w = np.exp(-((a - ANGLE_PEAK_DEG) ** 2) / (2.0 * sigma**2))
    return np.where(a >= min_angle_deg, w, 0.0)


def pair_scores(cams: Sequence[Camera], samples: Sequence[np.ndarray], min_angle_deg: float) -> np.ndarray:
    """(V, V) score of view j as a source for reference i (0 on the diagonal)."""
    n = len(cams)
    scores = np.zeros((n, n))
    for i, (ci, X) in enumerate(zip(cams, samples)):
        to_i = ci.center - X
        to_i /= np.maximum(np.linalg.norm(to_i, axis=1, keepdims=True), 1e-300)
        for j, cj in enumerate(cams):
            if j == i:
                continue
            uv, z = cj.project(X)
            inside = cj.in_image(uv, z)
            if not inside.any():
                continue
            to_j = cj.center - X[inside]
            to_j /= np.maximum(np.linalg.norm(to_j, axis=1, keepdims=True), 1e-300)
            cos = np.clip(np.sum(to_i[inside] * to_j, axis=1), -1.0, 1.0)
            scores[i, j] = angle_weight(np.degrees(np.arccos(cos)), min_angle_deg).sum() / len(X)
    return scores


def select_sources(cams: Sequence[Camera], sparse_points: np.ndarray | None,
                   depth_ranges: Sequence[tuple[float, float]], max_sources: int,
                   min_angle_deg: float = 1.0) -> list[list[int]]:
    """For each view, the indices of the views it is matched against, best first.

    With ``max_sources`` or fewer other views (or ``max_sources`` 0), every other view in its
    order. Otherwise the ``max_sources`` best by :func:`pair_scores`; sources that score 0 (they
    see none of the reference's samples from a useful angle) are left out, unless no source scores
    above 0, when the nearest camera centres are taken.
    """
    n = len(cams)
    everyone = [[j for j in range(n) if j != i] for i in range(n)]
    if max_sources <= 0 or n - 1 <= max_sources:
        return everyone
    samples = [reference_samples(c, sparse_points, r) for c, r in zip(cams, depth_ranges)]
    scores = pair_scores(cams, samples, min_angle_deg)
    centres = np.array([c.center for c in cams])
    out = []
    for i in range(n):
        order = sorted(everyone[i], key=lambda j: -scores[i, j])
        picked = [j for j in order[:max_sources] if scores[i, j] > 0]
        if not picked:
            picked = sorted(everyone[i], key=lambda j: float(np.linalg.norm(centres[j] - centres[i])))[:max_sources]
        out.append(picked)
    return out
