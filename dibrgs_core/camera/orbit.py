"""Circular acquisition orbits: the fitted circle, points and cameras on it.

OpenCV cameras (:mod:`.pinhole`), world units, up from :func:`.frame.estimate_up`.
NumPy only.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .frame import estimate_up, look_at_target, up_frame
from .pinhole import Camera, look_at


@dataclass
class Orbit:
    """A circular acquisition orbit.

    Attributes:
        center: circle centre in world coordinates.
        normal: unit normal of the circle's plane, oriented along the scene up.
        radius: circle radius (world units).
        height: signed distance from the look-at target to the circle plane
            along ``normal``.
        tilt_deg: angle between the circle plane normal and the scene up axis.
        elevation_deg: mean angle below the horizon at which cameras look.
        target: look-at point of the cameras.
        rms: RMS distance of the fitted cameras from the circle.
        basis: two unit vectors spanning the circle plane (angle 0 along the first).
    """

    center: np.ndarray
    normal: np.ndarray
    radius: float
    height: float
    tilt_deg: float
    elevation_deg: float
    target: np.ndarray
    rms: float
    basis: np.ndarray = field(default_factory=lambda: np.eye(3)[:2])

    def point(self, theta: np.ndarray | float) -> np.ndarray:
        """Points on the circle at angles ``theta`` (radians), shape (..., 3)."""
        th = np.asarray(theta, dtype=np.float64)[..., None]
        return self.center + self.radius * (np.cos(th) * self.basis[0] + np.sin(th) * self.basis[1])

    def angle_of(self, X: np.ndarray) -> np.ndarray:
        """Angle (radians) of points projected onto the circle plane."""
        d = np.asarray(X, dtype=np.float64) - self.center
        return np.arctan2(d @ self.basis[1], d @ self.basis[0])

    def cameras(self, thetas: Sequence[float], like: Camera, up: np.ndarray | None = None) -> list[Camera]:
        """Cameras on the orbit at ``thetas`` looking at ``target``, with ``like``'s intrinsics."""
        up = self.normal if up is None else up
        out = []
        for i, th in enumerate(thetas):
            eye = self.point(th)
            out.append(Camera(K=like.K.copy(), w2c=look_at(eye, self.target, up), width=like.width,
                              height=like.height, name=f"orbit_{i:03d}", depth_range=like.depth_range))
        return out

    def to_dict(self) -> dict:
        return {"center": self.center.tolist(), "normal": self.normal.tolist(), "radius": self.radius,
                "height": self.height, "tilt_deg": self.tilt_deg, "elevation_deg": self.elevation_deg,
                "target": self.target.tolist(), "rms": self.rms}


def fit_orbit(cams: Sequence[Camera], up: np.ndarray | None = None) -> Orbit:
    """Fit a circle (centre, radius, plane) through the camera centres.

    The plane is the least-squares plane of the centres (its normal oriented
    along ``up``); with fewer than 3 cameras, or collinear ones, the plane is
    taken perpendicular to ``up``. The circle is an algebraic (Kasa) fit in
    that plane, refined with a few Gauss-Newton steps on the geometric
    distance.
    """
    cams = list(cams)
    if len(cams) < 2:
        raise ValueError("fit_orbit needs at least 2 cameras")
    if up is None:
        up, _ = estimate_up(cams)
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    C = np.stack([c.center for c in cams])
    mu = C.mean(axis=0)
    normal = up.copy()
    if len(cams) >= 3:
        _, s, vt = np.linalg.svd(C - mu)
        if s[1] > 1e-9 * max(s[0], 1e-300):
            normal = vt[2]
            if normal @ up < 0:
                normal = -normal
    # In-plane basis: first axis towards the first camera, so angle 0 is view 1.
    d0 = C[0] - mu
    e1 = d0 - (d0 @ normal) * normal
    if np.linalg.norm(e1) < 1e-12:
        e1 = up_frame(normal)[0]
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    P = np.stack([(C - mu) @ e1, (C - mu) @ e2], axis=1)
    if len(cams) >= 3:
        A = np.column_stack([2 * P, np.ones(len(P))])
        sol, *_ = np.linalg.lstsq(A, (P ** 2).sum(1), rcond=None)
        c2 = sol[:2]
        r = float(np.sqrt(max(sol[2] + c2 @ c2, 0.0)))
        for _ in range(10):  # Gauss-Newton on geometric residuals
            diff = P - c2
            dist = np.linalg.norm(diff, axis=1)
            dist = np.where(dist < 1e-12, 1e-12, dist)
            J = np.column_stack([-diff / dist[:, None], -np.ones(len(P))])
            res = dist - r
            step, *_ = np.linalg.lstsq(J, -res, rcond=None)
            c2 = c2 + step[:2]
            r = float(r + step[2])
    else:
        c2 = P.mean(axis=0)
        r = float(np.linalg.norm(P - c2, axis=1).mean())
    center = mu + c2[0] * e1 + c2[1] * e2
    rms = float(np.sqrt(np.mean((np.linalg.norm(P - c2, axis=1) - r) ** 2)))
    target = look_at_target(cams)
    tilt = float(np.degrees(np.arccos(np.clip(normal @ up, -1.0, 1.0))))
    dirs = np.stack([c.view_dir for c in cams])
    elev = float(np.degrees(np.arcsin(np.clip(-(dirs @ up), -1.0, 1.0))).mean())
    height = float((center - target) @ normal)
    return Orbit(center=center, normal=normal, radius=abs(r), height=height, tilt_deg=tilt,
                 elevation_deg=elev, target=target, rms=rms, basis=np.stack([e1, e2]))
