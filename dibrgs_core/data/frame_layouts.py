"""Scenes given as one posed camera a photo: a ``transforms.json`` (:mod:`.transforms`), a
Metashape cameras export (:mod:`.metashape`), an OpenDroneMap / OpenSfM ``reconstruction.json``
(:mod:`.opensfm`), a Meshroom / AliceVision ``cameras.sfm`` (:mod:`.meshroom`), an OpenMVG
``sfm_data.json`` (:mod:`.openmvg`), a Bundler ``bundle.out`` (:mod:`.bundler`) or RealityCapture's
XMP sidecars (:mod:`.realitycapture`). Each reader turns its
files into :class:`~.photo_frame.Frame` objects; this module makes them views, cameras and a
split, the same way for all (the library's reader and the add-on's description share it).
Distorted cameras are undistorted on load as COLMAP's (pycolmap, cached).
"""
from __future__ import annotations

import json
import logging
from functools import partial
from pathlib import Path
from typing import Callable, Iterable, Literal

import numpy as np

from ..camera.pinhole import Camera
from ..common.colmap_lib import import_pycolmap
from ..common.errors import InputError
from .bundler import find_bundler, read_bundler_frames
from .colmap import read_photo
from .images import image_size, turned_to_fit
from .meshroom import find_meshroom, is_sfm_data, read_meshroom_frames
from .metashape import find_metashape, read_metashape_frames
from .openmvg import find_openmvg, is_openmvg, read_openmvg_frames
from .opensfm import find_opensfm, read_opensfm_frames
from .photo_frame import Frame
from .realitycapture import find_realitycapture, read_realitycapture_frames
from .scene import ImageFile, Scene, View, validate_camera_arrays
from .split import make_split, view_ids
from .transforms import PART_FILES, find_transforms, read_transforms_frames, read_transforms_file
from .undistort import undistorted_camera

log = logging.getLogger("dibrgs.io_frames")

FrameLayout = Literal["transforms", "metashape", "opensfm", "meshroom", "openmvg", "bundler", "realitycapture"]


def _read_transforms(path: Path) -> list[Frame]:
    return read_transforms_file(path) if path.is_file() else read_transforms_frames(path)


#: Each frame layout's finder (a scene folder -> its file(s), or nothing) and reader (the folder or
#: one of its files -> frames), in the order a folder holding several is read (Bundler, whose lens
#: has no principal point, last).
_LAYOUTS: tuple[tuple[FrameLayout, Callable[[Path], object], Callable[[Path], list[Frame]]], ...] = (
    ("transforms", find_transforms, _read_transforms),
    ("metashape", find_metashape, read_metashape_frames),
    ("opensfm", find_opensfm, read_opensfm_frames),
    ("meshroom", find_meshroom, read_meshroom_frames),
    ("openmvg", find_openmvg, read_openmvg_frames),
    ("realitycapture", find_realitycapture, read_realitycapture_frames),
    ("bundler", find_bundler, read_bundler_frames),
)


def find_frame_layout(root: str | Path) -> FrameLayout | None:
    """Which frame layout the scene folder ``root`` holds, or None; of several, the first in
    :data:`_LAYOUTS`' order."""
    return next((name for name, find, _ in _LAYOUTS if find(Path(root))), None)


def file_layout(path: str | Path) -> FrameLayout | None:
    """The frame layout whose file ``path`` is (a Metashape XML, a RealityCapture XMP, a Bundler
    ``.out``, a Meshroom ``.sfm``, a transforms JSON: an object with "frames", an OpenSfM
    reconstruction: a list of objects with "shots", an AliceVision SfMData JSON, an OpenMVG
    SfM_Data JSON), or None (a JSON camera list, or a file no reader takes: its reader says what is
    wrong with it)."""
    path = Path(path)
    layout = {".xml": "metashape", ".xmp": "realitycapture", ".out": "bundler",
              ".sfm": "meshroom"}.get(path.suffix.lower())
    if layout is not None:
        return layout
    if path.suffix.lower() != ".json":
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if isinstance(data, dict) and "frames" in data:
        return "transforms"
    if isinstance(data, list) and data and isinstance(data[0], dict) and "shots" in data[0]:
        return "opensfm"
    if is_sfm_data(data):
        return "meshroom"
    if is_openmvg(data):
        return "openmvg"
    return None


def layout_frames(path: str | Path) -> list[Frame]:
    """The frames of a frame layout's folder, or of one of its files (a transforms JSON, a Metashape
    XML, an OpenSfM reconstruction, a Meshroom SfMData file, an OpenMVG sfm_data.json, a Bundler
    file or a RealityCapture XMP); InputError naming the file when malformed."""
    path = Path(path)
    layout = (file_layout(path) or "transforms") if path.is_file() else find_frame_layout(path)
    read = {name: read for name, _, read in _LAYOUTS}.get(layout, read_metashape_frames)
    return read(path)


def stored_or_upright(frame: Frame, stored: tuple[int, int], upright: tuple[int, int]) -> tuple[tuple[int, int], bool]:
    """(the view's size, whether its photo is turned upright by its EXIF orientation): the stored
    pixels unless the layout gives a size that only the upright photo has (the layouts' tools read
    the stored order, as COLMAP does)."""
    if frame.size is None:
        return stored, False
    turned = turned_to_fit(stored, upright, frame.size)
    if turned is None:
        raise InputError(frame.photo, f"image is {stored[0]}x{stored[1]} but its camera entry says "
                                      f"{frame.size[0]}x{frame.size[1]}")
    return frame.size, turned


def layout_split(frames: list[Frame], ids: dict[str, str]) -> tuple[list[str], list[str], str] | None:
    """The split a transforms layout's part files give (train / test; val views are left out), or None."""
    if not any(f.part for f in frames):
        return None
    train = sorted(ids[f.name] for f in frames if f.part == "train")
    test = sorted(ids[f.name] for f in frames if f.part == "test")
    return train, test, " + ".join(PART_FILES[p] for p in ("train", "test") if any(f.part == p for f in frames))


def frames_and_ids(path: str | Path) -> tuple[list[Frame], dict[str, str]]:
    """The frames of a frame layout's folder (or of one of its files) and the view id of each
    frame's ``name`` (:func:`~.split.view_ids`)."""
    path = Path(path)
    frames = layout_frames(path)
    try:
        return frames, view_ids([f.name for f in frames])
    except ValueError as e:
        raise InputError(path, str(e)) from None


def read_frames_scene(root: str | Path, train_ids: Iterable[str] | None = None,
                      test_ids: Iterable[str] | None = None) -> Scene:
    """Read a frame layout and its photos as a :class:`~.scene.Scene` (no depth): every photo
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
    layout = find_frame_layout(root)
    log.info("read %s layout %s: %d views (%d undistorted), train %s (split: %s)", layout, root, len(views),
             undistorted, train, source)
    return Scene(root=root, views=views, track=[], train=train, test=test, split_source=source, layout=layout)


def read_frames_cameras(path: str | Path) -> list[Camera]:
    """The cameras of a frame layout's folder or of one of its files (sorted by view id),
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
