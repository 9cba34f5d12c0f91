"""COLMAP ``cameras`` and ``images`` files (text or binary), read with numpy and struct.

The library reads COLMAP models through pycolmap (``data.colmap``); Blender's
Python has no pycolmap, and importing a scene into Blender only needs the
posed pinhole cameras, so this module parses the two documented file formats
(https://colmap.github.io/format.html) itself. ``tests/bridge/test_bridge.py``
checks it against pycolmap on text and binary models.

As the library reads it, the binary model is read when ``cameras.bin`` and
``images.bin`` exist, else the text model; ``points3D`` may be missing (the
points themselves are not read).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..common.errors import InputError

#: COLMAP camera models: id -> (name, number of parameters, indices of the distortion parameters).
MODELS: dict[int, tuple[str, int, tuple[int, ...]]] = {
    0: ("SIMPLE_PINHOLE", 3, ()),
    1: ("PINHOLE", 4, ()),
    2: ("SIMPLE_RADIAL", 4, (3,)),
    3: ("RADIAL", 5, (3, 4)),
    4: ("OPENCV", 8, (4, 5, 6, 7)),
    5: ("OPENCV_FISHEYE", 8, (4, 5, 6, 7)),
    6: ("FULL_OPENCV", 12, tuple(range(4, 12))),
    7: ("FOV", 5, (4,)),
    8: ("SIMPLE_RADIAL_FISHEYE", 4, (3,)),
    9: ("RADIAL_FISHEYE", 5, (3, 4)),
    10: ("THIN_PRISM_FISHEYE", 12, tuple(range(4, 12))),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16, tuple(range(4, 16))),
}
_BY_NAME = {name: (mid, n, extra) for mid, (name, n, extra) in MODELS.items()}
#: Models whose focal lengths and principal point come first as (f, cx, cy) ...
_SINGLE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"}
#: ... and the perspective models that are pinholes when their distortion is 0 (as in data.colmap).
PINHOLE_LIKE = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"}


@dataclass
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray

    def K(self, where: Path) -> np.ndarray:
        """3x3 intrinsics; InputError for non-pinhole models or non-zero distortion."""
        if self.model not in PINHOLE_LIKE:
            raise InputError(where, f"camera {self.camera_id}: model {self.model} is not a pinhole model")
        extra = self.params[list(_BY_NAME[self.model][2])]
        if np.any(extra != 0):
            raise InputError(where, f"camera {self.camera_id}: model {self.model} has distortion "
                                    f"{extra.tolist()}; undistort the images first (colmap image_undistorter)")
        p = self.params
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if self.model in _SINGLE_FOCAL else p[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@dataclass
class ColmapImage:
    image_id: int
    qvec: np.ndarray  # (w, x, y, z), camera from world
    tvec: np.ndarray
    camera_id: int
    name: str

    def w2c(self) -> np.ndarray:
        """4x4 world-to-camera (OpenCV axes, COLMAP's own convention)."""
        w, x, y, z = self.qvec / np.linalg.norm(self.qvec)
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, self.tvec
        return T


def model_format(model_dir: Path) -> str:
    """``"bin"`` or ``"txt"``, the files pycolmap would read; InputError naming a missing file."""
    for ext in ("bin", "txt"):  # points3D may be absent: nothing here reads it
        if all((model_dir / f"{stem}.{ext}").is_file() for stem in ("cameras", "images")):
            return ext
    for stem in ("cameras", "images"):
        if not any((model_dir / f"{stem}.{e}").is_file() for e in ("bin", "txt")):
            raise InputError(model_dir / f"{stem}.bin", "COLMAP model file missing")
    raise InputError(model_dir, "COLMAP model mixes .bin and .txt files")


def read_model(model_dir: str | Path) -> tuple[dict[int, ColmapCamera], list[ColmapImage]]:
    """Cameras by id and images (in file order) of the model in ``model_dir``."""
    model_dir = Path(model_dir)
    ext = model_format(model_dir)
    try:
        if ext == "bin":
            return _cameras_bin(model_dir / "cameras.bin"), _images_bin(model_dir / "images.bin")
        return _cameras_txt(model_dir / "cameras.txt"), _images_txt(model_dir / "images.txt")
    except InputError:
        raise
    except (OSError, ValueError, KeyError, IndexError, struct.error, UnicodeDecodeError) as e:
        raise InputError(model_dir, f"unreadable COLMAP model ({type(e).__name__}: {e})") from None


def _data_lines(path: Path):
    for line in path.read_text().splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            yield s


def _camera(cid: int, model: str, w: int, h: int, params: list[float], where: Path) -> ColmapCamera:
    if model not in _BY_NAME:
        raise InputError(where, f"camera {cid}: unknown camera model {model}")
    if len(params) != _BY_NAME[model][1]:
        raise InputError(where, f"camera {cid}: model {model} needs {_BY_NAME[model][1]} parameters, "
                                f"found {len(params)}")
    return ColmapCamera(cid, model, int(w), int(h), np.asarray(params, dtype=np.float64))


def _cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    out = {}
    for s in _data_lines(path):
        t = s.split()
        cid = int(t[0])
        out[cid] = _camera(cid, t[1], int(t[2]), int(t[3]), [float(x) for x in t[4:]], path)
    return out


def _images_txt(path: Path) -> list[ColmapImage]:
    # Two lines per image; the second (2D points) may be empty, so only the
    # first of each pair may skip blank and comment lines (as COLMAP's reader).
    lines = path.read_text().splitlines()
    out, k = [], 0
    while k < len(lines):
        s = lines[k].strip()
        k += 1
        if not s or s.startswith("#"):
            continue
        t = s.split(maxsplit=9)
        if len(t) < 10:
            raise InputError(path, f"line {k}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        v = [float(x) for x in t[1:8]]
        out.append(ColmapImage(int(t[0]), np.array(v[:4]), np.array(v[4:]), int(t[8]), t[9]))
        k += 1  # the 2D points line
    return out


def _cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    data = path.read_bytes()
    (n,), off = struct.unpack_from("<Q", data, 0), 8
    out = {}
    for _ in range(n):
        cid, mid, w, h = struct.unpack_from("<iiQQ", data, off)
        off += 24
        if mid not in MODELS:
            raise InputError(path, f"camera {cid}: unknown camera model id {mid}")
        name, npar, _ = MODELS[mid]
        params = struct.unpack_from(f"<{npar}d", data, off)
        off += 8 * npar
        out[cid] = _camera(cid, name, w, h, list(params), path)
    return out


def _images_bin(path: Path) -> list[ColmapImage]:
    data = path.read_bytes()
    (n,), off = struct.unpack_from("<Q", data, 0), 8
    out = []
    for _ in range(n):
        iid, *v = struct.unpack_from("<I7d", data, off)
        off += 4 + 56
        (cid,) = struct.unpack_from("<I", data, off)
        off += 4
        end = data.index(b"\x00", off)
        name = data[off:end].decode("utf-8")
        off = end + 1
        (npts,) = struct.unpack_from("<Q", data, off)
        off += 8 + 24 * npts  # (x, y, point3D_id) per observation
        out.append(ColmapImage(iid, np.array(v[:4]), np.array(v[4:]), cid, name))
    return out
