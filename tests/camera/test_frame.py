"""The scene frame cameras imply: one near-nadir test with its thresholds as arguments."""
from __future__ import annotations

import numpy as np
import pytest

from dibrgs_core.camera.frame import MAX_NADIR_DEG, central_camera, estimate_up, near_nadir
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


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_up_of_level_cameras():
    """Level cameras at different headings fix up exactly (three views of an orbit, whose mean
    viewing direction misses it by about a degree); at one heading up stays where the viewing
    directions put it, so a camera pitched forward reads as nadir (documented: the poses cannot
    tell it from a nadir camera climbing a slope)."""
    from dibrgs_core.synth.flights import GRIDS, grid_cameras

    z = np.array([0.0, 0.0, 1.0])
    ring = _ring(15.0, n=20)
    sub = [ring[i] for i in (0, 7, 14)]
    assert _angle(-np.mean([c.view_dir for c in sub], 0), z) > 0.5
    assert _angle(estimate_up(sub)[0], z) < 1e-6
    K = ring[0].K
    # One heading (image x along +X), cameras pitched 3 deg: up keeps the pitch, across the x axis.
    side = [Camera(K, look_at([10.0 * k, 0.0, 100.0], [10.0 * k, -np.tan(np.radians(3)) * 100.0 + 0.0, 0.0],
                              [0.0, 1.0, 0.0]), 64, 64, name=f"{k:03d}") for k in range(4)]
    up, _ = estimate_up(side)
    assert abs(up[0]) < 1e-9 and _angle(up, z) == pytest.approx(3.0, abs=1e-6)
    cams, _, _ = grid_cameras(32, 0.7, np.random.default_rng(3), GRIDS["oblique"])
    assert _angle(estimate_up(cams)[0], z) > 30.0


def test_up_of_cameras_not_held_level_is_the_mean_viewing_direction():
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    rng = np.random.default_rng(0)
    rolled = []
    for k in range(6):
        eye = np.array([10.0 * k, 0.0, 100.0])
        roll = rng.uniform(-1, 1) * np.pi / 4
        w2c = look_at(eye, eye + np.array([0.3, 0.0, -1.0]), [np.cos(roll), np.sin(roll), 0.0])
        rolled.append(Camera(K, w2c, 64, 64, name=f"{k:03d}"))
    mean_up = -np.mean([c.view_dir for c in rolled], 0)
    assert _angle(estimate_up(rolled)[0], mean_up) < 1e-9
