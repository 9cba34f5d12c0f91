"""LEVIR-NVS scene layout: reading, writing and validation.

Layout of a scene folder::

    Images/NNN.png   RGB views (8- or 16-bit; also .jpg/.jpeg/.tif accepted)
    Cams/NNN.txt     "extrinsic", 4x4 world-to-camera (OpenCV axes), "intrinsic",
                     3x3 K in pixels, then "DEPTH_MIN DEPTH_MAX" (27 numbers)
    Depths/NNN.tiff  optional float32 z-depth (distance along the camera axis;
                     0 or non-finite = no depth). Depths/NNN.exr (channel "Z") also read.
    Track/NNN.txt    optional render-path cameras, same format as Cams/

Views 001-020 form the orbit; view 000 (near nadir) is in neither split by
default. The standard 3-view protocol trains on the orbit views at indices
0, 7 and 14 (001, 008, 015) and evaluates on the other 17.

Bad input raises :class:`~dibrgs_core.common.errors.InputError` naming the file.
This module needs numpy, Pillow, tifffile and OpenEXR, never torch or bpy.
"""
from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..camera.pinhole import Camera, camera_from_dict
from ..common.errors import InputError
from ..common.fileio import atomic_path, write_text

log = logging.getLogger("dibrgs.io_levir")

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
DEPTH_EXTS = (".tiff", ".tif", ".exr")
N_CAM_VALUES = 16 + 9 + 2


@dataclass
class View:
    """One input view.

    Attributes:
        camera: the view's camera (its ``name`` is the view id, e.g. ``"001"``).
        image: float32 (H, W, 3) RGB in [0, 1] (sRGB-encoded values as stored).
        depth: optional float32 (H, W) z-depth in world units; 0 where unknown.
    """

    camera: Camera
    image: np.ndarray
    depth: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.camera.name


