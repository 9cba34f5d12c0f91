"""LEVIR-NVS scene layout: reading, writing and validation.

Layout of a scene folder::

    Images/NNN.png   RGB views (8- or 16-bit; also .jpg/.jpeg/.tif accepted)
    Cams/NNN.txt     "extrinsic", 4x4 world-to-camera (OpenCV axes), "intrinsic",
                     3x3 K in pixels, then "DEPTH_MIN DEPTH_MAX" (27 numbers)
    Depths/NNN.tiff  optional float32 z-depth (distance along the camera axis;
                     0 or non-finite = no depth). Depths/NNN.exr (channel "Z") also read.
    Track/NNN.txt    optional render-path cameras, same format as Cams/
    Masks/NNN.png    optional: black where a photo holds no data (also NNN.png.png, COLMAP's
                     naming); transparent and no-data pixels of the photos count as masked

    split.json       optional {"train": [names], "test": [names]} (see data.split.make_split)

Views 001-020 form the orbit; view 000 (near nadir) is in neither split by
default. The standard 3-view protocol trains on the orbit views at indices
0, 7 and 14 (001, 008, 015) and evaluates on the other 17; ``split.json`` or
``--train`` / ``--test`` choose others.

Every image is decoded once when the scene is read (a damaged file is an error then) and left in
its file (:class:`~dibrgs_core.data.scene.ImageFile`): a run reads the views it uses again.
Bad input raises :class:`~dibrgs_core.common.errors.InputError` naming the file.
This module needs numpy, Pillow, tifffile and OpenEXR, never torch or bpy.
"""
from __future__ import annotations

import json
import logging
import math
import re
from collections import Counter
from functools import partial
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..camera.serialize import camera_from_dict
from ..common.errors import InputError
from ..common.fileio import write_text
from .images import (DEPTH_EXTS, IMAGE_EXTS, find_mask, image_size, read_depth, read_masked,
                     write_depth_tiff, write_png)
from .scene import ImageFile, Scene, View, validate_camera_arrays
from .split import make_split

log = logging.getLogger("dibrgs.io_levir")



# ---------------------------------------------------------------------------
# Cams files
# ---------------------------------------------------------------------------
_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf|infinity)$", re.I)


def parse_cams_text(text: str, path: Path) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """(w2c 4x4, K 3x3, (depth_min, depth_max)) from a Cams file's text; InputError names ``path``."""
    tokens = text.split()
    low = [t.lower() for t in tokens]
    if "extrinsic" not in low or "intrinsic" not in low:
        raise InputError(path, "not a LEVIR Cams file: needs the words 'extrinsic' and 'intrinsic'")
    ie, ii = low.index("extrinsic"), low.index("intrinsic")
    if ii < ie:
        raise InputError(path, "'intrinsic' comes before 'extrinsic'")
    ext, rest = tokens[ie + 1:ii], tokens[ii + 1:]
    for t in ext + rest:
        if not _NUM.match(t):
            raise InputError(path, f"unexpected token {t!r} (expected numbers)")
    if len(ext) != 16:
        raise InputError(path, f"extrinsic needs 16 values (4x4), found {len(ext)}")
    if len(rest) != 11:
        raise InputError(path, f"intrinsic needs 9 values (3x3) then DEPTH_MIN DEPTH_MAX, found {len(rest)} values")
    w2c = np.array([float(t) for t in ext]).reshape(4, 4)
    K = np.array([float(t) for t in rest[:9]]).reshape(3, 3)
    dr = (float(rest[9]), float(rest[10]))
    validate_camera_arrays(w2c, K, dr, path)
    return w2c, K, dr


def check_sizes(cameras: dict[str, Camera], photos: dict[str, Path], cams_files: dict[str, Path]) -> None:
    """Photos may differ in size (each camera has its photo's), but a Cams file does not say which
    size it was made for: when the photos differ, a photo whose camera's principal point lies off
    its middle half is an InputError naming it (its Cams file is likely for a photo of another
    size, e.g. one resized by mistake). Photos of one size are taken as they are, off-centre
    crops included."""
    if len({(c.width, c.height) for c in cameras.values()}) < 2:
        return
    for k, c in cameras.items():
        cx, cy = float(c.K[0, 2]), float(c.K[1, 2])
        if abs(cx - c.width / 2) > c.width / 4 or abs(cy - c.height / 2) > c.height / 4:
            raise InputError(photos[k], f"image is {c.width}x{c.height} but its camera's principal point "
                                        f"({cx:g}, {cy:g}) lies off its middle: {cams_files[k].name} is likely "
                                        "for a photo of another size (the scene's photos differ in size)")


