"""Scenes in Bundler's format (``bundle.out`` with its image list), which Bundler and VisualSFM write
and Metashape, RealityCapture and OpenSfM export; parsed with the standard library into the frames
:mod:`.frame_layouts` makes a scene of (the library's reader and the add-on's description share both).

Accepted layout: a ``*.out`` file starting ``# Bundle file v0.3`` in the scene folder or its
``bundle/`` folder, and beside it the image list (``list.txt``, or the ``.out`` file's name with
``bundle`` read as ``list``): one line a camera, in the ``.out`` file's order, the photo's path first
(relative to the list's folder or the scene folder, else found by name in ``images/``). Masks as for
COLMAP (``masks/NAME.png`` beside the photos' folder).

Conventions (the Bundler manual's, "Output format and scene representation"): each camera is
``f k1 k2``, a 3x3 rotation R and a translation t with P = R X + t, looking down -z with +y up
(OpenGL camera axes, turned here into OpenCV's), and a pixel p' = f r(p) p about the image centre,
p = -P / P.z, r(p) = 1 + k1 |p|^2 + k2 |p|^4: a COLMAP ``RADIAL`` camera with its principal point
at the image centre, for a photo of any size. A camera with f = 0 was not registered and is left
out (counted in the log).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from .images import find_mask
from .photo_frame import Frame, find_photo, layout_file

log = logging.getLogger("dibrgs.io_bundler")

HEADER = "# Bundle file v0.3"
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


def _is_bundle(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.readline().strip().startswith(HEADER)
    except OSError:
        return False


def find_bundler(root: str | Path) -> Path | None:
    """The Bundler ``.out`` file of a scene folder (in it or in ``bundle/``), or None; InputError
    naming them when there are several."""
    root = Path(root)
    found = [p for d in (root, root / "bundle") if d.is_dir()
             for p in sorted(d.glob("*.out")) if p.is_file() and _is_bundle(p)]
    if len(found) > 1:
        raise InputError(root, f"several Bundler files ({', '.join(p.name for p in found)}): keep one")
    return found[0] if found else None


def _image_list(out: Path) -> Path:
    names = ["list.txt", out.name.replace("bundle", "list"), out.stem.replace("bundle", "list") + ".txt"]
    found = next((out.parent / n for n in names if n != out.name and (out.parent / n).is_file()), None)
    if found is None:
        raise InputError(out, f"no image list beside it ({', '.join(dict.fromkeys(names))})")
    return found


def read_bundler_frames(path: str | Path) -> list[Frame]:
    """The frames of a Bundler file, or of the one in a scene folder (InputError naming the file
    when malformed, or a camera's photo when it is missing)."""
    path = Path(path)
    root = path if path.is_dir() else path.parent
    path = layout_file(path, find_bundler, f"no Bundler file ({HEADER})")
    if root.name == "bundle" and path.parent == root:
        root = root.parent
    cams = _cameras(path)
    n = len(cams)
    listing = _image_list(path)
    names = [ln.split()[0] for ln in listing.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    if len(names) != n:
        raise InputError(listing, f"{len(names)} photos listed for {n} cameras in {path.name}")
    images = next((root / d for d in ("images", "Images") if (root / d).is_dir()), root)
    frames, unregistered = [], []
    for k, (name, c) in enumerate(zip(names, cams)):
        f, k1, k2 = c[:3]
        if f == 0.0:
            unregistered.append(name)
            continue
        if f < 0.0:
            raise InputError(path, f"camera {k} ({name}): focal length {f} is negative")
        R, t = c[3:12].reshape(3, 3), c[12:15]
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = _OPENGL_TO_OPENCV @ R, _OPENGL_TO_OPENCV @ t
        photo = _photo(name.replace("\\", "/"), (listing.parent, root, images), path, k)
        rel = photo.relative_to(images).as_posix() if photo.is_relative_to(images) else photo.name
        frames.append(Frame(name=rel, photo=photo, w2c=w2c, size=None, intrinsics={
            "fl_x": float(f), "fl_y": float(f), "k1": float(k1), "k2": float(k2)}, part=None,
            mask=find_mask(photo.parent, photo.name)))
    if unregistered:
        log.info("%s: %d cameras not registered (f = 0) left out: %s%s", path, len(unregistered),
                 ", ".join(unregistered[:5]), " ..." if len(unregistered) > 5 else "")
    if not frames:
        raise InputError(path, "no registered cameras (every f is 0)")
    return frames


def _cameras(path: Path) -> np.ndarray:
    """The (n, 15) camera entries of a Bundler file (f, k1, k2, R row-major, t), reading no further
    than the cameras (the points that follow can be large)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = (ln for ln in f if ln.strip() and not ln.lstrip().startswith("#"))
            head = next(lines, "").split()
            if len(head) != 2 or not all(s.isdigit() for s in head) or int(head[0]) <= 0:
                raise InputError(path, "expected <num_cameras> <num_points> after the header")
            n = int(head[0])
            values = [float(v) for _, ln in zip(range(5 * n), lines) for v in ln.split()]
    except OSError as e:
        raise InputError(path, f"unreadable Bundler file ({e})") from None
    except ValueError:
        raise InputError(path, "a camera entry holds something else than numbers") from None
    if len(values) != 15 * n or not np.isfinite(values).all():
        raise InputError(path, f"{n} cameras announced, {len(values) // 15} given")
    return np.asarray(values, np.float64).reshape(n, 15)


def _photo(name: str, folders: tuple[Path, ...], where: Path, k: int) -> Path:
    """The listed photo: relative to the list's folder or the scene folder, else by its file name in
    the photos' folder (the last of ``folders``)."""
    for folder in folders[:-1]:
        if (folder / name).is_file():
            return folder / name
    return find_photo(folders[-1], Path(name).name, where, f"camera {k}")
