"""COLMAP models (text or binary) as :class:`~dibrgs_core.data.levir.Scene`, through pycolmap.

Accepted layouts (the first that holds ``cameras.bin`` or ``cameras.txt`` wins)::

    ROOT/sparse/N/{cameras,images,points3D}.{bin,txt}   + ROOT/images/<name>
    ROOT/sparse/{cameras,images,points3D}.{bin,txt}     + ROOT/images/<name>
    ROOT/{cameras,images,points3D}.{bin,txt}            + ROOT/images/<name> (or ROOT/../../images)

COLMAP's mapper writes one model a part of the flight it could join (``sparse/0``, ``sparse/1``,
...): of several, the one with the most images is read, and the log says so; a model's own folder
(``SCENE/sparse/1``) reads that one, with ``SCENE``'s photos and ``split.json``.

``points3D`` may be missing (a model of known cameras and poses only): its points are never read.

COLMAP poses are world-to-camera with OpenCV axes and pixel centres at +0.5,
the project's own convention, so they are taken over unchanged. Pinhole
cameras are used as they are; ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV`` and
``FULL_OPENCV`` cameras with distortion are undistorted on load
(:mod:`.undistort`: pycolmap, cached); fisheye models are refused.

Photos: JPEG, PNG or TIFF, any aspect ratio, of any sizes (each view keeps its own). COLMAP reconstructs from the
stored pixel order and ignores EXIF orientation, so the stored order is used
when it matches the camera's size; a photo that matches only when turned
upright (a model made from rotated copies) is turned upright. Pixels without data (transparent,
no-data values, :mod:`.images`) and those a mask image zeroes (``ROOT/masks/<name>.png``, COLMAP's
``mask_path`` convention) are left out of training, evaluation and geometry.

View ids are the image file stems (a rig's like-named photos in folders of their own: their paths,
:func:`~dibrgs_core.data.split.view_ids`); the split comes from ``--train``/``--test``,
``split.json`` or :func:`~dibrgs_core.data.split.default_split`.
"""
from __future__ import annotations

import logging
import mmap
import shutil
import struct
from functools import partial
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..common.colmap_lib import import_pycolmap
from ..common.errors import InputError
from .scene import ImageFile, Pixels, Scene, View, validate_camera_arrays
from .split import make_split, view_ids
from .images import find_mask, image_size, read_masked, turned_to_fit
from .undistort import cache_dir, check_model, undistort_photo, undistorted_camera

log = logging.getLogger("dibrgs.io_colmap")


