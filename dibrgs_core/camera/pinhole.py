"""Pinhole cameras and the conventions DIBR-GS meets.

Conventions (used everywhere in ``dibrgs_core``):

* **OpenCV / COLMAP / LEVIR-NVS** (the internal one): camera axes x right,
  y down, z forward. ``Camera.w2c`` is the 4x4 *world-to-camera* matrix, so a
  world point ``X`` maps to camera coordinates ``w2c @ [X, 1]``.
* **Pixels**: ``K`` is in pixels and pixel ``(i, j)`` covers ``[i, i+1] x
  [j, j+1]``; its centre is at ``(i + 0.5, j + 0.5)``. A camera with
  ``cx = W / 2`` is therefore centred on the image.
* **Blender** conversions: :mod:`.blender`.

This module imports numpy only, so Blender's Python can use it without torch.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np


@dataclass
class Camera:
    """A pinhole camera.

    Attributes:
        K: 3x3 intrinsics in pixels (pixel centres at +0.5).
        w2c: 4x4 world-to-camera extrinsics, OpenCV axes (x right, y down,
            z forward).
        width, height: image size in pixels.
        name: view id, e.g. ``"001"``.
        depth_range: optional ``(near, far)`` along the camera z axis, in
            world units.
    """

    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    name: str = ""
    depth_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.w2c = np.asarray(self.w2c, dtype=np.float64).reshape(4, 4)
        self.width = int(self.width)
        self.height = int(self.height)

    # -- extrinsics ---------------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        """3x3 world-to-camera rotation."""
        return self.w2c[:3, :3]

    @property
    def t(self) -> np.ndarray:
        """World-to-camera translation (3,)."""
        return self.w2c[:3, 3]

    @property
    def c2w(self) -> np.ndarray:
        """4x4 camera-to-world matrix (OpenCV axes), the exact rigid inverse."""
        return rigid_inverse(self.w2c)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (3,)."""
        return -self.R.T @ self.t

    @property
    def view_dir(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in world coordinates (3,)."""
        d = self.R[2, :]
        return d / np.linalg.norm(d)

    # -- intrinsics ---------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def span(self) -> float:
        """Width of what the view covers per unit of depth: ``sqrt(W H / (fx fy))``, the geometric
        mean of both sides (``2 tan(fov / 2)`` for a square image; about 1 for a survey camera, 0.01
        for a satellite's). The same at any image size."""
        return float(np.sqrt(self.width * self.height / (self.fx * self.fy)))

    def translated(self, d: Sequence[float] | np.ndarray) -> "Camera":
        """The same camera in a world moved by ``d`` (world units): a point ``X`` there is
        ``X + d``, the rotation is unchanged and the centre becomes ``center + d``, exactly even
        when ``R`` carries float32 rounding (a camera from Blender): ``t - R d`` would move it by
        that rounding times ``|d|``, a unit at 1e7."""
        w2c = self.w2c.copy()
        w2c[:3, 3] = self.t - np.linalg.solve(self.R.T, np.asarray(d, np.float64).reshape(3))
        return replace(self, w2c=w2c)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (pixel-centre exact)."""
        K = self.K.copy()
        K[:2] *= factor
        return replace(self, K=K, width=max(1, round(self.width * factor)),
                       height=max(1, round(self.height * factor)))

    # -- projection ---------------------------------------------------------
    def world_to_cam(self, X: np.ndarray) -> np.ndarray:
        """(N,3) world points -> (N,3) camera-frame points."""
        X = np.asarray(X, dtype=np.float64)
        return X @ self.R.T + self.t

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N,3) world points. Returns (uv (N,2) pixels, depth z (N,)).

        Points with z <= 0 get non-finite-free but meaningless uv; filter by depth.
        """
        Xc = self.world_to_cam(X)
        z = Xc[:, 2]
        zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
        uv = (Xc[:, :2] / zs[:, None]) * np.array([self.fx, self.fy]) + np.array([self.cx, self.cy])
        # Skew, if any.
        uv[:, 0] += self.K[0, 1] * Xc[:, 1] / zs
        return uv, z

    def in_image(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Mask of the projections ``uv, z`` (:meth:`project`) in front of the camera and inside its image."""
        return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)

    def unproject(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(N,2) pixel positions at z-depths (N,) -> (N,3) world points (the inverse of :meth:`project`)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        rays = np.stack([uv[:, 0], uv[:, 1], np.ones(len(uv))], 1) @ np.linalg.inv(self.K).T
        return (rays * np.asarray(z, dtype=np.float64).reshape(-1, 1) - self.t) @ self.R  # camera -> world

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays through every pixel centre, row-major (H*W).

        Returns (origins (H*W,3), directions (H*W,3)) in world space, where the
        direction has camera-z component 1, so ``origin + d * dir`` is the point
        at z-depth ``d``.
        """
        j, i = np.meshgrid(np.arange(self.height) + 0.5, np.arange(self.width) + 0.5, indexing="ij")
        pix = np.stack([i.ravel(), j.ravel(), np.ones(i.size)], axis=1)
        dirs_c = pix @ np.linalg.inv(self.K).T
        dirs_w = dirs_c @ self.R  # R^T applied to row vectors
        origins = np.broadcast_to(self.center, dirs_w.shape).copy()
        return origins, dirs_w

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """(H,W) z-depth map -> (H*W,3) world points, row-major."""
        o, d = self.pixel_rays()
        return o + d * np.asarray(depth, dtype=np.float64).reshape(-1, 1)


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform using R^T (exact for rotations)."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float]) -> np.ndarray:
    """World-to-camera (OpenCV) matrix of a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear up in the image (image -y).
    Falls back to another reference axis when ``up`` is parallel to the view.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z /= n
    up = up / max(np.linalg.norm(up), 1e-300)
    x = np.cross(z, up)  # image right = forward x up (OpenCV: y down, so -y follows up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any image x
        alt = np.eye(3)[np.argmin(np.abs(z))]
        x = np.cross(z, alt)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c
