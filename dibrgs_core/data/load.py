"""Reading any supported scene folder (LEVIR-NVS ``Cams/``, a COLMAP model, a transforms.json, a
Metashape cameras XML, an OpenDroneMap / OpenSfM reconstruction, a Meshroom cameras.sfm, an OpenMVG
sfm_data.json, a Bundler file or RealityCapture's XMP sidecars), or any cameras to render."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..common.digest import Digest
from ..common.errors import InputError
from .levir import read_cameras, read_scene
from .scene import Scene


def read_any_scene(root: str | Path, train_ids: Iterable[str] | None = None, load_depth: bool = True,
                   test_ids: Iterable[str] | None = None) -> Scene:
    """Read a LEVIR-NVS folder (``Cams/``), a COLMAP model (``sparse/0``, ``sparse`` or the folder
    itself) or a frame layout (a transforms.json, a Metashape cameras XML, an OpenSfM
    reconstruction, a Meshroom SfMData file, an OpenMVG sfm_data.json, a Bundler file or
    RealityCapture sidecars: :mod:`.frame_layouts`), in a frame of its own when it lies far from its
    coordinate origin (``Scene.origin``,
    :meth:`~dibrgs_core.data.scene.Scene.recentred`)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, not_a_folder(root))
    if (root / "Cams").is_dir():
        return read_scene(root, train_ids=train_ids, load_depth=load_depth, test_ids=test_ids).recentred()
    from .colmap import find_colmap_model, read_colmap_scene

    if find_colmap_model(root) is not None:
        return read_colmap_scene(root, train_ids=train_ids, test_ids=test_ids).recentred()
    from .frame_layouts import find_frame_layout, read_frames_scene

    if find_frame_layout(root) is not None:
        return read_frames_scene(root, train_ids=train_ids, test_ids=test_ids).recentred()
    raise not_a_scene(root)


#: What each reader (``Scene.layout``) is called where a person reads it (the add-on's messages).
LAYOUT_NAMES = {"levir": "LEVIR-NVS folder", "colmap": "COLMAP model", "transforms": "transforms.json",
                "metashape": "Metashape camera export", "opensfm": "OpenDroneMap / OpenSfM reconstruction",
                "meshroom": "Meshroom project", "openmvg": "OpenMVG reconstruction",
                "realitycapture": "RealityCapture sidecars", "bundler": "Bundler file"}


def not_a_folder(root: Path) -> str:
    """What is wrong with a scene path that is no folder (the library's and the add-on's readers
    say it alike)."""
    if not root.exists():
        return "scene folder not found"
    return "not a folder (a scene is the folder holding the camera file and the photos)"


def not_a_scene(root: Path) -> InputError:
    """The error for a folder that no reader takes (the library's and the add-on's readers say it
    alike): what a scene folder holds, or how to convert OpenMVG's binary file when it holds one."""
    from .openmvg import binary_sfm_data

    return binary_sfm_data(root) or InputError(root, NOT_A_SCENE)


#: What a scene folder holds.
NOT_A_SCENE = ("not a scene: expected LEVIR-NVS Images/ + Cams/, a COLMAP model (cameras/images/points3D "
               ".bin or .txt in sparse/N, sparse/ or the folder), a transforms.json (instant-ngp, nerfstudio), a "
               "Metashape cameras XML (cameras.xml, photos in images/), an OpenDroneMap / OpenSfM "
               "reconstruction (opensfm/reconstruction.json or reconstruction.json, photos in images/), a "
               "Meshroom cameras.sfm (or a project's MeshroomCache), an OpenMVG sfm_data.json, a Bundler bundle.out "
               "with its list.txt, or RealityCapture XMP sidecars beside the photos")


def load_scene(root: str | Path, train_ids: Iterable[str] | None = None,
               test_ids: Iterable[str] | None = None, load_depth: bool = True) -> Scene:
    """Read a scene folder for a run, with its split (``--train`` / ``--test``, else ``split.json``,
    else the default; :func:`~dibrgs_core.data.split.make_split`). ``InputError`` when it does not
    exist or is no scene."""
    return read_any_scene(root, train_ids=train_ids, test_ids=test_ids, load_depth=load_depth)


def read_any_cameras(path: str | Path) -> list[Camera]:
    """Cameras to render, in the frame of the files they come from: a LEVIR-NVS Cams file, a folder
    of them or a LEVIR scene (its ``Cams/``), a JSON camera list (:func:`~.levir.read_cameras`), a
    COLMAP model (a folder holding one in ``sparse/0``, ``sparse/`` or itself: every posed image,
    named by its view id, with the pinhole camera training uses - undistorted where the model has
    distortion - at the photo's full size), or a frame layout's folder or one of its files (a
    transforms JSON, a Metashape XML, an OpenSfM reconstruction, a Meshroom .sfm, an OpenMVG
    sfm_data.json, a Bundler file or a RealityCapture XMP; likewise)."""
    from .colmap import find_colmap_model, read_colmap_cameras
    from .frame_layouts import file_layout, find_frame_layout, read_frames_cameras

    path = Path(path)
    if path.is_dir() and not (path / "Cams").is_dir():
        if find_colmap_model(path) is not None:
            return read_colmap_cameras(path)
        if find_frame_layout(path) is not None:
            return read_frames_cameras(path)
    if path.is_file() and file_layout(path) is not None:
        return read_frames_cameras(path)
    return read_cameras(path)


def cameras_digest(cams: Sequence[Camera]) -> str:
    """Digest of cameras' names, sizes and K / w2c (their content, whatever file or folder held them)."""
    d = Digest("cameras/1")
    for c in cams:
        d.text(c.name or "").json([int(c.width), int(c.height)])
        d.array(np.asarray(c.K, np.float64)).array(np.asarray(c.w2c, np.float64))
    return d.hex()