@dataclass
class Scene:
    """A multi-view scene with its train/test split.

    Attributes:
        root: the folder it was read from.
        views: view id -> :class:`View`, sorted by id.
        track: render-path cameras (may be empty).
        train, test: view ids of the split.
    """

    root: Path
    views: dict[str, View]
    track: list[Camera] = field(default_factory=list)
    train: list[str] = field(default_factory=list)
    test: list[str] = field(default_factory=list)

    def train_views(self) -> list[View]:
        return [self.views[i] for i in self.train]

    def test_views(self) -> list[View]:
        return [self.views[i] for i in self.test]

    @property
    def cameras(self) -> list[Camera]:
        """Cameras of all views, sorted by id."""
        return [v.camera for v in self.views.values()]

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) shared by all views."""
        c = next(iter(self.views.values())).camera
        return c.width, c.height


# ---------------------------------------------------------------------------
# Split protocol
# ---------------------------------------------------------------------------
def orbit_ids(ids: Sequence[str]) -> list[str]:
    """The orbit views among ``ids``: all but the near-nadir view 000 of a 21-view LEVIR scene."""
    ids = sorted(ids)
    if len(ids) == 21 and ids[0] == "000":
        return ids[1:]
    return list(ids)


def default_split(ids: Sequence[str], n_train: int = 3) -> tuple[list[str], list[str]]:
    """LEVIR-NVS sparse-view protocol: ``n_train`` evenly spaced orbit views
    (indices ceil(i * n / n_train): 0, 7, 14 of 20) train, the other orbit views test."""
    orbit = orbit_ids(ids)
    if len(orbit) < 2:
        raise ValueError("need at least 2 orbit views for a train/test split")
    n_train = min(n_train, len(orbit) - 1)
    idx = sorted({math.ceil(i * len(orbit) / n_train) for i in range(n_train)})
    train = [orbit[i] for i in idx]
    return train, [i for i in orbit if i not in train]


def make_split(root: Path, ids: Sequence[str], train_ids: Iterable[str] | None,
               test_ids: Iterable[str] | None = None) -> tuple[list[str], list[str]]:
    """Train/test ids: the default protocol, or the given train ids (test = the other orbit views)."""
    if train_ids is None:
        if test_ids is not None:
            raise ValueError("test_ids needs train_ids")
        return default_split(ids)
    train = [_norm_id(i) for i in train_ids]
    missing = [i for i in train if i not in ids]
    if missing:
        raise InputError(root, f"train views {missing} not in the scene (views: {', '.join(ids)})")
    if test_ids is None:
        test = [i for i in orbit_ids(ids) if i not in train]
    else:
        test = [_norm_id(i) for i in test_ids]
        missing = [i for i in test if i not in ids]
        if missing:
            raise InputError(root, f"test views {missing} not in the scene")
    return train, test


def _norm_id(i: str | int) -> str:
    """Accept 8 or "8" or "008" for view 008."""
    s = str(i)
    return f"{int(s):03d}" if s.isdigit() and len(s) < 3 else s


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


def validate_camera_arrays(w2c: np.ndarray, K: np.ndarray, depth_range: tuple[float, float] | None,
                           path: Path | None) -> None:
    """Raise InputError unless w2c is a finite rigid transform and K a finite upper-triangular pinhole."""
    if not (np.isfinite(w2c).all() and np.isfinite(K).all()):
        raise InputError(path, "camera has NaN or infinite values")
    if depth_range is not None and not all(map(math.isfinite, depth_range)):
        raise InputError(path, f"depth range {depth_range} is not finite")
    if not np.allclose(w2c[3], [0, 0, 0, 1], atol=1e-6):
        raise InputError(path, f"extrinsic last row must be 0 0 0 1, got {w2c[3].tolist()}")
    R = w2c[:3, :3]
    det = float(np.linalg.det(R))
    if abs(det) < 1e-6:
        raise InputError(path, f"extrinsic rotation is singular (det {det:.3g})")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or det < 0:
        raise InputError(path, f"extrinsic rotation is not a rotation (det {det:.4g}, R R^T != I)")
    if abs(float(np.linalg.det(K))) < 1e-12 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"intrinsic matrix is singular or has non-positive focal length: {K.tolist()}")
    if not np.allclose(K[2], [0, 0, 1], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise InputError(path, f"intrinsic matrix must be upper-triangular with last row 0 0 1: {K.tolist()}")


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


# ---------------------------------------------------------------------------
# Images and depth maps
# ---------------------------------------------------------------------------
def _find(folder: Path, stem: str, exts: Sequence[str]) -> Path | None:
    for e in exts:
        p = folder / f"{stem}{e}"
        if p.is_file():
            return p
    return None


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from the image header."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, UnidentifiedImageError) as e:
        raise InputError(path, f"unreadable image ({e})") from None


def read_image(path: str | Path) -> np.ndarray:
    """Float32 (H, W, 3) RGB in [0, 1]; 16-bit images are scaled by 1/65535, alpha is dropped."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()  # decodes fully: truncated files fail here
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                a = np.asarray(im, dtype=np.float32) / 65535.0
                return np.repeat(a[..., None], 3, axis=2)
            return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise InputError(path, "image file not found") from None
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:
        raise InputError(path, f"unreadable or truncated image ({e})") from None


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8, rounded; NaN becomes 0 and values outside [0, 1] are clipped."""
    return np.round(np.clip(np.nan_to_num(np.asarray(image, dtype=np.float64)), 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write an 8-bit PNG from uint8 (H,W,3) or float in [0, 1] (rounded)."""
    from PIL import Image

    a = np.asarray(image)
    if a.dtype != np.uint8:
        a = to_uint8(a)
    with atomic_path(path) as tmp:
        Image.fromarray(a).save(tmp, format="PNG")


def read_depth(path: str | Path) -> np.ndarray:
    """Float32 (H, W) depth from .tiff/.tif (tifffile) or .exr (channel Z, else the first);
    non-finite values become 0 (no depth)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "depth file not found")
    try:
        if path.suffix.lower() == ".exr":
            d = read_depth_exr(path)
        else:
            import tifffile

            d = tifffile.imread(path)
    except InputError:
        raise
    except Exception as e:  # tifffile/OpenEXR raise many types for corrupt files
        raise InputError(path, f"unreadable depth map ({type(e).__name__}: {e})") from None
    d = np.asarray(d)
    if d.size == 0:
        raise InputError(path, "unreadable depth map (no pixel data)")
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise InputError(path, f"depth map must be 2-D, got shape {d.shape}")
    d = d.astype(np.float32)
    bad = ~np.isfinite(d)
    if bad.any():
        log.warning("%s: %d non-finite depth values set to 0", path, int(bad.sum()))
        d[bad] = 0.0
    return d


def write_depth_tiff(path: str | Path, depth: np.ndarray) -> None:
    """Write a float32 depth map as TIFF (atomically)."""
    import tifffile

    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, np.asarray(depth, dtype=np.float32))


def read_depth_exr(path: str | Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        key = "Z" if "Z" in ch else next((k for k in ch if k.endswith(".Z") or k.endswith(".V")), None)
        key = key or next(iter(ch))
        return np.asarray(ch[key].pixels, dtype=np.float32)


def write_depth_exr(path: str | Path, depth: np.ndarray) -> None:
    """Write a depth map as a 32-bit float EXR with a single channel ``Z`` (atomically)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, {"Z": np.ascontiguousarray(depth, dtype=np.float32)}) as f:
            f.write(str(tmp))


