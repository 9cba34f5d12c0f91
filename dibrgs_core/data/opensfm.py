"""Scenes as OpenDroneMap and OpenSfM leave them (``reconstruction.json``), parsed with the standard
library into the frames :mod:`.frame_layouts` makes a scene of (the library's reader and the
add-on's description share both).

Accepted layouts: an ODM project folder (``opensfm/reconstruction.json``, photos in ``images/``) or
an OpenSfM dataset folder (``reconstruction.json`` beside ``images/``). The file holds a list of
reconstructions (OpenSfM writes one a part of the flight it could join); the one with the most
shots is read and the log lists them. Masks as OpenDroneMap takes them (``NAME_mask.EXT`` beside
the photo) or as for COLMAP (``masks/NAME.png`` beside ``images/``).

Conventions (OpenSfM's documentation, "Geometric Models"): a shot's ``rotation`` (axis-angle,
radians) and ``translation`` take world coordinates to camera coordinates with OpenCV axes (+x
right, +y down, looking along +z); the world is topocentric metres (x east, y north, z up) when the
photos had GPS. Cameras project to normalised image coordinates, whose origin is the image centre
and whose unit is the image's larger side, so a pixel coordinate with the image spanning [0, w]
(COLMAP's convention) is ``w / 2 + max(w, h) * x``. Models: ``perspective`` (f, k1, k2),
``simple_radial`` / ``radial`` (f_x, f_y, c_x, c_y, k1 (, k2)) and ``brown`` (adds k3 and p1, p2
in OpenCV's order); fisheye, spherical and dual cameras are refused. Photos are the stored pixels
(OpenSfM's coordinates are not turned upright).
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from .images import find_mask, image_named
from .photo_frame import Frame, find_photo, layout_file

log = logging.getLogger("dibrgs.io_opensfm")

RECONSTRUCTION_FILE = "reconstruction.json"
#: Where a scene folder keeps it: an OpenSfM dataset, then an ODM project.
_PLACES = (RECONSTRUCTION_FILE, f"opensfm/{RECONSTRUCTION_FILE}")
_PERSPECTIVE = ("perspective", "simple_radial", "radial", "brown")


def find_opensfm(root: str | Path) -> Path | None:
    """The ``reconstruction.json`` of an OpenSfM dataset or ODM project folder, or None."""
    root = Path(root)
    return next((root / p for p in _PLACES if (root / p).is_file()), None)


def _rotation(rvec: np.ndarray) -> np.ndarray:
    """The rotation matrix of an axis-angle vector (Rodrigues' formula)."""
    angle = float(np.linalg.norm(rvec))
    if angle < 1e-12:
        return np.eye(3)
    k = rvec / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def _intrinsics(cam: dict, cid: str, where: Path) -> tuple[tuple[int, int], dict[str, float]]:
    """((width, height), intrinsics in pixels with OpenCV's distortion) of an OpenSfM camera."""
    kind = str(cam.get("projection_type", "perspective"))
    if kind not in _PERSPECTIVE:
        raise InputError(where, f"camera {cid}: projection {kind} is not supported (perspective cameras are: "
                                f"{', '.join(_PERSPECTIVE)}; undistort fisheye and spherical photos first)")

    def number(key: str, default: float | None = 0.0) -> float:
        v = cam.get(key, default)
        if v is None or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(where, f"camera {cid}: {key} must be a finite number, got {v!r}")
        return float(v)

    w, h = int(number("width", None)), int(number("height", None))
    if w <= 0 or h <= 0:
        raise InputError(where, f"camera {cid}: width and height must be positive, got {w}x{h}")
    size = max(w, h)
    if kind == "perspective":
        fx = fy = number("focal", None)
        cx = cy = 0.0
    else:
        fx, fy = number("focal_x", None), number("focal_y", None)
        cx, cy = number("c_x"), number("c_y")
    if fx <= 0.0 or fy <= 0.0:
        raise InputError(where, f"camera {cid}: focal length must be positive, got {fx}, {fy}")
    out = {"fl_x": fx * size, "fl_y": fy * size, "cx": 0.5 * w + cx * size, "cy": 0.5 * h + cy * size,
           "k1": number("k1"), "k2": number("k2")}
    if kind == "brown":
        out.update(k3=number("k3"), p1=number("p1"), p2=number("p2"))
    return (w, h), out


def _largest(data: object, where: Path) -> dict:
    if not isinstance(data, list) or not data or not all(isinstance(r, dict) for r in data):
        raise InputError(where, "expected a list of reconstructions (objects with \"cameras\" and \"shots\")")
    sizes = [len(r["shots"]) if isinstance(r.get("shots"), dict) else 0 for r in data]
    best = int(np.argmax(sizes))
    if len(data) > 1:
        log.info("%s: %d reconstructions (%s shots), reading the largest", where, len(data),
                 ", ".join(map(str, sizes)))
    return data[best]


def read_opensfm_frames(path: str | Path) -> list[Frame]:
    """The frames of an OpenSfM ``reconstruction.json``, or of the one in a scene folder
    (InputError naming the file when malformed, or a shot's photo when it is missing)."""
    path = Path(path)
    path = layout_file(path, find_opensfm, f"no {RECONSTRUCTION_FILE} (or opensfm/{RECONSTRUCTION_FILE})")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"unreadable reconstruction file ({e})") from None
    rec = _largest(data, path)
    cameras, shots = rec.get("cameras"), rec.get("shots")
    if not isinstance(cameras, dict) or not isinstance(shots, dict) or not shots:
        raise InputError(path, "the reconstruction has no shots")
    # the photos: beside the file (a dataset), else in the project above opensfm/ (ODM)
    folder = next((d / "images" for d in (path.parent, path.parent.parent) if (d / "images").is_dir()), None)
    if folder is None:
        raise InputError(path.parent / "images", "image folder not found")
    intrinsics = {}
    frames = []
    for name, shot in sorted(shots.items()):
        cid = shot.get("camera") if isinstance(shot, dict) else None
        if not isinstance(cid, str) or cid not in cameras:
            raise InputError(path, f"shot {name}: camera {cid!r} is not in the reconstruction")
        if cid not in intrinsics:
            if not isinstance(cameras[cid], dict):
                raise InputError(path, f"camera {cid}: expected an object")
            intrinsics[cid] = _intrinsics(cameras[cid], cid, path)
        size, intr = intrinsics[cid]
        try:
            r = np.asarray(shot["rotation"], np.float64)
            t = np.asarray(shot["translation"], np.float64)
        except (KeyError, TypeError, ValueError):
            raise InputError(path, f"shot {name}: needs rotation and translation (three numbers each)") from None
        if r.shape != (3,) or t.shape != (3,) or not (np.isfinite(r).all() and np.isfinite(t).all()):
            raise InputError(path, f"shot {name}: rotation and translation must be three finite numbers each")
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = _rotation(r), t
        photo = find_photo(folder, name, path, f"shot {name}")
        rel = photo.relative_to(folder).as_posix()
        frames.append(Frame(name=rel, photo=photo, w2c=w2c, size=size, intrinsics=dict(intr), part=None,
                            mask=find_mask(folder, rel) or _odm_mask(photo)))
    return frames


def _odm_mask(photo: Path) -> Path | None:
    """OpenDroneMap's mask of a photo: ``NAME_mask.EXT`` beside it (any image extension), or None."""
    return image_named(photo.parent, f"{photo.stem}_mask")
