"""Where the plane sweep looks: the point the cameras converge on (orbits), else the ground from the
SfM points (mapping grids), the depth range of each view, and the height planes of near-nadir sweeps.
World units; ``up`` from :func:`~dibrgs_core.camera.frame.estimate_up`."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..camera.pinhole import Camera
from .config import MvsConfig


def depth_range_for(cam: Camera, sparse_points: np.ndarray | None, fallback_distance: float,
                    margin: float = 1.25) -> tuple[float, float]:
    """Plane-sweep range for ``cam``: SfM point depths (2nd-98th percentile, widened by ``margin``)
    when at least 10 project in front of it, else the camera's ``depth_range``, else
    ``[d/2, 2d]`` around ``fallback_distance`` (distance to the scene's look-at point)."""
    if sparse_points is not None and len(sparse_points) >= 10:
        uv, z = cam.project(sparse_points)
        ok = cam.in_image(uv, z)
        if ok.sum() >= 10:
            lo, hi = np.percentile(z[ok], [2, 98])
            near, far = lo / margin, hi * margin
            if cam.depth_range is not None:  # the camera's range is a hard bound when given
                near = max(near, cam.depth_range[0])
                far = min(far, cam.depth_range[1])
            if 0 < near < far:
                return float(near), float(far)
    if cam.depth_range is not None and 0 < cam.depth_range[0] < cam.depth_range[1]:
        return float(cam.depth_range[0]), float(cam.depth_range[1])
    d = max(float(fallback_distance), 1e-6)
    return d / 2, d * 2


def converging_target(cams: Sequence[Camera], min_spread_deg: float = 5.0) -> np.ndarray | None:
    """The point the cameras' optical axes converge on (:func:`cameras.look_at_target`), or None when
    it is not determined.

    Axes that are nearly parallel (a nadir mapping grid, a corridor of parallel
    oblique photos) meet anywhere: the least-squares point then moves tens of
    flying heights, in front of or behind the cameras, with tilts of a degree.
    It counts only when the axes spread by at least ``min_spread_deg`` around
    its direction (the smallest eigenvalue of ``sum(I - d d^T)`` over the
    cameras, per camera, is at least ``sin^2(min_spread_deg)``) and it lies in
    front of every camera.
    """
    from ..camera.frame import look_at_target

    cams = list(cams)
    if len(cams) < 2:
        return None
    A = sum(np.eye(3) - np.outer(c.view_dir, c.view_dir) for c in cams)
    if np.linalg.eigvalsh(A)[0] / len(cams) < np.sin(np.radians(min_spread_deg)) ** 2:
        return None
    target = look_at_target(cams)
    if not np.all(np.isfinite(target)):
        return None
    if any(float((target - c.center) @ c.view_dir) <= 0 for c in cams):
        return None
    return target


def scene_ground(cams: Sequence[Camera], up: np.ndarray, sparse_points: np.ndarray | None = None,
                 min_points: int = 10) -> tuple[float, float, str] | None:
    """``(ground height, flying height above it, source)`` along ``up`` (world units), or None.

    The ground is the cameras' convergence point (:func:`converging_target`)
    when their axes determine one, else the 5th percentile of the heights of
    the SfM points the cameras see (at least ``min_points``); the flying height
    is the median camera height above it. None when neither exists or the
    cameras are not above that ground.
    """
    n_up = np.asarray(up, np.float64) / np.linalg.norm(up)
    cam_h = float(np.median([n_up @ c.center for c in cams]))
    target = converging_target(cams)
    if target is not None and cam_h - float(n_up @ target) > 0:
        ground = float(n_up @ target)
        return ground, cam_h - ground, "look-at"
    if sparse_points is not None and len(sparse_points) >= min_points:
        P = np.asarray(sparse_points, np.float64)
        seen = np.zeros(len(P), bool)
        for c in cams:
            uv, z = c.project(P)
            seen |= c.in_image(uv, z)
        if seen.sum() >= min_points:
            ground = float(np.percentile(P[seen] @ n_up, 5.0))
            if cam_h - ground > 0:
                return ground, cam_h - ground, "sfm"
    return None


def scene_heights(cams: Sequence[Camera], up: np.ndarray, cfg: MvsConfig,
                  sparse_points: np.ndarray | None = None, span: float = 1.0) -> tuple[float, float] | None:
    """Heights to sweep: from ``height_below`` to ``height_above`` times the flying height above the
    ground (:func:`scene_ground`: the cameras' convergence point, else the SfM points) times ``span``
    (:func:`~dibrgs_core.camera.frame.span_factor`: a narrow lens sees a small patch of ground from
    high up, whose relief is small against the height).

    The cameras' depth ranges allow every height from far below the ground up
    to the cameras; sweeping all of it spreads the planes thin and, on
    repetitive texture (street grids), finds spurious matches far from the
    scene. None (full range) when the ground is unknown or not below the cameras.
    """
    g = scene_ground(cams, up, sparse_points)
    if g is None:
        return None
    ground, alt, _ = g
    return ground - cfg.height_below * alt * span, ground + cfg.height_above * alt * span


def sweep_up(cams: Sequence[Camera], config: MvsConfig) -> np.ndarray | None:
    """The up axis for horizontal (height) planes, or None for fronto-parallel planes.

    ``planes="auto"`` sweeps heights when the cameras look down (mean view
    direction within ``max_nadir_deg`` of the up axis estimated from them, with
    an unambiguous up): ground and roofs are then planes of the sweep, so the
    NCC windows match exactly even across wide baselines, where a fronto-parallel
    plane cuts the tilted ground at one depth only.
    """
    from ..camera.frame import estimate_up, near_nadir

    if config.planes == "fronto":
        return None
    up, conf = estimate_up(cams)
    if config.planes == "height":
        return up
    if config.planes != "auto":
        raise ValueError(f"unknown MVS plane family {config.planes!r} (auto, height, fronto)")
    if not near_nadir(cams, config.max_nadir_deg, config.min_up_confidence)[0]:
        return None
    return up