def _is_model(d: Path) -> bool:
    return (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file()


def image_count(model_dir: Path) -> int:
    """Images in a COLMAP model, from the head of ``images.bin`` or the image lines of ``images.txt``
    (without decoding the model); 0 when neither is readable."""
    try:
        if (model_dir / "images.bin").is_file():
            with open(model_dir / "images.bin", "rb") as f:
                head = f.read(8)
            return struct.unpack("<Q", head)[0] if len(head) == 8 else 0
        n = 0
        with open(model_dir / "images.txt", encoding="utf-8", errors="replace") as f:
            for line in f:
                t = line.split()  # an image line: ID QW QX QY QZ TX TY TZ CAMERA_ID NAME
                n += len(t) >= 10 and not line.startswith("#") and t[0].isdigit() and t[8].isdigit()
        return n
    except OSError:
        return 0


def colmap_models(root: str | Path) -> list[Path]:
    """The numbered models in ``root/sparse`` (``0``, ``1``, ...), in number order."""
    sparse = Path(root) / "sparse"
    if not sparse.is_dir():
        return []
    return sorted((d for d in sparse.iterdir() if d.name.isdigit() and _is_model(d)), key=lambda d: int(d.name))


def find_colmap_model(root: str | Path) -> Path | None:
    """The folder holding the COLMAP model under ``root``, or None: of ``root/sparse``'s numbered
    models the one with the most images (the lowest number of those as large), else ``root/sparse``,
    else ``root`` itself."""
    root = Path(root)
    numbered = colmap_models(root)
    if numbered:  # counted only when there is a choice (images.txt can be large)
        return numbered[0] if len(numbered) == 1 else max(numbered, key=image_count)
    return next((d for d in (root / "sparse", root) if _is_model(d)), None)


def split_folder(root: str | Path) -> Path:
    """Where a COLMAP scene's ``split.json`` is read: ``root``, or, for a model's own folder inside
    ``SCENE/sparse/`` with none of its own, ``SCENE``."""
    root = Path(root)
    if not (root / "split.json").is_file() and root.parent.name == "sparse" and _is_model(root):
        return root.parent.parent
    return root


def image_folder(root: Path, model_dir: Path) -> Path | None:
    """The photos' folder of a COLMAP model: ``root/images`` (or ``Images``), else ``images`` beside
    the model folder or beside its ``sparse`` folder (``root`` given as ``SCENE/sparse/1``)."""
    near = [root / "images", root / "Images", model_dir.parent / "images"]
    up = [model_dir.parent.parent / "images"] if model_dir.parent.name == "sparse" else []
    return next((d for d in near + up if d.is_dir()), None)


def read_colmap_cameras(root: str | Path) -> list[Camera]:
    """Posed cameras of a COLMAP model (sorted by image name), without images."""
    rec, model_dir = _load(root)
    return [c for c, _ in _cameras(rec, model_dir)]


def _load(root: str | Path):
    root = Path(root)
    if not root.exists():
        raise InputError(root, "COLMAP folder not found")
    model_dir = find_colmap_model(root)
    if model_dir is None:
        raise InputError(root, "no COLMAP model (cameras.bin/.txt in sparse/N, sparse/ or the folder)")
    numbered = colmap_models(root)
    if len(numbered) > 1:
        log.warning("%s holds %d COLMAP models (%s): reading sparse/%s, the one with the most images; give a model's "
                    "folder (%s) to read another", root / "sparse", len(numbered),
                    ", ".join(f"{d.name}: {image_count(d)} images" for d in numbered), model_dir.name,
                    root / "sparse" / "N")
    if not any((model_dir / f"images{e}").is_file() for e in (".bin", ".txt")):
        raise InputError(model_dir / "images.bin", "COLMAP model file missing")
    check_binary_counts(model_dir)
    try:
        rec = _without_points(model_dir)
        _ = [im.name for im in rec.images.values()]  # a damaged name is no UTF-8: fails here, not later
        return rec, model_dir
    except Exception as e:  # pycolmap raises plain exceptions for corrupt models
        why = dangling_camera(model_dir) or f"unreadable COLMAP model ({type(e).__name__}: {e})"
        raise InputError(model_dir, why) from None


def dangling_camera(model_dir: Path) -> str | None:
    """Which image of the model in ``model_dir`` names a camera the model lacks, as a line, else
    None. pycolmap refuses such a model as a whole, naming the rig or frame it made for the camera
    (text models have neither); the add-on's plain parser (numpy and struct) can name the image."""
    from ..bridge.colmap_model import missing_camera, read_model

    try:
        return missing_camera(*read_model(model_dir))
    except InputError:
        return None  # damaged otherwise: pycolmap's own message stands


#: Bytes of one record of each binary file after its count, at the least (COLMAP's
#: reconstruction_io_binary.cc): a frame's id, rig id and pose; an image's id, pose, camera id and
#: the name's terminating zero; a rig's id and sensor count; a camera's id, model, size and one parameter.
_MIN_RECORD = {"frames": 4 + 4 + 56 + 4, "images": 4 + 56 + 4 + 1 + 8, "rigs": 4 + 4, "cameras": 4 + 4 + 16 + 8}


def check_binary_counts(model_dir: Path) -> None:
    """InputError naming a binary model file whose counts announce more records than it holds:
    pycolmap reads such a file past its end without stopping (a damaged frames.bin took minutes).
    Walks the frames' data ids, the images' points and the rigs' sensors; reads no values."""
    for stem, least in _MIN_RECORD.items():
        path = model_dir / f"{stem}.bin"
        if not path.is_file():
            continue
        size = path.stat().st_size
        if size < 8:
            raise InputError(path, f"unreadable COLMAP model file (damaged: {size} bytes, no count)")
        with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            _walk_binary(path, stem, least, data, size)


def _walk_binary(path: Path, stem: str, least: int, data, size: int) -> None:
    """:func:`check_binary_counts` of one file's bytes ``data`` (a memory map: images.bin can be large)."""
    off = 8

    def need(n: int, what: str) -> None:
        if off + n > size:
            raise InputError(path, f"unreadable COLMAP model file (damaged: {what} reach past its {size} bytes)")

    (count,) = struct.unpack_from("<Q", data, 0)
    if count * least > size - 8:
        raise InputError(path, f"unreadable COLMAP model file (damaged: {count} records announced in {size} bytes)")
    if stem == "cameras":
        return  # each camera's parameters are a fixed number for its model: pycolmap checks them
    for _ in range(count):
        if stem == "frames":
            need(68, "a frame")
            (k,) = struct.unpack_from("<I", data, off + 64)
            off += 68
            need(16 * k, f"a frame's {k} data ids")
            off += 16 * k
        elif stem == "images":
            need(64, "an image")
            end = data.find(b"\0", off + 64)
            if end < 0:
                raise InputError(path, "unreadable COLMAP model file (damaged: an image name without its end)")
            off = end + 1
            need(8, "an image's point count")
            (k,) = struct.unpack_from("<Q", data, off)
            off += 8
            need(24 * k, f"an image's {k} points")
            off += 24 * k
        else:
            need(8, "a rig")
            (k,) = struct.unpack_from("<I", data, off + 4)
            off += 8 + (8 if k else 0)
            for _ in range(max(k - 1, 0)):
                need(9, "a rig's sensor")
                off += 9 + (56 if data[off + 8] else 0)
                need(0, "a rig's sensor pose")


def _without_points(model_dir: Path):
    """A model's cameras and poses, read by pycolmap beside an empty points file: the pipeline
    triangulates its own points, a known-poses model may have none (COLMAP's FAQ writes an empty
    file, not every exporter does), a large model's millions of points cost seconds and gigabytes
    to read, and a damaged ``points3D.bin`` (a count of 2^40 points) keeps pycolmap reading
    forever. The other files are linked (copied where links are not allowed)."""
    import tempfile

    pycolmap = import_pycolmap()

    ext = ".bin" if (model_dir / "cameras.bin").is_file() else ".txt"
    with tempfile.TemporaryDirectory(prefix="dibrgs-colmap-") as tmp:
        for stem in ("cameras", "images", "rigs", "frames"):
            src, dst = model_dir / f"{stem}{ext}", Path(tmp) / f"{stem}{ext}"
            if src.is_file():
                try:
                    dst.symlink_to(src.resolve())
                except OSError:
                    shutil.copyfile(src, dst)
        (Path(tmp) / f"points3D{ext}").write_bytes(struct.pack("<Q", 0) if ext == ".bin" else b"")
        return pycolmap.Reconstruction(tmp)


def _cameras(rec, model_dir: Path) -> list[tuple[Camera, str]]:
    """(camera as loaded - undistorted where the model has distortion -, image name) of every posed image."""
    out: list[tuple[Camera, str]] = []
    posed = []
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        if not img.has_pose:
            log.warning("%s: image %s has no pose, skipped", model_dir, img.name)
            continue
        posed.append(img)
    try:
        ids = view_ids([img.name for img in posed])
    except ValueError as e:
        raise InputError(model_dir, str(e)) from None
    for img in posed:
        cam = rec.cameras[img.camera_id]
        if check_model(cam, model_dir):
            cam = undistorted_camera(cam)
        K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(img.cam_from_world().matrix(), dtype=np.float64)
        validate_camera_arrays(w2c, K, None, model_dir)
        out.append((Camera(K=K, w2c=w2c, width=cam.width, height=cam.height, name=ids[img.name]), img.name))
    if not out:
        raise InputError(model_dir, "COLMAP model has no posed images")
    return out


def read_colmap_scene(root: str | Path, train_ids: Iterable[str] | None = None,
                      test_ids: Iterable[str] | None = None) -> Scene:
    """Read a COLMAP model and its images (``ROOT/images/``) as a :class:`Scene` (no depth). Every
    photo is decoded (and undistorted) once to check it and left in its file
    (:class:`~dibrgs_core.data.scene.ImageFile`)."""
    root = Path(root)
    rec, model_dir = _load(root)
    img_dir = image_folder(root, model_dir)
    if img_dir is None:
        raise InputError(root / "images", "image folder not found")
    by_name = {im.name: im for im in rec.images.values()}
    photos: list[tuple[Camera, Path, object, bool, bool]] = []
    for cam, name in _cameras(rec, model_dir):
        path = img_dir / name
        if not path.is_file():
            raise InputError(path, "image file missing (listed in the COLMAP model)")
        ccam = rec.cameras[by_name[name].camera_id]
        photos.append((cam, path, ccam, _orientation(path, ccam.width, ccam.height), check_model(ccam, model_dir)))
    undistorted = sum(p[4] for p in photos)
    views: dict[str, View] = {}
    for cam, path, ccam, oriented, distorted in photos:  # each photo at its own size
        pixels, size = ImageFile.checked(path, partial(read_photo, path, ccam, oriented, distorted,
                                                       find_mask(img_dir, path.relative_to(img_dir).as_posix())))
        if size != (cam.width, cam.height):
            raise InputError(path, f"image is {size[0]}x{size[1]} but its COLMAP camera is {cam.width}x{cam.height}")
        views[cam.name] = View(camera=cam, image=pixels)
    if undistorted:
        log.info("%s: %d photos undistorted (pycolmap; cache %s)", model_dir, undistorted, cache_dir())
    ids = sorted(views)
    views = {k: views[k] for k in ids}
    try:
        train, test, source = make_split(split_folder(root), ids, train_ids, test_ids)
    except ValueError as e:
        raise InputError(root, str(e)) from None
    log.info("read COLMAP model %s: %d views, train %s (split: %s)", model_dir, len(views), train, source)
    return Scene(root=root, views=views, track=[], train=train, test=test, split_source=source, layout="colmap")


def _orientation(path: Path, width: int, height: int) -> bool:
    """Whether to apply the photo's EXIF orientation: only when the stored pixels do not match the
    COLMAP camera's size and the upright photo does (COLMAP itself ignores EXIF orientation)."""
    raw = image_size(path, orient=False)
    if raw == (width, height):  # the usual case: one header read
        return False
    turned = bool(turned_to_fit(raw, image_size(path, orient=True), (width, height)))
    if turned:
        log.info("%s: turned upright by its EXIF orientation to match its COLMAP camera", path.name)
    return turned


def read_photo(path: Path, ccam, oriented: bool, distorted: bool, mask: Path | None = None) -> Pixels:
    """A photo's :data:`~.scene.Pixels` as its view holds them: read in the pixel order of its
    pycolmap camera ``ccam``, with its ``mask`` file if any, undistorted when ``distorted``."""
    if distorted:
        u = undistort_photo(path, ccam, oriented, lambda: read_masked(path, mask, orient=oriented), mask)
        return u.image, u.valid
    return read_masked(path, mask, orient=oriented)  # its size is checked against its camera by the caller


def write_colmap_model(cams: Sequence[Camera], out_dir: str | Path, binary: bool = True,
                       points: np.ndarray | None = None, colors: np.ndarray | None = None) -> Path:
    """Write cameras (one PINHOLE camera each, image name ``<name>.png``) and optional
    3D points (no tracks) as a COLMAP model in ``out_dir``."""
    pycolmap = import_pycolmap()

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
