"""Point-cloud tools shared by fusion, anchors and pseudo views: spacing, voxel grids, z-buffers.

Points are (N,3) world coordinates in the scene's units; cameras are OpenCV
(:class:`~dibrgs_core.camera.pinhole.Camera`); depth is z-depth along the camera axis.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..camera.pinhole import Camera


def zbuffer(cam: Camera, points: np.ndarray, farthest: bool = False, footprint: float = 0.0,
            max_radius: int = 4, empty: float = np.nan) -> np.ndarray:
    """Depth image (H,W, float64 z-depth) of ``points`` seen by ``cam``: the nearest point per pixel
    (or the farthest), ``empty`` where none lands.

    With ``footprint`` (world units, e.g. the cloud's point spacing) each point is splatted as a
    square of half-size ``round(footprint * f / z / 2)`` pixels, at most ``max_radius``, so a
    sparse cloud still covers the image; 0 writes only the pixel the point falls in.
    """
    H, W = cam.height, cam.width
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    acc = np.full(H * W, -np.inf if farthest else np.inf)
    if len(pts):
        uv, z = cam.project(pts)
        ok = (z > 0) & np.isfinite(z) & np.isfinite(uv).all(1)
        uv, z = uv[ok], z[ok]
        f = 0.5 * (cam.fx + cam.fy)
        r = np.clip(np.round(0.5 * footprint * f / z), 0, max_radius).astype(np.int64)
        u = np.floor(uv[:, 0]).astype(np.int64)
        v = np.floor(uv[:, 1]).astype(np.int64)
        near = (u >= -r) & (u < W + r) & (v >= -r) & (v < H + r)
        u, v, z, r = u[near], v[near], z[near], r[near]
        reduce = np.maximum.at if farthest else np.minimum.at
        R = int(r.max()) if len(r) else 0
        for dy in range(-R, R + 1):
            for dx in range(-R, R + 1):
                m = r >= max(abs(dx), abs(dy))
                x, y = u[m] + dx, v[m] + dy
                inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
                reduce(acc, y[inside] * W + x[inside], z[m][inside])
    return np.where(np.isfinite(acc), acc, empty).reshape(H, W)


def voxel_downsample(points: np.ndarray, colors: np.ndarray, voxel: float, origin: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Mean position and colour per occupied voxel of side ``voxel`` (world axes, relative to ``origin``)."""
    if len(points) == 0 or not voxel or voxel <= 0:
        return np.asarray(points, np.float64), np.asarray(colors, np.uint8)
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    rel = np.asarray(points, np.float64) - origin
    keys = np.floor(rel / voxel).astype(np.int64)
    _, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    m = len(cnt)
    P = np.zeros((m, 3))
    C = np.zeros((m, 3))
    np.add.at(P, inv, rel)
    np.add.at(C, inv, np.asarray(colors, np.float64))
    P /= cnt[:, None]
    C /= cnt[:, None]
    return P + origin, np.clip(C.round(), 0, 255).astype(np.uint8)


def point_spacing(points: np.ndarray, sample: int = 4000, seed: int = 0) -> float:
    """Median distance from a point to its nearest neighbour (world units); 0 if < 2 points."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    tree = cKDTree(pts)
    rng = np.random.default_rng(seed)
    q = pts[rng.choice(len(pts), size=min(sample, len(pts)), replace=False)]
    d, _ = tree.query(q, k=2)
    return float(np.median(d[:, 1]))


def voxelize(points: np.ndarray, voxel: float) -> np.ndarray:
    """Unique voxel centres ``round(p / voxel) * voxel`` of ``points`` (N,3), as float32."""
    keys = np.unique(np.round(np.asarray(points, np.float64) / voxel).astype(np.int64), axis=0)
    return (keys * voxel).astype(np.float32)
