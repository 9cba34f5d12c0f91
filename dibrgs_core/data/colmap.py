"""COLMAP models (text or binary) as :class:`~dibrgs_core.data.levir.Scene`, through pycolmap.

Accepted layouts (the first that holds ``cameras.bin`` or ``cameras.txt`` wins)::

    ROOT/sparse/0/{cameras,images,points3D}.{bin,txt}   + ROOT/images/<name>
    ROOT/sparse/{cameras,images,points3D}.{bin,txt}     + ROOT/images/<name>
    ROOT/{cameras,images,points3D}.{bin,txt}            + ROOT/images/<name>

COLMAP poses are world-to-camera with OpenCV axes and pixel centres at +0.5,
the project's own convention, so they are taken over unchanged. Only
undistorted pinhole cameras are accepted (distortion parameters all 0):
run ``colmap image_undistorter`` first otherwise. View ids are the image file
stems; the split follows :func:`~dibrgs_core.data.levir.default_split`.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..common.errors import InputError
from .scene import Scene, View, make_split, validate_camera_arrays
from .images import read_image

log = logging.getLogger("dibrgs.io_colmap")

_PINHOLE_LIKE = {"SIMPLE_PINHOLE", "PINHOLE"}
# Perspective models that are pinholes when their distortion parameters are all 0.
_DISTORTED_PINHOLE = {"SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"}


def find_colmap_model(root: str | Path) -> Path | None:
    """The folder holding the COLMAP model under ``root``, or None."""
    root = Path(root)
    for d in (root / "sparse" / "0", root / "sparse", root):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def _camera_K(cam, where: Path) -> np.ndarray:
    """3x3 K of a pycolmap camera; InputError for fisheye models or non-zero distortion."""
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    if model not in _PINHOLE_LIKE:
        if model not in _DISTORTED_PINHOLE:
            raise InputError(where, f"camera {cam.camera_id}: model {model} is not a pinhole model")
        extra = np.asarray(cam.params, dtype=np.float64)[list(cam.extra_params_idxs())]
        if np.any(extra != 0):
            raise InputError(where, f"camera {cam.camera_id}: model {model} has distortion {extra.tolist()}; "
                                    "undistort the images first (colmap image_undistorter)")
    return np.asarray(cam.calibration_matrix(), dtype=np.float64)


def read_colmap_cameras(root: str | Path) -> list[Camera]:
    """Posed cameras of a COLMAP model (sorted by image name), without images."""
    rec, model_dir = _load(root)
    return [c for c, _ in _cameras(rec, model_dir)]


def _load(root: str | Path):
    import pycolmap

    root = Path(root)
    if not root.exists():
        raise InputError(root, "COLMAP folder not found")
    model_dir = find_colmap_model(root)
    if model_dir is None:
        raise InputError(root, "no COLMAP model (cameras.bin/.txt in sparse/0, sparse/ or the folder)")
    for stem in ("images", "points3D"):
        if not any((model_dir / f"{stem}{e}").is_file() for e in (".bin", ".txt")):
            raise InputError(model_dir / f"{stem}.bin", "COLMAP model file missing")
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises plain exceptions for corrupt models
        raise InputError(model_dir, f"unreadable COLMAP model ({type(e).__name__}: {e})") from None
    return rec, model_dir


def _cameras(rec, model_dir: Path) -> list[tuple[Camera, str]]:
    out: list[tuple[Camera, str]] = []
    seen: dict[str, str] = {}
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        if not img.has_pose:
            log.warning("%s: image %s has no pose, skipped", model_dir, img.name)
            continue
        cam = rec.cameras[img.camera_id]
        K = _camera_K(cam, model_dir)
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(img.cam_from_world().matrix(), dtype=np.float64)
        validate_camera_arrays(w2c, K, None, model_dir)
        vid = Path(img.name).stem
        if vid in seen:
            raise InputError(model_dir, f"images {seen[vid]} and {img.name} share the view id {vid!r}")
        seen[vid] = img.name
        out.append((Camera(K=K, w2c=w2c, width=cam.width, height=cam.height, name=vid), img.name))
    if not out:
        raise InputError(model_dir, "COLMAP model has no posed images")
    return out


def read_colmap_scene(root: str | Path, train_ids: Iterable[str] | None = None,
                      test_ids: Iterable[str] | None = None) -> Scene:
    """Read a COLMAP model and its images (``ROOT/images/``) as a :class:`Scene` (no depth)."""
    root = Path(root)
    rec, model_dir = _load(root)
    img_dir = next((d for d in (root / "images", root / "Images", model_dir.parent / "images")
                    if d.is_dir()), None)
    if img_dir is None:
        raise InputError(root / "images", "image folder not found")
    views: dict[str, View] = {}
    for cam, name in _cameras(rec, model_dir):
        path = img_dir / name
        if not path.is_file():
            raise InputError(path, "image file missing (listed in the COLMAP model)")
        image = read_image(path)
        h, w = image.shape[:2]
        if (w, h) != (cam.width, cam.height):
            raise InputError(path, f"image is {w}x{h} but its COLMAP camera is {cam.width}x{cam.height}")
        views[cam.name] = View(camera=cam, image=image)
    sizes = {(v.camera.width, v.camera.height) for v in views.values()}
    if len(sizes) > 1:
        raise InputError(img_dir, f"images have different sizes: {sorted(sizes)}")
    ids = sorted(views)
    views = {k: views[k] for k in ids}
    try:
        train, test = make_split(root, ids, train_ids, test_ids)
    except ValueError as e:
        raise InputError(root, str(e)) from None
    log.info("read COLMAP model %s: %d views, train %s", model_dir, len(views), train)
    return Scene(root=root, views=views, track=[], train=train, test=test)


def write_colmap_model(cams: Sequence[Camera], out_dir: str | Path, binary: bool = True,
                       points: np.ndarray | None = None, colors: np.ndarray | None = None) -> Path:
    """Write cameras (one PINHOLE camera each, image name ``<name>.png``) and optional
    3D points (no tracks) as a COLMAP model in ``out_dir``."""
    import pycolmap

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    for i, c in enumerate(cams, start=1):
        if abs(c.K[0, 1]) > 1e-12:
            raise ValueError(f"camera {c.name}: COLMAP pinhole cameras have no skew")
        cam = pycolmap.Camera(model="PINHOLE", width=c.width, height=c.height,
                              params=[c.fx, c.fy, c.cx, c.cy], camera_id=i)
        rec.add_camera_with_trivial_rig(cam)
        img = pycolmap.Image(name=f"{c.name or f'{i:03d}'}.png", camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(c.w2c[:3, :4]))
    if points is not None:
        cols = np.zeros((len(points), 3), np.uint8) if colors is None else np.asarray(colors, np.uint8)
        for p, col in zip(np.asarray(points, np.float64), cols):
            rec.add_point3D(p, pycolmap.Track(), col)
    (rec.write_binary if binary else rec.write_text)(str(out_dir))
    return out_dir
