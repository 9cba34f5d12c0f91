"""Exact conversion between OpenCV cameras and Blender camera parameters.

Blender: the camera looks down its local -Z with +Y up, ``matrix_world`` is
*camera-to-world*; intrinsics are the focal length and sensor size in
millimetres with a sensor fit, a lens shift in units of the fitted sensor
dimension, and a pixel aspect ratio. NumPy only (the add-on applies the
parameters with bpy).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .frame import overlap_distance
from .pinhole import Camera, rigid_inverse


# OpenCV camera axes -> Blender camera axes (flip y and z); its own inverse.
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


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


#: Blender's own camera clip range (start, end), for cameras of unknown depth range and scale.
DEFAULT_CLIP = (0.1, 1000.0)


def clip_range(cams: Sequence[Camera]) -> tuple[float, float]:
    """Clip start and end for cameras without a depth range (COLMAP, transforms.json): 1/100 and
    100 x :func:`.frame.overlap_distance`, in the scene's units (Blender's 0.1-1000 cuts away a
    model in millimetres or kilometres); :data:`DEFAULT_CLIP` without two camera positions."""
    cams = list(cams)
    if len(cams) < 2 or not np.ptp(np.stack([c.center for c in cams]), axis=0).any():
        return DEFAULT_CLIP
    d = overlap_distance(cams)
    return d / 100.0, d * 100.0


def to_blender(cam: Camera, sensor_width: float = 36.0, sensor_fit: str = "AUTO",
               clip: tuple[float, float] | None = None) -> BlenderCameraParams:
    """Convert an OpenCV camera to Blender camera parameters (exact).

    ``fx != fy`` is expressed with the pixel aspect ratio (fy/fx = pax/pay);
    an off-centre principal point with the lens shift. Skew is not
    representable in Blender and raises. The clip range is the camera's depth range, else ``clip``
    (:func:`clip_range`), else :data:`DEFAULT_CLIP`.
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
    near, far = cam.depth_range if cam.depth_range else (clip or DEFAULT_CLIP)
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
