"""JSON camera lists, as ``dibrgs render --cameras``, ``dibrgs train --pseudo-path`` and the
Blender add-on exchange them: ``[{"name", "width", "height", "K", "w2c", "depth_range"?}]``
(``K`` in pixels, ``w2c`` world-to-camera with OpenCV axes). NumPy only.
"""
from __future__ import annotations

import numpy as np

from .pinhole import Camera


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
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{source}: camera entry needs name/width/height/K/w2c ({e})") from None
    if K.shape != (3, 3) or w2c.shape != (4, 4):
        raise ValueError(f"{source}: K must be 3x3 and w2c 4x4, got {K.shape} and {w2c.shape}")
    if not (np.isfinite(K).all() and np.isfinite(w2c).all()):
        raise ValueError(f"{source}: camera {d.get('name', '?')} has non-finite values")
    if W < 1 or H < 1:
        raise ValueError(f"{source}: image size must be positive, got {W}x{H}")
    dr = d.get("depth_range")
    if dr is not None:
        try:
            dr = tuple(float(v) for v in dr)
        except (TypeError, ValueError):
            dr = ()
        if len(dr) != 2:
            raise ValueError(f"{source}: camera {d.get('name', '?')}: depth_range must be two numbers (near, far)")
    return Camera(K=K, w2c=w2c, width=W, height=H, name=str(d.get("name", "")), depth_range=dr)
