"""Describe a scene folder for the Blender add-on, in Blender's own Python.

Blender's Python has numpy but no torch, Pillow or pycolmap, so this module
reads what the add-on needs (cameras, image paths, the train/test split, the
track) with numpy and the standard library only: Cams files through the
library's own parser, image sizes and EXIF orientations from file headers
(:mod:`.imagesize`), COLMAP models with :mod:`.colmap_model` (cameras with lens
distortion as the undistorted pinholes the library trains them as; the image paths
are the photos as taken) and frame layouts (transforms.json, Metashape XML, OpenSfM /
OpenDroneMap reconstruction.json, Meshroom cameras.sfm, OpenMVG sfm_data.json, Bundler
files, RealityCapture XMP sidecars) through the library's own parsers
(``data.frame_layouts``). It applies the same rules and messages as the library's
readers (``data.levir.read_scene``, ``data.colmap.read_colmap_scene``,
``data.frame_layouts.read_frames_scene``), which ``tests/bridge/test_bridge.py`` checks on
LEVIR, COLMAP (text and binary), transforms, Metashape, OpenSfM, Meshroom, OpenMVG, Bundler
and RealityCapture scenes.
The description is::

    {"root": str, "layout": the reader (Scene.layout), "layout_name": its name in words,
     "views": [{"name", "split": "train"|"test"|"other",
                             "camera": camera_to_dict(...), "image": path,
                             "orientation": EXIF orientation 1-8 that turns the file's
                                            stored pixels into the view's image,
                                            "undistorted": whether the camera is the
                                            undistorted pinhole of a distorted one}],
     "train": [names], "test": [names], "split_source": where the split came from,
     "track": [camera dicts], "origin": [x, y, z],
     "clip": [start, end]}

``clip`` is the Blender clip range for cameras without a depth range
(:func:`~dibrgs_core.camera.blender.clip_range`: in the scene's units).

Cameras are relative to ``origin`` (zeros unless the scene lies far from its coordinate origin:
:func:`~dibrgs_core.data.scene.in_local_frame`, the rule the library's readers follow), because
Blender holds positions in float32; cameras going back to the command line are moved by it
again (:func:`~dibrgs_core.bridge.path.write_camera_list`).

Bad input raises :class:`~dibrgs_core.common.errors.InputError` naming the file.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..camera.blender import clip_range
from ..camera.pinhole import Camera
from ..camera.serialize import camera_to_dict
from ..common.errors import InputError
from ..data.colmap import find_colmap_model, image_folder, split_folder
from ..data.frame_layouts import find_frame_layout, frames_and_ids, layout_split, stored_or_upright
from ..data.images import turned_to_fit, upright_size
from ..data.levir import check_sizes, paired_files, read_cams_file, read_track
from ..data.load import LAYOUT_NAMES, not_a_folder, not_a_scene
from ..data.scene import in_local_frame, validate_camera_arrays
from ..data.split import make_split, view_ids
from .colmap_model import ColmapCamera, missing_camera, read_model
from .imagesize import image_header


def describe_scene(root: str | Path) -> dict[str, Any]:
    """The description of the LEVIR-NVS, COLMAP or frame-layout (transforms, Metashape, OpenSfM,
    Meshroom, OpenMVG, Bundler, RealityCapture) scene at ``root`` (its ``split.json``, else the
    layout's own split, else the default)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, not_a_folder(root))
    layout = None
    if (root / "Cams").is_dir():
        views, images, track = _levir(root)
        kind = "levir"
    elif find_colmap_model(root) is not None:
        views, images, track = _colmap(root)
        kind = "colmap"
    elif (kind := find_frame_layout(root)) is not None:
        views, images, layout = _frames(root)
        track = []
    else:
        raise not_a_scene(root)
    try:
        train, test, source = make_split(split_folder(root), list(views), None, layout=layout)
    except ValueError as e:
        raise InputError(root, str(e)) from None
    origin, views, track = in_local_frame(views, track)
    out = []
    for name, cam in views.items():
        split = "train" if name in train else "test" if name in test else "other"
        path, orientation, undistorted = images[name]
        out.append({"name": name, "split": split, "camera": camera_to_dict(cam), "image": str(path.resolve()),
                    "orientation": orientation, "undistorted": undistorted})
    return {"root": str(root.resolve()), "layout": kind, "layout_name": LAYOUT_NAMES[kind], "views": out,
            "train": train, "test": test, "split_source": source,
            "track": [camera_to_dict(c) for c in track], "origin": [float(v) for v in origin],
            "clip": [float(v) for v in clip_range(list(views.values()))]}


def _levir(root: Path) -> tuple[dict[str, Camera], dict[str, tuple[Path, int, bool]], list[Camera]]:
    img_dir, cam_dir = root / "Images", root / "Cams"
    if not img_dir.is_dir():
        raise InputError(img_dir, "missing folder (a LEVIR-NVS scene needs Images/ and Cams/)")
    images, cams = paired_files(img_dir, cam_dir)
    headers = {stem: image_header(images[stem]) for stem in sorted(images)}
    # LEVIR views are the photos as a viewer shows them (the library follows EXIF orientation)
    views = {stem: read_cams_file(cams[stem], size=upright_size(w, h, o)) for stem, (w, h, o) in headers.items()}
    check_sizes(views, images, cams)  # each photo at its own size
    track = read_track(root, views)
    return views, {k: (images[k], headers[k][2], False) for k in views}, track


def _colmap(root: Path) -> tuple[dict[str, Camera], dict[str, tuple[Path, int, bool]], list[Camera]]:
    model_dir = find_colmap_model(root)
    cams, imgs = read_model(model_dir)
    img_dir = image_folder(root, model_dir)
    if img_dir is None:
        raise InputError(root / "images", "image folder not found")
    views: dict[str, Camera] = {}
    paths: dict[str, tuple[Path, int, bool]] = {}
    pinholes: dict[int, ColmapCamera] = {}  # one a camera: a project of many photos shares a few
    try:
        ids = view_ids([im.name for im in imgs])
    except ValueError as e:
        raise InputError(model_dir, str(e)) from None
    why = missing_camera(cams, imgs)
    if why:
        raise InputError(model_dir, why)
    for im in sorted(imgs, key=lambda i: i.name):
        cam = cams[im.camera_id]
        if im.camera_id not in pinholes:  # undistorted where the camera has distortion, as the library
            pinholes[im.camera_id] = cam.pinhole(model_dir)
        pin = pinholes[im.camera_id]
        K, w2c = pin.K(), im.w2c()
        validate_camera_arrays(w2c, K, None, model_dir)
        vid = ids[im.name]
        path = img_dir / im.name
        if not path.is_file():
            raise InputError(path, "image file missing (listed in the COLMAP model)")
        w, h, orientation = image_header(path)
        turned = turned_to_fit((w, h), upright_size(w, h, orientation), (cam.width, cam.height))
        if turned is None:
            raise InputError(path, f"image is {w}x{h} but its COLMAP camera is {cam.width}x{cam.height}")
        views[vid] = Camera(K=K, w2c=w2c, width=pin.width, height=pin.height, name=vid)
        paths[vid] = (path, orientation if turned else 1, pin is not cam)
    if not views:
        raise InputError(model_dir, "COLMAP model has no posed images")
    ids = sorted(views)
    return {k: views[k] for k in ids}, paths, []


def _frames(root: Path) -> tuple[dict[str, Camera], dict[str, tuple[Path, int, bool]], tuple | None]:
    frames, ids = frames_and_ids(root)
    views: dict[str, Camera] = {}
    paths: dict[str, tuple[Path, int, bool]] = {}
    for f in frames:
        w, h, orientation = image_header(f.photo)
        (W, H), turned = stored_or_upright(f, (w, h), upright_size(w, h, orientation))
        model, params = f.camera_model(W, H)
        pin = ColmapCamera(0, model, W, H, np.asarray(params, np.float64)).pinhole(f.photo)
        validate_camera_arrays(f.w2c, pin.K(), None, f.photo)
        vid = ids[f.name]
        views[vid] = Camera(K=pin.K(), w2c=f.w2c, width=pin.width, height=pin.height, name=vid)
        paths[vid] = (f.photo, orientation if turned else 1, model != "PINHOLE")
    return {k: views[k] for k in sorted(views)}, paths, layout_split(frames, ids)
