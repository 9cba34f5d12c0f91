"""One photo of a frame layout with its camera, as the readers of one camera a photo give it
(:mod:`.transforms`, :mod:`.metashape`, :mod:`.opensfm`, :mod:`.meshroom`, :mod:`.openmvg`,
:mod:`.bundler`, :mod:`.realitycapture`; :mod:`.frame_layouts` makes views of them).

Conventions: ``w2c`` is world-to-camera with OpenCV axes (+x right, +y down, looking along +z);
intrinsics are in pixels with the principal point in COLMAP's convention (the image spans [0, w])
and OpenCV's distortion coefficients.
"""
from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..common.errors import InputError
from .images import IMAGE_EXTS, find_mask, image_named

log = logging.getLogger("dibrgs.io_frames")

DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")
#: Where a layout's photos sit beside its camera file.
PHOTO_FOLDERS = ("images", "Images")


@dataclass
class Frame:
    """One photo of a frame layout, before its size is known.

    Attributes:
        name: the photo's name as the layout gives it (relative to the scene folder or the photos'
            folder; view ids come from it).
        photo: the photo file.
        w2c: 4x4 world-to-camera, OpenCV axes.
        size: (width, height) the layout gives, or None (the photo's own).
        intrinsics: ``fl_x``, ``fl_y``, ``cx``, ``cy`` (pixels), ``camera_angle_x``,
            ``camera_angle_y`` (radians), or ``fl_long``, ``cx_long``, ``cy_long`` (the focal length,
            and the principal point's offset from the image centre, in units of the photo's longer
            side), those given, and OpenCV distortion ``k1``, ``k2``, ``p1``, ``p2``, ``k3``.
        part: ``"train"``, ``"test"``, ``"val"`` (from a transforms part file) or None.
        mask: the photo's mask image (black pixels hold no data), or None.
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
        if "fl_long" in i:  # in units of the longer side: any size of the photo
            side = max(width, height)
            i = {**i, "fl_x": i["fl_long"] * side, "cx": width / 2.0 + i.get("cx_long", 0.0) * side,
                 "cy": height / 2.0 + i.get("cy_long", 0.0) * side}
        fx = i.get("fl_x")
        if fx is None:
            if "camera_angle_x" not in i:
                raise InputError(self.photo, "its camera has neither fl_x nor camera_angle_x")
            fx = 0.5 * width / math.tan(0.5 * i["camera_angle_x"])
        fy = i.get("fl_y")
        if fy is None:
            fy = 0.5 * height / math.tan(0.5 * i["camera_angle_y"]) if "camera_angle_y" in i else fx
        pin = [fx, fy, i.get("cx", width / 2.0), i.get("cy", height / 2.0)]
        k = [i.get(key, 0.0) for key in DISTORTION_KEYS]
        if k[4]:
            return "FULL_OPENCV", pin + k + [0.0, 0.0, 0.0]
        if any(k[:4]):
            return "OPENCV", pin + k[:4]
        return "PINHOLE", pin


def find_photo(folder: Path, name: str, where: Path, what: str) -> Path:
    """The photo ``name`` in ``folder``: as written, or with an image extension added (Blender's
    synthetic scenes write ``./train/r_0`` for ``train/r_0.png``; Metashape labels may drop it).
    InputError naming ``where`` and ``what`` (the entry) when there is none."""
    p = folder / name
    if p.suffix.lower() in IMAGE_EXTS and p.is_file():
        return p
    q = image_named(p.parent, p.name)
    if q is not None:
        return q
    if p.is_file():
        return p  # another extension: the image readers say whether they can read it
    raise InputError(where, f"{what}: photo {name} not found in {folder}")


def labelled_photo(folder: Path, label: str, where: Path, what: str, index: dict[str, list[Path]]) -> Path:
    """The photo of a camera label (a file name, with or without its extension, as Metashape,
    Meshroom and OpenMVG give it): in ``folder``, else the one photo of that name in its subfolders (a drone's
    card keeps 100MEDIA/, 101MEDIA/, ...), looked up in ``index`` (name and stem -> photos; filled
    on the first miss); errors name ``where`` and ``what`` (the entry)."""
    try:
        return find_photo(folder, label, where, what)
    except InputError:
        if not index:
            for p in sorted(folder.rglob("*")):
                if p.suffix.lower() in IMAGE_EXTS and p.is_file():
                    index.setdefault(p.name, []).append(p)
                    index.setdefault(p.stem, []).append(p)
        found = index.get(label, [])
        if len(found) == 1:
            return found[0]
        if found:
            raise InputError(where, f"{what}: several photos of that name ("
                                    f"{', '.join(p.relative_to(folder).as_posix() for p in found[:4])}): rename "
                                    "them (and their entries in the camera file) to tell them apart") from None
        raise


def photo_folder(places: Iterable[Path | None]) -> Path | None:
    """The first ``images/`` (or ``Images/``) folder in ``places`` (None entries skipped), or None."""
    return next((d / f for d in places if d is not None for f in PHOTO_FOLDERS if (d / f).is_dir()), None)


def written_photo(written: str, folder: Path | None, where: Path, what: str,
                  index: dict[str, list[Path]]) -> tuple[Path, str, Path]:
    """(the photo, its name, the folder its mask is looked up in) of a photo that the file ``where``
    names by a path written where the reconstruction ran (Meshroom, OpenMVG): by that path's file
    name in ``folder`` (also in its subfolders: :func:`labelled_photo`) when there is one, else at
    the path as written (a relative one from ``where``'s folder)."""
    label = re.split(r"[\\/]", written)[-1]
    if folder is not None:
        photo = labelled_photo(folder, label, where, what, index)
        return photo, photo.relative_to(folder).as_posix(), folder
    photo = Path(written) if Path(written).is_absolute() else where.parent / written
    if not label or not photo.is_file():
        raise InputError(where, f"{what}: photo {written} not found (nor an images/ folder beside {where.name})")
    return photo, photo.name, photo.parent


def posed_frame(written: str, folder: Path | None, where: Path, what: str, index: dict[str, list[Path]],
                w2c: np.ndarray, lens: tuple[tuple[int, int], dict[str, float] | str]) -> Frame:
    """The frame of a posed view whose photo the file ``where`` names by a written path
    (:func:`written_photo`), with its camera's ``lens`` ((width, height), intrinsics), or
    InputError naming ``what`` when the lens is the reason it cannot be read (a string)."""
    size, intrinsics = lens
    if isinstance(intrinsics, str):
        raise InputError(where, f"{what}: {intrinsics}")
    photo, name, masks = written_photo(written, folder, where, what, index)
    return Frame(name=name, photo=photo, w2c=w2c, size=size, intrinsics=dict(intrinsics), part=None,
                 mask=find_mask(masks, name))


def reconstructed(frames: list[Frame], unposed: list[str], where: Path, hint: str) -> list[Frame]:
    """``frames`` sorted by name, the views without a pose (``unposed``) counted in the log;
    InputError with ``hint`` (which file to read instead) when no view has a pose."""
    if unposed:
        log.info("%s: %d views without a pose (not reconstructed) left out: %s%s", where, len(unposed),
                 ", ".join(unposed[:5]), " ..." if len(unposed) > 5 else "")
    if not frames:
        raise InputError(where, f"no reconstructed views (no view has a pose): {hint}")
    return sorted(frames, key=lambda f: f.name)


def layout_file(path: Path, find: Callable[[Path], Path | None], missing: str) -> Path:
    """``path`` when it is a layout's file, else the file ``find`` finds in the folder ``path``
    (InputError naming the folder with ``missing`` when there is none)."""
    if not path.is_dir():
        return path
    found = find(path)
    if found is None:
        raise InputError(path, missing)
    return found


def layout_json(path: Path, find: Callable[[Path], Path | None], missing: str, what: str,
                results: Callable[[Path], list[Path]], runs: str) -> tuple[Path, Path | None, object]:
    """(the layout's JSON file, the scene folder when ``path`` is one else None, the parsed JSON):
    :func:`layout_file`, and when the file found is the newest of several ``results(folder)``
    (a tool's ``runs``, newest first) the log says so; InputError naming the file when it is no
    readable JSON (``what``: the format's name)."""
    root = path if path.is_dir() else None
    path = layout_file(path, find, missing)
    several = results(root) if root is not None else []
    if path in several and len(several) > 1:
        log.info("%s: %d %s, reading the newest (%s)", root, len(several), runs, path.relative_to(root).as_posix())
    try:
        return path, root, json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"unreadable {what} file ({e})") from None
