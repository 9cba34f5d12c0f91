"""Scenes in the ``transforms.json`` layout of instant-ngp and nerfstudio (also written by
Blender's NeRF exporters and by nerfstudio's converters from Metashape, RealityCapture, ODM and
COLMAP), parsed with numpy and the standard library (the library's reader and the add-on's
description share it).

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
on load as COLMAP's (``OPENCV`` / ``FULL_OPENCV``); fisheye and other models are refused. ``file_path`` is relative to the JSON's folder, with or without the
photo's extension. Photos keep their stored pixel order (as the layout's tools read them) unless
only the upright photo fits the given size. A frame's ``mask_path`` (nerfstudio's: black pixels are
left out) or a mask in ``masks/`` beside the photos marks pixels without data.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Iterable

import numpy as np

from ..camera.pinhole import Camera
from ..common.colmap_lib import import_pycolmap
from ..common.errors import InputError
from .colmap import read_photo
from .images import IMAGE_EXTS, find_mask, image_size, turned_to_fit
from .scene import ImageFile, Scene, View, validate_camera_arrays
from .split import make_split, view_ids
from .undistort import undistorted_camera

log = logging.getLogger("dibrgs.io_transforms")

TRANSFORMS_FILE = "transforms.json"
#: The files of a layout split in parts (Blender's synthetic NeRF scenes), in reading order.
PART_FILES = {"train": "transforms_train.json", "test": "transforms_test.json", "val": "transforms_val.json"}
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
_DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")
#: ``camera_model`` values of perspective cameras, whose distortion is k1, k2, p1, p2 (k3).
_PERSPECTIVE = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "PERSPECTIVE")


def find_transforms(root: str | Path) -> list[Path]:
    """The transforms files of a scene folder (empty when it has none)."""
    root = Path(root)
    if (root / TRANSFORMS_FILE).is_file():
        return [root / TRANSFORMS_FILE]
    parts = [root / f for f in PART_FILES.values() if (root / f).is_file()]
    return parts if (root / PART_FILES["train"]).is_file() else []


@dataclass
class Frame:
    """One photo of a transforms layout, before its size is known.

    Attributes:
        name: ``file_path`` as written (relative to the scene folder; view ids come from it).
        photo: the photo file.
        w2c: 4x4 world-to-camera, OpenCV axes.
        size: (width, height) the JSON gives, or None (the photo's own).
        intrinsics: the JSON's ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``camera_angle_x``,
            ``camera_angle_y`` (those present) and distortion ``k1`` ... ``k3``.
        part: ``"train"``, ``"test"``, ``"val"`` (from a part file) or None.
        mask: the frame's mask image (nerfstudio's ``mask_path``; else, for a photo in a folder
            (``images/x.jpg``), ``masks/x.jpg.png`` or ``masks/x.png`` beside that folder,
            :func:`~.images.find_mask`), or None.
    """

    name: str
    photo: Path
    w2c: np.ndarray
    size: tuple[int, int] | None
    intrinsics: dict[str, float]
    part: str | None
    mask: Path | None = None

    def camera_model(self, width: int, height: int) -> tuple[str, list[float]]:
        """The COLMAP camera model and parameters of this frame's camera for a photo of
        ``width`` x ``height``: ``PINHOLE`` [fx, fy, cx, cy], ``OPENCV`` [.., k1, k2, p1, p2] or
        ``FULL_OPENCV`` [.., k1, k2, p1, p2, k3, 0, 0, 0]."""
        i = self.intrinsics
        fx = i.get("fl_x")
        if fx is None:
            if "camera_angle_x" not in i:
                raise InputError(self.photo, "its camera has neither fl_x nor camera_angle_x")
            fx = 0.5 * width / math.tan(0.5 * i["camera_angle_x"])
        fy = i.get("fl_y")
        if fy is None:
            fy = 0.5 * height / math.tan(0.5 * i["camera_angle_y"]) if "camera_angle_y" in i else fx
        pin = [fx, fy, i.get("cx", width / 2.0), i.get("cy", height / 2.0)]
        k = [i.get(key, 0.0) for key in _DISTORTION_KEYS]
        if k[4]:
            return "FULL_OPENCV", pin + k + [0.0, 0.0, 0.0]
        if any(k[:4]):
            return "OPENCV", pin + k[:4]
        return "PINHOLE", pin


def read_frames(root: str | Path) -> list[Frame]:
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
    keys = ("fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y", *_DISTORTION_KEYS)
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
        photo = _photo(path.parent, name, path, k)
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


def _photo(folder: Path, name: str, where: Path, k: int) -> Path:
    """The photo ``file_path`` names: as written, or with an image extension added (Blender's
    synthetic scenes write ``./train/r_0`` for ``train/r_0.png``)."""
    p = folder / name
    if p.suffix.lower() in IMAGE_EXTS and p.is_file():
        return p
    for ext in IMAGE_EXTS + tuple(e.upper() for e in IMAGE_EXTS):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    if p.is_file():
        return p  # another extension: the image readers say whether they can read it
    raise InputError(where, f"frame {k}: photo {name} not found in {folder}")


def stored_or_upright(frame: Frame, stored: tuple[int, int], upright: tuple[int, int]) -> tuple[tuple[int, int], bool]:
    """(the view's size, whether its photo is turned upright by its EXIF orientation): the stored
    pixels unless the JSON gives a size that only the upright photo has (the layout's tools read
    the stored order, as COLMAP does)."""
    if frame.size is None:
        return stored, False
    turned = turned_to_fit(stored, upright, frame.size)
    if turned is None:
        raise InputError(frame.photo, f"image is {stored[0]}x{stored[1]} but its transforms entry says "
                                      f"{frame.size[0]}x{frame.size[1]}")
    return frame.size, turned


def layout_split(frames: list[Frame], ids: dict[str, str]) -> tuple[list[str], list[str], str] | None:
    """The split the part files give (train / test; val views are left out), or None."""
    if not any(f.part for f in frames):
        return None
    train = sorted(ids[f.name] for f in frames if f.part == "train")
    test = sorted(ids[f.name] for f in frames if f.part == "test")
    return train, test, " + ".join(PART_FILES[p] for p in ("train", "test") if any(f.part == p for f in frames))


def frames_and_ids(path: str | Path) -> tuple[list[Frame], dict[str, str]]:
    """The frames of a transforms layout's folder (or of one transforms file) and the view id of
    each frame's ``name`` (:func:`~.split.view_ids`)."""
    path = Path(path)
    frames = _read_file(path, None) if path.is_file() else read_frames(path)
    try:
        return frames, view_ids([f.name for f in frames])
    except ValueError as e:
        raise InputError(path, str(e)) from None


def read_transforms_scene(root: str | Path, train_ids: Iterable[str] | None = None,
                          test_ids: Iterable[str] | None = None) -> Scene:
    """Read a transforms layout and its photos as a :class:`~.scene.Scene` (no depth): every photo
    decoded (and undistorted: pycolmap, cached) once to check it, then left in its file."""
    root = Path(root)
    frames, ids = frames_and_ids(root)
    views: dict[str, View] = {}
    undistorted = 0
    for f in frames:
        cam, ccam, oriented = _camera(f, ids[f.name])
        pixels, got = ImageFile.checked(f.photo, partial(read_photo, f.photo, ccam, oriented, ccam is not None,
                                                         f.mask))
        if got != (cam.width, cam.height):
            raise InputError(f.photo, f"image is {got[0]}x{got[1]} but its camera is {cam.width}x{cam.height}")
        views[cam.name] = View(camera=cam, image=pixels)
        undistorted += ccam is not None
    views = {k: views[k] for k in sorted(views)}
    try:
        train, test, source = make_split(root, list(views), train_ids, test_ids, layout=layout_split(frames, ids))
    except ValueError as e:
        raise InputError(root, str(e)) from None
    log.info("read transforms layout %s: %d views (%d undistorted), train %s (split: %s)", root, len(views),
             undistorted, train, source)
    return Scene(root=root, views=views, track=[], train=train, test=test, split_source=source)


def read_transforms_cameras(path: str | Path) -> list[Camera]:
    """The cameras of a transforms layout's folder or of one transforms file (sorted by view id),
    as a scene's views have them, from the photos' headers (the pixels are not read)."""
    frames, ids = frames_and_ids(path)
    return sorted((_camera(f, ids[f.name])[0] for f in frames), key=lambda c: c.name)


def _camera(f: Frame, name: str) -> tuple[Camera, object, bool]:
    """(the view's camera - undistorted where the frame's camera has distortion -, the pycolmap
    camera of the photo when it is to be undistorted else None, whether the photo is turned upright)."""
    (W, H), oriented = stored_or_upright(f, image_size(f.photo, orient=False), image_size(f.photo, orient=True))
    model, params = f.camera_model(W, H)
    ccam = None
    if model == "PINHOLE":
        K, size = np.array([[params[0], 0.0, params[2]], [0.0, params[1], params[3]], [0.0, 0.0, 1.0]]), (W, H)
    else:
        pycolmap = import_pycolmap()

        ccam = pycolmap.Camera(model=model, width=W, height=H, params=params)
        pin = undistorted_camera(ccam)
        K, size = np.asarray(pin.calibration_matrix(), np.float64), (pin.width, pin.height)
    validate_camera_arrays(f.w2c, K, None, f.photo)
    return Camera(K=K, w2c=f.w2c, width=size[0], height=size[1], name=name), ccam, oriented
