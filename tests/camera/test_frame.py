"""The scene frame cameras imply: one near-nadir test with its thresholds as arguments."""
from __future__ import annotations

import numpy as np

from dibrgs_core.camera.frame import MAX_NADIR_DEG, central_camera, near_nadir
from dibrgs_core.camera.pinhole import Camera, look_at


def _ring(off_nadir_deg: float, n: int = 6, height: float = 100.0) -> list[Camera]:
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    r = height * np.tan(np.radians(off_nadir_deg))
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([r * np.cos(a), r * np.sin(a), height])
        out.append(Camera(K, look_at(eye, np.zeros(3), [0, 0, 1.0]), 64, 64, name=f"{k:03d}"))
    return out


def test_near_nadir_follows_its_thresholds():
    cams = _ring(30.0)
    ok, why = near_nadir(cams)
    assert ok and "30.0 deg" in why
    assert near_nadir(cams, max_nadir_deg=25.0) == (False, near_nadir(cams, max_nadir_deg=25.0)[1])
    assert "not near-nadir" in near_nadir(cams, max_nadir_deg=25.0)[1]
    assert not near_nadir(_ring(MAX_NADIR_DEG + 5))[0]
    # Cameras looking at each other from opposite sides of a horizon: no clear up axis.
    ok, why = near_nadir(_ring(89.0, n=2), max_nadir_deg=90.0)
    assert not ok and "ambiguous" in why
    assert near_nadir(_ring(89.0, n=2), max_nadir_deg=90.0, min_up_confidence=0.0)[0]


def test_central_camera_is_the_one_nearest_the_mean_centre():
    cams = _ring(20.0)
    cams.append(Camera(cams[0].K, look_at([0.0, 0.0, 100.0], np.zeros(3), [0, 1.0, 0]), 64, 64, name="mid"))
    assert central_camera(cams).name == "mid"
