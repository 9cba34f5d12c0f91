"""Undistorting photos of COLMAP cameras with lens distortion, through pycolmap, cached by content.

COLMAP's perspective models with distortion (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``,
``FULL_OPENCV``) become ``PINHOLE`` cameras: :func:`pycolmap.undistort_camera` chooses the
pinhole (COLMAP's ``image_undistorter`` defaults: no blank pixels, scale in [0.2, 2]) and
:func:`pycolmap.undistort_image` resamples the photo (8-bit, as COLMAP's own undistorter).
Fisheye and other non-perspective models are refused: their undistorted views would need far
larger images or lose the field of view's edge, so the user decides (``colmap image_undistorter``).

Cache: ``$DIBRGS_CACHE/undistorted/<digest>.npy`` (default ``~/.cache/dibrgs``), the digest
taken over the photo file's bytes, the camera model and parameters, the undistortion options and
the orientation used, so an edited photo or camera never reuses an old result. A cache that
cannot be written is skipped with a warning.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..common.colmap_lib import import_pycolmap
from ..common.digest import Digest, file_digest
from ..common.errors import InputError
from ..common.fileio import atomic_path
from .images import fill_no_data

log = logging.getLogger("dibrgs.undistort")

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
#: Perspective models with distortion that are undistorted on load.
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_VERSION = "undistort/2"


def model_name(cam) -> str:
    return cam.model.name if hasattr(cam.model, "name") else str(cam.model)


def distortion(cam) -> np.ndarray:
    """The distortion parameters of a pycolmap camera (empty for pinholes)."""
    return np.asarray(cam.params, dtype=np.float64)[list(cam.extra_params_idxs())]


def check_model(cam, where: Path) -> bool:
    """Whether ``cam`` needs undistortion; ``InputError`` for models that are not perspective."""
    model = model_name(cam)
    if model in PINHOLE_MODELS:
        return False
    if model not in DISTORTED_MODELS:
        raise InputError(where, unsupported_model(cam.camera_id, model))
    return bool(np.any(distortion(cam) != 0))


def unsupported_model(camera_id: int, model: str) -> str:
    """Why camera ``camera_id`` of COLMAP model ``model`` (neither pinhole nor in ``DISTORTED_MODELS``)
    is refused: the one message of the library's reader and the add-on's."""
    kind = "a fisheye model" if "FISHEYE" in model or model in ("FOV", "EUCM") else "not a perspective model"
    return (f"camera {camera_id}: {model} is {kind}; only pinhole models and {', '.join(DISTORTED_MODELS)} "
            "(undistorted on load) are supported: undistort the photos first (colmap image_undistorter)")


def _options():
    pycolmap = import_pycolmap()

    return pycolmap.UndistortCameraOptions()


def undistorted_camera(cam):
    """The pinhole pycolmap camera the undistorted photos of ``cam`` have."""
    pycolmap = import_pycolmap()

    return pycolmap.undistort_camera(_options(), cam)


def cache_dir() -> Path:
    return Path(os.environ.get("DIBRGS_CACHE", Path.home() / ".cache" / "dibrgs")) / "undistorted"


@dataclass
class Undistorted:
    """An undistorted photo: float32 (H, W, 3) RGB in [0, 1], bool (H, W) valid pixels (None when all
    are) and its pinhole pycolmap camera."""

    image: np.ndarray
    valid: np.ndarray | None
    camera: object


def undistort_photo(path: Path, cam, oriented: bool, read: Callable[[], tuple[np.ndarray, np.ndarray | None]],
                    mask: Path | None = None) -> Undistorted:
    """The undistorted photo at ``path`` taken with pycolmap camera ``cam``; ``read()`` gives the
    photo (float RGB in [0, 1], in the pixel order the camera describes) and its valid pixels when
    it is not cached; ``mask``, the mask file those come from, if any (part of the cache key). A
    pixel of the undistorted photo is valid when every photo pixel it is drawn from is."""
    pycolmap = import_pycolmap()

    out_cam = undistorted_camera(cam)
    key = (Digest(_VERSION).text(file_digest(path)).text("" if mask is None else file_digest(mask))
           .text(model_name(cam)).array(np.asarray(cam.params, np.float64))
           .json([cam.width, cam.height, bool(oriented), _options().todict()]).hex())
    cached = cache_dir() / f"{key}.npy"
    if cached.is_file():
        try:
            a = np.load(cached, allow_pickle=False)
            if a.shape[:2] == (out_cam.height, out_cam.width) and a.shape[2] in (3, 4) and a.dtype == np.uint8:
                return _undistorted(a, out_cam)
        except (OSError, ValueError) as e:
            log.warning("%s: unreadable cache entry, recomputing (%s)", cached, e)
    image, valid = read()
    if image.shape[:2] != (cam.height, cam.width):
        raise InputError(path, f"image is {image.shape[1]}x{image.shape[0]} but its COLMAP camera is "
                               f"{cam.width}x{cam.height}")

    def undistorted(u8: np.ndarray) -> np.ndarray:
        bitmap, _ = pycolmap.undistort_image(_options(), pycolmap.Bitmap.from_array(np.ascontiguousarray(u8)), cam)
        return np.asarray(bitmap.to_array(), dtype=np.uint8).reshape(out_cam.height, out_cam.width, -1)

    a = undistorted(np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8))[..., :3]
    if valid is not None:  # alpha 255 where every source pixel of the bilinear resampling is valid
        a = np.concatenate([a, np.where(undistorted(valid.astype(np.uint8) * 255)[..., :1] == 255, 255, 0)
                            .astype(np.uint8)], axis=2)
    try:
        with atomic_path(cached) as tmp:
            with open(tmp, "wb") as f:
                np.save(f, np.ascontiguousarray(a), allow_pickle=False)
    except (OSError, InputError) as e:
        log.warning("cannot cache the undistorted %s in %s (%s); continuing without the cache", path.name,
                    cached.parent, e)
    return _undistorted(a, out_cam)


def _undistorted(a: np.ndarray, out_cam) -> Undistorted:
    """An :class:`Undistorted` of uint8 (H, W, 3) RGB or (H, W, 4) RGB and validity (alpha 255)."""
    valid = None if a.shape[2] == 3 or (a[..., 3] == 255).all() else a[..., 3] == 255
    image = a[..., :3].astype(np.float32) / 255.0
    return Undistorted(fill_no_data(image, valid), valid, out_cam)