def read_cams_file(path: str | Path, size: tuple[int, int] | None = None) -> Camera:
    """Read a LEVIR Cams file.

    ``size`` is the image (width, height); by default it comes from the
    matching ``../Images/<id>.*`` when present, else from the principal point
    (``2 cx`` x ``2 cy``, rounded up).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError(path, "camera file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read camera file ({e})") from None
    w2c, K, dr = parse_cams_text(text, path)
    if size is None:
        img = _find(path.parent.parent / "Images", path.stem, IMAGE_EXTS)
        if img is not None:
            size = image_size(img)
        else:
            size = (max(1, math.ceil(2 * K[0, 2] - 1e-6)), max(1, math.ceil(2 * K[1, 2] - 1e-6)))
    return Camera(K=K, w2c=w2c, width=size[0], height=size[1], name=path.stem, depth_range=dr)


def format_cams(cam: Camera) -> str:
    """LEVIR Cams text; floats with 17 significant digits so float64 round-trips exactly."""
    def row(v: Iterable[float]) -> str:
        return " ".join(repr(float(x)) for x in v)

    dr = cam.depth_range if cam.depth_range is not None else (0.0, 0.0)
    lines = ["extrinsic"] + [row(r) for r in cam.w2c] + ["", "intrinsic"] + [row(r) for r in cam.K]
    lines += ["", row(dr), ""]
    return "\n".join(lines)


def write_cams_file(path: str | Path, cam: Camera) -> None:
    """Write a LEVIR Cams file (atomically). A missing depth range is written as ``0 0``."""
    write_text(path, format_cams(cam))


def read_cameras(path: str | Path) -> list[Camera]:
    """Cameras from a LEVIR Cams file, a folder of them (or a scene folder with
    ``Cams/``), or a JSON list of :func:`~dibrgs_core.camera.pinhole.camera_to_dict`
    entries (optionally under a ``"cameras"`` key)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "camera path not found")
    if path.is_dir():
        folder = path / "Cams" if (path / "Cams").is_dir() else path
        files = sorted(folder.glob("*.txt"))
        if not files:
            raise InputError(folder, "no camera .txt files in folder")
        return [read_cams_file(f) for f in files]
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(path, f"cannot read JSON camera list ({e})") from None
        if isinstance(data, dict) and "cameras" in data:
            data = data["cameras"]
        if not isinstance(data, list) or not data:
            raise InputError(path, "expected a non-empty JSON list of cameras")
        cams = []
        for k, d in enumerate(data):
            if not isinstance(d, dict):
                raise InputError(path, f"camera entry {k} is not an object")
            try:
                cam = camera_from_dict(d, source=f"entry {k}")
            except ValueError as e:
                raise InputError(path, str(e)) from None
            validate_camera_arrays(cam.w2c, cam.K, cam.depth_range, path)
            if not cam.name:
                cam.name = f"{k:03d}"
            cams.append(cam)
        return cams
    return [read_cams_file(path)]


def _find(folder: Path, stem: str, exts: Sequence[str]) -> Path | None:
    for e in exts:
        p = folder / f"{stem}{e}"
        if p.is_file():
            return p
    return None


# ---------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------
def paired_files(img_dir: Path, cam_dir: Path) -> tuple[dict[str, Path], dict[str, Path]]:
    """``(images, cams)`` of a LEVIR-NVS scene by view id (file stem), hidden files skipped;
    ``InputError`` naming the file when there are no images or an image lacks its Cams file
    or the reverse."""
    images = {p.stem: p for p in sorted(img_dir.iterdir()) if p.suffix.lower() in IMAGE_EXTS and p.is_file()
              and not p.name.startswith(".")}
    cams = {p.stem: p for p in sorted(cam_dir.glob("*.txt")) if not p.name.startswith(".")}
    if not images:
        raise InputError(img_dir, "no images found")
    for stem in sorted(set(images) - set(cams)):
        raise InputError(cam_dir / f"{stem}.txt", f"camera file missing for image {images[stem].name}")
    for stem in sorted(set(cams) - set(images)):
        raise InputError(img_dir / f"{stem}.png", f"image missing for camera {cams[stem].name}")
    return images, cams