# ---------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------
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
    images = {p.stem: p for p in sorted(img_dir.iterdir()) if p.suffix.lower() in IMAGE_EXTS and p.is_file()
              and not p.name.startswith(".")}
    cams = {p.stem: p for p in sorted(cam_dir.glob("*.txt")) if not p.name.startswith(".")}
    if not images:
        raise InputError(img_dir, "no images found")
    for stem in sorted(set(images) - set(cams)):
        raise InputError(cam_dir / f"{stem}.txt", f"camera file missing for image {images[stem].name}")
    for stem in sorted(set(cams) - set(images)):
        raise InputError(img_dir / f"{stem}.png", f"image missing for camera {cams[stem].name}")
    use_depth = load_depth and dep_dir.is_dir()
    views: dict[str, View] = {}
    size: tuple[int, int] | None = None
    first = None
    for stem in sorted(images):
        img = read_image(images[stem])
        h, w = img.shape[:2]
        if size is None:
            size, first = (w, h), images[stem]
        elif (w, h) != size:
            raise InputError(images[stem], f"image is {w}x{h} but {first.name} is {size[0]}x{size[1]}")
        cam = read_cams_file(cams[stem], size=(w, h))
        depth = None
        if use_depth:
            dp = _find(dep_dir, stem, DEPTH_EXTS)
            if dp is None:
                raise InputError(dep_dir / f"{stem}.tiff", "depth map missing (Depths/ exists for this scene)")
            depth = read_depth(dp)
            if depth.shape != (h, w):
                raise InputError(dp, f"depth map is {depth.shape[1]}x{depth.shape[0]} but its image "
                                     f"{images[stem].name} is {w}x{h}")
        views[stem] = View(camera=cam, image=img, depth=depth)
    track = []
    if (root / "Track").is_dir():
        track = [read_cams_file(p, size=size) for p in sorted((root / "Track").glob("*.txt"))
                 if not p.name.startswith(".")]
    try:
        train, test = make_split(root, list(views), train_ids, test_ids)
    except ValueError as e:
        raise InputError(root, str(e)) from None
    log.info("read %s: %d views %dx%d, train %s, %d test, %d track cameras%s", root, len(views), size[0],
             size[1], train, len(test), len(track), ", with depth" if use_depth else "")
    return Scene(root=root, views=views, track=track, train=train, test=test)


def write_scene(root: str | Path, views: dict[str, View] | Iterable[View], track: Iterable[Camera] = ()) -> Path:
    """Write views (PNG, Cams, and depth as TIFF when present) and Track cameras in LEVIR layout."""
    root = Path(root)
    vs = list(views.values()) if isinstance(views, dict) else list(views)
    for v in vs:
        if not v.name:
            raise ValueError("every view's camera needs a name (its id)")
        write_png(root / "Images" / f"{v.name}.png", v.image)
        write_cams_file(root / "Cams" / f"{v.name}.txt", v.camera)
        if v.depth is not None:
            write_depth_tiff(root / "Depths" / f"{v.name}.tiff", v.depth)
    for k, c in enumerate(track):
        write_cams_file(root / "Track" / f"{c.name or f'{k:03d}'}.txt", c)
    return root


def read_any_scene(root: str | Path, train_ids: Iterable[str] | None = None, load_depth: bool = True,
                   test_ids: Iterable[str] | None = None) -> Scene:
    """Read a LEVIR-NVS folder (``Cams/``) or a COLMAP model (``sparse/0``, ``sparse`` or the folder itself)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "scene folder not found")
    if (root / "Cams").is_dir():
        return read_scene(root, train_ids=train_ids, load_depth=load_depth, test_ids=test_ids)
    from .colmap import find_colmap_model, read_colmap_scene

    if find_colmap_model(root) is not None:
        return read_colmap_scene(root, train_ids=train_ids, test_ids=test_ids)
    raise InputError(root, "not a scene: expected LEVIR-NVS Images/ + Cams/ or a COLMAP model "
                           "(cameras/images/points3D .bin or .txt in sparse/0, sparse/ or the folder)")
