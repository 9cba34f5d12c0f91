"""The scene model every reader fills: views (camera, image, optional depth), a render track and
the train/test split; camera validation shared by the readers.

Cameras are :class:`~dibrgs_core.camera.pinhole.Camera` (OpenCV axes, world-to-camera);
images float32 RGB in [0, 1]; depth z-depth in world units (0 = unknown).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..common.errors import InputError


@dataclass
class View:
    """One input view.

    Attributes:
        camera: the view's camera (its ``name`` is the view id, e.g. ``"001"``).
        image: float32 (H, W, 3) RGB in [0, 1] (sRGB-encoded values as stored).
        depth: optional float32 (H, W) z-depth in world units; 0 where unknown.
    """

    camera: Camera
    image: np.ndarray
    depth: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.camera.name


@dataclass
class Scene:
    """A multi-view scene with its train/test split.

    Attributes:
        root: the folder it was read from.
        views: view id -> :class:`View`, sorted by id.
        track: render-path cameras (may be empty).
        train, test: view ids of the split.
    """

    root: Path
    views: dict[str, View]
    track: list[Camera] = field(default_factory=list)
    train: list[str] = field(default_factory=list)
    test: list[str] = field(default_factory=list)

    def train_views(self) -> list[View]:
        return [self.views[i] for i in self.train]

    def test_views(self) -> list[View]:
        return [self.views[i] for i in self.test]

    @property
    def cameras(self) -> list[Camera]:
        """Cameras of all views, sorted by id."""
        return [v.camera for v in self.views.values()]

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) shared by all views."""
        c = next(iter(self.views.values())).camera
        return c.width, c.height


def orbit_ids(ids: Sequence[str]) -> list[str]:
    """The orbit views among ``ids``: all but the near-nadir view 000 of a 21-view LEVIR scene."""
    ids = sorted(ids)
    if len(ids) == 21 and ids[0] == "000":
        return ids[1:]
    return list(ids)


def default_split(ids: Sequence[str], n_train: int = 3) -> tuple[list[str], list[str]]:
    """LEVIR-NVS sparse-view protocol: ``n_train`` evenly spaced orbit views
    (indices ceil(i * n / n_train): 0, 7, 14 of 20) train, the other orbit views test."""
    orbit = orbit_ids(ids)
    if len(orbit) < 2:
        raise ValueError("need at least 2 orbit views for a train/test split")
    n_train = min(n_train, len(orbit) - 1)
    idx = sorted({math.ceil(i * len(orbit) / n_train) for i in range(n_train)})
    train = [orbit[i] for i in idx]
    return train, [i for i in orbit if i not in train]


def make_split(root: Path, ids: Sequence[str], train_ids: Iterable[str] | None,
               test_ids: Iterable[str] | None = None) -> tuple[list[str], list[str]]:
    """Train/test ids: the default protocol, or the given train ids (test = the other orbit views)."""
    if train_ids is None:
        if test_ids is not None:
            raise ValueError("test_ids needs train_ids")
        return default_split(ids)
    train = [_norm_id(i) for i in train_ids]
    missing = [i for i in train if i not in ids]
    if missing:
        raise InputError(root, f"train views {missing} not in the scene (views: {', '.join(ids)})")
    if test_ids is None:
        test = [i for i in orbit_ids(ids) if i not in train]
    else:
        test = [_norm_id(i) for i in test_ids]
        missing = [i for i in test if i not in ids]
        if missing:
            raise InputError(root, f"test views {missing} not in the scene")
    return train, test


def _norm_id(i: str | int) -> str:
    """Accept 8 or "8" or "008" for view 008."""
    s = str(i)
    return f"{int(s):03d}" if s.isdigit() and len(s) < 3 else s


def validate_camera_arrays(w2c: np.ndarray, K: np.ndarray, depth_range: tuple[float, float] | None,
                           path: Path | None) -> None:
    """Raise InputError unless w2c is a finite rigid transform and K a finite upper-triangular pinhole."""
    if not (np.isfinite(w2c).all() and np.isfinite(K).all()):
        raise InputError(path, "camera has NaN or infinite values")
    if depth_range is not None and not all(map(math.isfinite, depth_range)):
        raise InputError(path, f"depth range {depth_range} is not finite")
    if not np.allclose(w2c[3], [0, 0, 0, 1], atol=1e-6):
        raise InputError(path, f"extrinsic last row must be 0 0 0 1, got {w2c[3].tolist()}")
    R = w2c[:3, :3]
    det = float(np.linalg.det(R))
    if abs(det) < 1e-6:
        raise InputError(path, f"extrinsic rotation is singular (det {det:.3g})")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or det < 0:
        raise InputError(path, f"extrinsic rotation is not a rotation (det {det:.4g}, R R^T != I)")
    if abs(float(np.linalg.det(K))) < 1e-12 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"intrinsic matrix is singular or has non-positive focal length: {K.tolist()}")
    if not np.allclose(K[2], [0, 0, 1], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise InputError(path, f"intrinsic matrix must be upper-triangular with last row 0 0 1: {K.tolist()}")