def read_scene(root: str | Path, train_ids: Iterable[str] | None = None, load_depth: bool = True,
               test_ids: Iterable[str] | None = None) -> Scene:
    """Read a LEVIR-NVS scene folder (see module docstring).

    Args:
        root: scene folder with ``Images/`` and ``Cams/``.
        train_ids: training view ids (default: the 3-view protocol, 001/008/015).
        load_depth: read ``Depths/`` when present.
        test_ids: evaluation view ids (default: the other orbit views).
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "scene folder not found")
    img_dir, cam_dir, dep_dir = root / "Images", root / "Cams", root / "Depths"
    for d in (img_dir, cam_dir):
        if not d.is_dir():
            raise InputError(d, "missing folder (a LEVIR-NVS scene needs Images/ and Cams/)")
    images, cams = paired_files(img_dir, cam_dir)
    use_depth = load_depth and dep_dir.is_dir()
    cameras = {stem: read_cams_file(cams[stem], size=image_size(images[stem])) for stem in sorted(images)}
    check_sizes(cameras, images, cams)
    views: dict[str, View] = {}
    for stem, cam in cameras.items():  # each photo at its own size
        pixels, (w, h) = ImageFile.checked(images[stem], partial(read_masked, images[stem],
                                                                 find_mask(img_dir, images[stem].name)))
        if (w, h) != (cam.width, cam.height):
            raise InputError(images[stem], f"image decodes to {w}x{h} but its header says {cam.width}x{cam.height}")
        depth = None
        if use_depth:
            dp = _find(dep_dir, stem, DEPTH_EXTS)
            if dp is None:
                raise InputError(dep_dir / f"{stem}.tiff", "depth map missing (Depths/ exists for this scene)")
            depth = read_depth(dp)
            if depth.shape != (h, w):
                raise InputError(dp, f"depth map is {depth.shape[1]}x{depth.shape[0]} but its image "
                                     f"{images[stem].name} is {w}x{h}")
        views[stem] = View(camera=cam, image=pixels, depth=depth)
    track = read_track(root, cameras)
    try:
        train, test, source = make_split(root, list(views), train_ids, test_ids)
    except ValueError as e:
        raise InputError(root, str(e)) from None
    scene = Scene(root=root, views=views, track=track, train=train, test=test, split_source=source, layout="levir")
    sizes = scene.sizes()
    (w, h), others = next(iter(sizes)), len(sizes) - 1
    log.info("read %s: %d views %dx%d%s, train %s, %d test (split: %s), %d track cameras%s", root, len(views),
             w, h, f" (and {others} other sizes)" if others else "", train, len(test), source, len(track),
             ", with depth" if use_depth else "")
    return scene


def read_track(root: Path, cameras: dict[str, Camera]) -> list[Camera]:
    """The render-path cameras of ``ROOT/Track/`` (none without the folder), at the size of the
    scene's photos ``cameras`` (the most common one): a Cams file holds no size."""
    if not (root / "Track").is_dir():
        return []
    size = Counter((c.width, c.height) for c in cameras.values()).most_common(1)[0][0]
    return [read_cams_file(p, size=size) for p in sorted((root / "Track").glob("*.txt")) if not p.name.startswith(".")]


def write_scene(root: str | Path, views: dict[str, View] | Iterable[View], track: Iterable[Camera] = ()) -> Path:
    """Write views (PNG, Cams, a mask PNG where some pixels hold no data, and depth as TIFF when
    present) and Track cameras in LEVIR layout."""
    root = Path(root)
    vs = list(views.values()) if isinstance(views, dict) else list(views)
    for v in vs:
        if not v.name:
            raise ValueError("every view's camera needs a name (its id)")
        image, valid = v.pixels()
        write_png(root / "Images" / f"{v.name}.png", image)
        if valid is not None:
            write_png(root / "Masks" / f"{v.name}.png", np.repeat(valid[..., None], 3, axis=2).astype(np.uint8) * 255)
        write_cams_file(root / "Cams" / f"{v.name}.txt", v.camera)
        if v.depth is not None:
            write_depth_tiff(root / "Depths" / f"{v.name}.tiff", v.depth)
    for k, c in enumerate(track):
        write_cams_file(root / "Track" / f"{c.name or f'{k:03d}'}.txt", c)
    return root


