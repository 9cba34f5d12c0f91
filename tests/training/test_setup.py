"""Building a method from the scene: the 3DGS baseline's random points."""
from __future__ import annotations

import numpy as np

from dibrgs_core.camera.frame import look_at_target
from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.training.setup import random_init


def _grid(tilt_deg: float, rng: np.random.Generator, height: float = 5.0) -> list[Camera]:
    """A 3x3 nadir mapping grid at ``height`` over the ground z = 0, each camera tilted by up to
    ``tilt_deg`` in a random direction (a drone's gimbal)."""
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    out = []
    for i in range(3):
        for j in range(3):
            eye = np.array([2.0 * i, 1.5 * j, height])
            off = np.tan(np.radians(tilt_deg)) * height * rng.uniform(-1, 1, 2)
            out.append(Camera(K, look_at(eye, [eye[0] + off[0], eye[1] + off[1], 0.0], [0, 1.0, 0]), 64, 48,
                              name=f"{3 * i + j:03d}"))
    return out


def test_random_points_of_a_mapping_grid_lie_on_its_ground():
    """Nearly parallel axes meet anywhere (their least-squares point is far off the ground);
    the random points are put around where the axes meet the SfM points' ground instead."""
    rng = np.random.default_rng(3)
    cams = _grid(1.0, rng)
    ground_pts = np.c_[rng.uniform(-1, 5, (400, 2)), rng.normal(0, 0.05, 400)]
    naive = look_at_target(cams)
    assert abs(naive[2]) > 2.0  # what the old box was centred on
    pts, cols = random_init(cams, 3000, np.random.default_rng(0), ground_pts)
    assert pts.shape == (3000, 3) and np.all(np.isfinite(pts)) and np.allclose(cols, 0.5)
    assert abs(np.median(pts[:, 2])) < 0.2 and np.abs(pts[:, 2]).max() < 1.5
    assert np.all(np.abs(np.median(pts[:, :2], axis=0) - [2.0, 1.5]) < 0.5)
    # An orbit's axes converge: the box is around the convergence point, no SfM points needed.
    ring = [Camera(cams[0].K, look_at([6 * np.cos(a), 6 * np.sin(a), 4.0], [1.0, -1.0, 0.0], [0, 0, 1.0]), 64, 48)
            for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    pts, _ = random_init(ring, 2000, np.random.default_rng(0))
    assert np.allclose(np.median(pts, axis=0), [1.0, -1.0, 0.0], atol=0.3)
