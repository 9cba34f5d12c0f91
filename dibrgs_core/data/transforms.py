"""Scenes in the ``transforms.json`` layout of instant-ngp and nerfstudio (also written by
Blender's NeRF exporters and by nerfstudio's converters from Metashape, RealityCapture, ODM and
COLMAP), parsed with numpy and the standard library into the frames :mod:`.frame_layouts` makes a
scene of (the library's reader and the add-on's description share both).

Accepted layouts: ``ROOT/transforms.json``, or ``ROOT/transforms_train.json`` with
``transforms_test.json`` (and ``transforms_val.json``), whose parts give the split when neither
``--train`` / ``--test`` nor ``split.json`` do.

Conventions (the layout's own): ``transform_matrix`` is camera-to-world with OpenGL camera axes
(+x right, +y up, looking along -z), turned here into the project's world-to-camera with OpenCV
axes. Intrinsics ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` (pixels, the principal point
in COLMAP's convention: the image spans [0, w]) at the top level or per frame; without focal
lengths, ``camera_angle_x`` (and ``camera_angle_y``) in radians give them from the width; without a
principal point, the image centre. Distortion ``k1``, ``k2``, ``p1``, ``p2`` (``k3``) of a
perspective ``camera_model`` (``OPENCV``, the default, or a pinhole or radial one) is undistorted
on load as COLMAP's (``OPENCV`` / ``FULL_OPENCV``); fisheye and other models are refused.
``file_path`` is relative to the JSON's folder, with or without the photo's extension. Photos keep
their stored pixel order (as the layout's tools read them) unless only the upright photo fits the
given size. A frame's ``mask_path`` (nerfstudio's: black pixels are left out) or a mask in
``masks/`` beside the photos marks pixels without data.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from .images import find_mask
from .photo_frame import DISTORTION_KEYS, Frame, find_photo

TRANSFORMS_FILE = "transforms.json"
#: The files of a layout split in parts (Blender's synthetic NeRF scenes), in reading order.
PART_FILES = {"train": "transforms_train.json", "test": "transforms_test.json", "val": "transforms_val.json"}
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
#: ``camera_model`` values of perspective cameras, whose distortion is k1, k2, p1, p2 (k3).
_PERSPECTIVE = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "PERSPECTIVE")


def find_transforms(root: str | Path) -> list[Path]:
    """The transforms files of a scene folder (empty when it has none)."""
    root = Path(root)
    if (root / TRANSFORMS_FILE).is_file():
        return [root / TRANSFORMS_FILE]
    parts = [root / f for f in PART_FILES.values() if (root / f).is_file()]
    return parts if (root / PART_FILES["train"]).is_file() else []


def read_transforms_frames(root: str | Path) -> list[Frame]:
    """The frames of the transforms layout in ``root`` (InputError naming the file when malformed)."""
    root = Path(root)
    files = find_transforms(root)
    if not files:
        raise InputError(root, f"no {TRANSFORMS_FILE} (or {PART_FILES['train']})")
    frames: list[Frame] = []
    for f in files:
        part = next((k for k, v in PART_FILES.items() if f.name == v), None)
        frames += _read_file(f, part)
    if not frames:
        raise InputError(files[0], "no frames")
    return frames


def read_transforms_file(path: str | Path) -> list[Frame]:
    """The frames of one transforms file (its part, if any, not taken as a split)."""
    return _read_file(Path(path), None)


def _number(d: dict, key: str, where: Path, k: int | None) -> float | None:
    if key not in d or d[key] is None:
        return None
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(where, f"{'' if k is None else f'frame {k}: '}{key} must be a finite number, got {v!r}")
    return float(v)


def _read_file(path: Path, part: str | None) -> list[Frame]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"unreadable transforms file ({e})") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise InputError(path, "expected an object with a \"frames\" list")
    model = str(data.get("camera_model", "OPENCV")).upper()
    if model not in _PERSPECTIVE:
        raise InputError(path, f"camera_model {model} is not supported (perspective cameras are: "
                               f"{', '.join(_PERSPECTIVE)}; undistort fisheye and equirectangular photos first)")
    keys = ("fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y", *DISTORTION_KEYS)
    top = {key: v for key in keys if (v := _number(data, key, path, None)) is not None}
    if _number(data, "k4", path, None) or any(isinstance(fr, dict) and _number(fr, "k4", path, k)
                                              for k, fr in enumerate(data["frames"])):
        raise InputError(path, "k4 is a fisheye coefficient (OPENCV_FISHEYE): undistort the photos first")
    size = (_number(data, "w", path, None), _number(data, "h", path, None))
    out = []
    for k, fr in enumerate(data["frames"]):
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise InputError(path, f"frame {k}: needs file_path and transform_matrix")
        if str(fr.get("camera_model", model)).upper() not in _PERSPECTIVE:
            raise InputError(path, f"frame {k}: camera_model {fr['camera_model']} is not supported")
        intr = dict(top)
        intr.update({key: v for key in keys if (v := _number(fr, key, path, k)) is not None})
        w, h = (_number(fr, "w", path, k) or size[0]), (_number(fr, "h", path, k) or size[1])
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(path, f"frame {k}: transform_matrix is not a matrix of numbers") from None
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise InputError(path, f"frame {k}: transform_matrix must be a finite 4x4 (or 3x4) matrix")
        c2w = m @ _OPENGL_TO_OPENCV
        R, C = c2w[:3, :3], c2w[:3, 3]
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R.T, -R.T @ C
        name = str(fr["file_path"]).replace("\\", "/")
        photo = find_photo(path.parent, name, path, f"frame {k}")
        # as COLMAP names masks: beside the photos' folder (the path's first part), by the rest
        parts = Path(_strip_dot(name)).parts
        mask = find_mask(path.parent / parts[0], photo.relative_to(path.parent / parts[0]).as_posix()) \
            if len(parts) > 1 and photo.is_relative_to(path.parent / parts[0]) else None
        if fr.get("mask_path") is not None:
            mask = path.parent / str(fr["mask_path"]).replace("\\", "/")
            if not mask.is_file():
                raise InputError(path, f"frame {k}: mask_path {fr['mask_path']} not found in {path.parent}")
        out.append(Frame(name=_strip_dot(name), photo=photo, w2c=w2c, size=(int(w), int(h)) if w and h else None,
                         intrinsics=intr, part=part, mask=mask))
    return out


def _strip_dot(name: str) -> str:
    return name[2:] if name.startswith("./") else name
