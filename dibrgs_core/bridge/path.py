"""Cameras along a user-edited path (the add-on's pseudo-view curve).

The add-on evaluates its curve object in world space (Blender does the spline
maths, whatever the spline type) and hands the resulting polyline here. The
polyline is resampled uniformly by arc length and every sample becomes a
camera looking at the target, with the intrinsics of a reference camera.
World units and the OpenCV camera convention of :mod:`dibrgs_core.camera.pinhole`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..camera.pinhole import Camera, look_at
from ..camera.orbit import Orbit
from ..camera.serialize import camera_to_dict
from ..common.fileio import write_json


def resample_polyline(points: np.ndarray, n: int, closed: bool) -> np.ndarray:
    """``n`` points spaced uniformly by arc length along a polyline.

    Args:
        points: (M, 3) polyline vertices in order, M >= 1.
        n: number of samples, >= 1.
        closed: the polyline returns from the last vertex to the first. A
            closed path gets samples at ``k * L / n`` (the first is not
            repeated at the end); an open one at ``k * L / (n - 1)`` so both
            end points are included.

    Returns:
        (n, 3) float64 samples. A degenerate polyline (zero length) returns
        its first vertex ``n`` times.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0:
        raise ValueError("resample_polyline: empty polyline")
    if n < 1:
        raise ValueError(f"resample_polyline: n must be >= 1, got {n}")
    if not np.isfinite(P).all():
        raise ValueError("resample_polyline: non-finite vertices")
    if closed:
        P = np.concatenate([P, P[:1]], axis=0)
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = cum[-1]
    if total <= 0.0:
        return np.repeat(P[:1], n, axis=0)
    if closed:
        s = np.arange(n) * (total / n)
    else:
        s = np.linspace(0.0, total, n) if n > 1 else np.zeros(1)
    # Segment index of each sample; zero-length segments are never chosen
    # because searchsorted lands on the last vertex with that arc length.
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    seg_len = seg[idx]
    frac = np.where(seg_len > 0, (s - cum[idx]) / np.where(seg_len > 0, seg_len, 1.0), 0.0)
    return P[idx] + frac[:, None] * (P[idx + 1] - P[idx])


def path_cameras(points: np.ndarray, n: int, target: Sequence[float], up: Sequence[float],
                 like: Camera, closed: bool, prefix: str = "pseudo") -> list[Camera]:
    """``n`` cameras spaced along the polyline, each looking at ``target``.

    ``up`` is the world direction that appears up in the images (the scene's
    up axis); ``like`` gives K, image size and depth range. Names are
    ``f"{prefix}_{k:03d}"``. A sample that coincides with the target is
    moved off it along ``up`` by a tiny amount so the look-at is defined.
    """
    eyes = resample_polyline(points, n, closed)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    scale = max(float(np.abs(eyes).max(initial=0.0)), float(np.abs(target).max()), 1.0)
    cams = []
    for k, eye in enumerate(eyes):
        if np.linalg.norm(eye - target) < 1e-9 * scale:
            eye = eye + 1e-6 * scale * up / max(np.linalg.norm(up), 1e-300)
        cams.append(Camera(K=like.K.copy(), w2c=look_at(eye, target, up), width=like.width,
                           height=like.height, name=f"{prefix}_{k:03d}", depth_range=like.depth_range))
    return cams


def orbit_control_points(orbit: Orbit, n: int = 8) -> np.ndarray:
    """(n, 3) points on the fitted orbit, evenly spaced, starting at angle 0 (view 1).

    The add-on turns them into a cyclic curve with automatic handles; 8
    points keep the curve within a fraction of a percent of the circle.
    """
    if n < 3:
        raise ValueError("an orbit curve needs at least 3 control points")
    return orbit.point(np.arange(n) * (2.0 * np.pi / n))


def write_camera_list(path: str | Path, cams: Sequence[Camera]) -> Path:
    """Write cameras as a JSON camera list (``camera_to_dict`` format), atomically."""
    path = Path(path)
    write_json(path, [camera_to_dict(c) for c in cams])
    return path
