"""Pinhole cameras and the conventions DIBR-GS meets.

Conventions (used everywhere in ``dibrgs_core``):

* **OpenCV / COLMAP / LEVIR-NVS** (the internal one): camera axes x right,
  y down, z forward. ``Camera.w2c`` is the 4x4 *world-to-camera* matrix, so a
  world point ``X`` maps to camera coordinates ``w2c @ [X, 1]``.
* **Pixels**: ``K`` is in pixels and pixel ``(i, j)`` covers ``[i, i+1] x
  [j, j+1]``; its centre is at ``(i + 0.5, j + 0.5)``. A camera with
  ``cx = W / 2`` is therefore centred on the image.
* **Blender**: the camera looks down its local -Z with +Y up, and
  ``matrix_world`` is *camera-to-world*. Intrinsics are the focal length and
  sensor size in millimetres with a sensor fit, a lens shift in units of the
  fitted sensor dimension, and a pixel aspect ratio.

This module imports numpy only, so Blender's Python can use it without torch.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Iterable, Sequence

import numpy as np

# OpenCV camera axes -> Blender camera axes (flip y and z); its own inverse.
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


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


# ---------------------------------------------------------------------------
# Blender conversion
# ---------------------------------------------------------------------------
@dataclass
class BlenderCameraParams:
    """Everything Blender needs to reproduce a :class:`Camera` exactly.

    ``matrix_world`` is camera-to-world with Blender camera axes (looks down
    -Z, +Y up). ``lens``, ``sensor_width`` and ``sensor_height`` are in mm;
    ``shift_x``/``shift_y`` are in units of the fitted sensor dimension as in
    ``bpy.types.Camera``; ``sensor_fit`` is ``'AUTO'``, ``'HORIZONTAL'`` or
    ``'VERTICAL'``.
    """

    matrix_world: np.ndarray
    lens: float
    sensor_width: float
    sensor_height: float
    sensor_fit: str
    shift_x: float
    shift_y: float
    resolution_x: int
    resolution_y: int
    pixel_aspect_x: float = 1.0
    pixel_aspect_y: float = 1.0
    clip_start: float = 0.1
    clip_end: float = 1000.0
    name: str = ""


def _blender_fit(sensor_fit: str, width: int, height: int, pax: float, pay: float) -> str:
    if sensor_fit == "AUTO":
        return "HORIZONTAL" if width * pax >= height * pay else "VERTICAL"
    if sensor_fit not in ("HORIZONTAL", "VERTICAL"):
        raise ValueError(f"unknown sensor_fit {sensor_fit!r}")
    return sensor_fit


def to_blender(cam: Camera, sensor_width: float = 36.0, sensor_fit: str = "AUTO") -> BlenderCameraParams:
    """Convert an OpenCV camera to Blender camera parameters (exact).

    ``fx != fy`` is expressed with the pixel aspect ratio (fy/fx = pax/pay);
    an off-centre principal point with the lens shift. Skew is not
    representable in Blender and raises.
    """
    if abs(cam.K[0, 1]) > 1e-12 * max(1.0, cam.fx):
        raise ValueError("Blender cameras cannot represent a skewed K")
    W, H = cam.width, cam.height
    # Pixel aspect: Blender wants both >= 1; keep the larger side at 1.
    ratio = cam.fy / cam.fx  # = pax / pay
    if ratio >= 1.0:
        pax, pay = ratio, 1.0
    else:
        pax, pay = 1.0, 1.0 / ratio
    fit = _blender_fit(sensor_fit, W, H, pax, pay)
    ycor = pay / pax
    # ``sensor_width`` is the size of the fitted sensor dimension (Blender uses
    # sensor_width for AUTO and HORIZONTAL, sensor_height for VERTICAL).
    sensor = sensor_width
    viewfac = W if fit == "HORIZONTAL" else ycor * H
    lens = cam.fx * sensor / viewfac
    shift_x = (W / 2.0 - cam.cx) / viewfac
    shift_y = (cam.cy - H / 2.0) * ycor / viewfac
    other = sensor * (H * ycor / W if fit == "HORIZONTAL" else W / (H * ycor))
    sw, sh = (sensor, other) if (sensor_fit == "AUTO" or fit == "HORIZONTAL") else (other, sensor)
    near, far = cam.depth_range if cam.depth_range else (0.1, 1000.0)
    return BlenderCameraParams(
        matrix_world=cam.c2w @ _CV_TO_GL, lens=float(lens), sensor_width=float(sw),
        sensor_height=float(sh), sensor_fit=sensor_fit, shift_x=float(shift_x),
        shift_y=float(shift_y), resolution_x=W, resolution_y=H, pixel_aspect_x=float(pax),
        pixel_aspect_y=float(pay), clip_start=float(near), clip_end=float(far), name=cam.name)


def from_blender(p: BlenderCameraParams, depth_range: bool = False) -> Camera:
    """Convert Blender camera parameters back to an OpenCV :class:`Camera`.

    Follows Blender's viewplane computation: the fitted sensor dimension spans
    ``W`` (horizontal fit) or ``H * pay / pax`` x-pixels (vertical fit).
    """
    W, H = int(p.resolution_x), int(p.resolution_y)
    pax, pay = float(p.pixel_aspect_x), float(p.pixel_aspect_y)
    fit = _blender_fit(p.sensor_fit, W, H, pax, pay)
    ycor = pay / pax
    if p.sensor_fit == "AUTO":
        sensor = p.sensor_width
    else:
        sensor = p.sensor_width if fit == "HORIZONTAL" else p.sensor_height
    viewfac = W if fit == "HORIZONTAL" else ycor * H
    fx = p.lens / sensor * viewfac
    fy = fx / ycor
    cx = W / 2.0 - p.shift_x * viewfac
    cy = H / 2.0 + p.shift_y * viewfac / ycor
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    c2w_cv = np.asarray(p.matrix_world, dtype=np.float64) @ _CV_TO_GL
    return Camera(K=K, w2c=rigid_inverse(c2w_cv), width=W, height=H, name=p.name,
                  depth_range=(p.clip_start, p.clip_end) if depth_range else None)


# ---------------------------------------------------------------------------
# Scene frame from a set of cameras
# ---------------------------------------------------------------------------
def estimate_up(cams: Iterable[Camera]) -> tuple[np.ndarray, float]:
    """Scene up axis from the cameras: opposite to the mean viewing direction.

    Returns ``(up (3,), confidence)`` where confidence is the length of the
    mean unit viewing direction in [0, 1]; near 0 means the cameras look in
    all directions and the up axis is ambiguous. Aerial views are not assumed
    to use +Z as up.
    """
    dirs = np.stack([c.view_dir for c in cams])
    m = dirs.mean(axis=0)
    n = float(np.linalg.norm(m))
    if n < 1e-12:
        return np.array([0.0, 0.0, 1.0]), 0.0
    return -m / n, n


def nadir_angle_deg(cams: Sequence[Camera], up: np.ndarray | None = None) -> float:
    """Angle in degrees between the mean viewing direction and straight down."""
    if up is None:
        up, _ = estimate_up(cams)
    dirs = np.stack([c.view_dir for c in cams])
    ang = np.degrees(np.arccos(np.clip(dirs @ -up, -1.0, 1.0)))
    return float(ang.mean())


def up_frame(up: np.ndarray) -> np.ndarray:
    """3x3 rotation whose rows are (e1, e2, up): world -> (horizontal, horizontal, height)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    ref = np.eye(3)[np.argmin(np.abs(up))]
    e1 = np.cross(ref, up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return np.stack([e1, e2, up])


def look_at_target(cams: Sequence[Camera]) -> np.ndarray:
    """Least-squares point closest to all optical axes (the orbit's look-at point)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cams:
        d = c.view_dir
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if np.linalg.cond(A) > 1e12:  # all axes parallel: no unique point
        return np.mean([c.center + c.view_dir for c in cams], axis=0)
    return np.linalg.solve(A, b)


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


# ---------------------------------------------------------------------------
# JSON camera lists (used by `dibrgs render`, `dibrgs train --pseudo-path` and
# the Blender add-on): [{"name", "width", "height", "K", "w2c", "depth_range"?}]
# ---------------------------------------------------------------------------
def camera_to_dict(cam: Camera) -> dict:
    d = {"name": cam.name, "width": cam.width, "height": cam.height,
         "K": cam.K.tolist(), "w2c": cam.w2c.tolist()}
    if cam.depth_range is not None:
        d["depth_range"] = list(cam.depth_range)
    return d


def camera_from_dict(d: dict, source: str = "<dict>") -> Camera:
    """Build a camera from :func:`camera_to_dict` output; ValueError names ``source``."""
    try:
        K = np.asarray(d["K"], dtype=np.float64)
        w2c = np.asarray(d["w2c"], dtype=np.float64)
        W, H = int(d["width"]), int(d["height"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{source}: camera entry needs name/width/height/K/w2c ({e})") from None
    if K.shape != (3, 3) or w2c.shape != (4, 4):
        raise ValueError(f"{source}: K must be 3x3 and w2c 4x4, got {K.shape} and {w2c.shape}")
    if not (np.isfinite(K).all() and np.isfinite(w2c).all()):
        raise ValueError(f"{source}: camera {d.get('name', '?')} has non-finite values")
    if W < 1 or H < 1:
        raise ValueError(f"{source}: image size must be positive, got {W}x{H}")
    dr = d.get("depth_range")
    return Camera(K=K, w2c=w2c, width=W, height=H, name=str(d.get("name", "")),
                  depth_range=tuple(map(float, dr)) if dr is not None else None)
