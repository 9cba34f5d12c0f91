"""COLMAP ``cameras`` and ``images`` files (text or binary), read with numpy and struct.

The library reads COLMAP models through pycolmap (``data.colmap``); Blender's
Python has no pycolmap, and importing a scene into Blender only needs the
posed pinhole cameras, so this module parses the two documented file formats
(https://colmap.github.io/format.html) itself. ``tests/bridge/test_bridge.py``
checks it against pycolmap on text and binary models.

As the library reads it, the binary model is read when ``cameras.bin`` and
``images.bin`` exist, else the text model; ``points3D`` may be missing (the
points themselves are not read). Cameras with lens distortion become the pinhole
camera the library trains them as (:meth:`ColmapCamera.pinhole`: COLMAP's
undistorter's choice, computed here with numpy; the library asks pycolmap).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from ..data.undistort import DISTORTED_MODELS, PINHOLE_MODELS, unsupported_model

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
#: Models whose focal lengths and principal point come first as (f, cx, cy).
_SINGLE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"}


@dataclass
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray

    @property
    def distortion(self) -> np.ndarray:
        return self.params[list(_BY_NAME[self.model][2])]

    def K(self) -> np.ndarray:
        """3x3 intrinsics (focal lengths and principal point; distortion not included)."""
        p = self.params
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if self.model in _SINGLE_FOCAL else p[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def pinhole(self, where: Path) -> "ColmapCamera":
        """The pinhole camera the library trains this one as (``data.colmap``): itself when it has
        no distortion, else the ``PINHOLE`` camera of its undistorted photos as COLMAP's undistorter
        chooses it with its default options (focal lengths kept; width, height and principal point
        scaled so that no blank pixels show, the scale kept within [0.2, 2]). InputError for models
        that are not perspective (fisheye and others), as the library."""
        if self.model not in PINHOLE_MODELS and self.model not in DISTORTED_MODELS:
            raise InputError(where, unsupported_model(self.camera_id, self.model))
        if not np.any(self.distortion != 0):
            return self
        K = self.K()
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        W, H = self.width, self.height
        xs, ys = np.arange(W) + 0.5, np.arange(H) + 0.5
        big = np.finfo(np.float64).max

        def border(x, y, axis: int, largest: bool) -> float:
            """The largest (smallest) undistorted coordinate of a border's pixels; where none can be
            undistorted (strong distortion has no inverse there), -big (big), as COLMAP."""
            u, v = _undistort(self.model, self.distortion, (x - cx) / fx, (y - cy) / fy)
            px = (fx * u + cx, fy * v + cy)[axis][np.isfinite(u) & np.isfinite(v)]
            return (px.max() if largest else px.min()) if px.size else (-big if largest else big)

        # the scales that show no blank pixel (COLMAP's blank_pixels = 0), within [0.2, 2]
        scale_x = 1.0 / max(cx / (cx - border(0.5, ys, 0, True)),
                            (W - 0.5 - cx) / (border(W - 0.5, ys, 0, False) - cx))
        scale_y = 1.0 / max(cy / (cy - border(xs, 0.5, 1, True)),
                            (H - 0.5 - cy) / (border(xs, H - 0.5, 1, False) - cy))
        scale_x, scale_y = (min(max(s, 0.2), 2.0) for s in (scale_x, scale_y))
        W2, H2 = int(max(1.0, scale_x * W)), int(max(1.0, scale_y * H))
        return ColmapCamera(self.camera_id, "PINHOLE", W2, H2, np.array([fx, fy, cx * W2 / W, cy * H2 / H]))


def _distortion(model: str, k: np.ndarray, u: np.ndarray, v: np.ndarray):
    """The offsets (du, dv) COLMAP's perspective ``model`` with distortion parameters ``k`` adds to
    points (u, v) of the normalised image plane, and their Jacobian (d du/du, d du/dv, d dv/du,
    d dv/dv). Every such model is du = u R(r^2) + 2 p1 u v + p2 (r^2 + 2 u^2), dv alike, with a
    radial term R (FULL_OPENCV's rational factor minus 1) and tangential p1, p2 (OPENCV's)."""
    u2, v2, uv = u * u, v * v, u * v
    r2 = u2 + v2
    p1 = p2 = 0.0
    if model == "SIMPLE_RADIAL":
        R, dR = k[0] * r2, k[0]
    elif model in ("RADIAL", "OPENCV"):
        R, dR = k[0] * r2 + k[1] * r2 * r2, k[0] + 2 * k[1] * r2
        if model == "OPENCV":
            p1, p2 = k[2], k[3]
    else:  # FULL_OPENCV: k1, k2, p1, p2, k3, k4, k5, k6
        k1, k2, p1, p2, k3, k4, k5, k6 = k[:8]
        N, D = 1 + r2 * (k1 + r2 * (k2 + r2 * k3)), 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dN, dD = k1 + r2 * (2 * k2 + 3 * k3 * r2), k4 + r2 * (2 * k5 + 3 * k6 * r2)
        R, dR = N / D - 1, (dN * D - N * dD) / (D * D)
    du = u * R + 2 * p1 * uv + p2 * (r2 + 2 * u2)
    dv = v * R + 2 * p2 * uv + p1 * (r2 + 2 * v2)
    cross = 2 * uv * dR + 2 * p1 * u + 2 * p2 * v
    return du, dv, (R + 2 * u2 * dR + 2 * p1 * v + 6 * p2 * u, cross,
                    cross, R + 2 * v2 * dR + 2 * p2 * u + 6 * p1 * v)


def _undistort(model: str, k: np.ndarray, u0: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points of the normalised plane whose distorted images are (u0, v0), found as COLMAP finds
    them: Newton steps limited to a trust region (a step at most 0.1 max(1, |x|) long), at most
    100 of them, a point done when its step's squared length is below 1e-10; NaN where that does
    not converge (strong distortion has no inverse near the image's border)."""
    u0, v0 = np.broadcast_arrays(np.asarray(u0, np.float64), np.asarray(v0, np.float64))
    u, v = u0.copy(), v0.copy()
    active = np.ones(u.shape, bool)
    with np.errstate(all="ignore"):
        for _ in range(100):
            idx = np.flatnonzero(active)
            if idx.size == 0:
                break
            x, y = u.flat[idx], v.flat[idx]
            dx, dy, (a, b, c, d) = _distortion(model, k, x, y)
            a, d = a + 1, d + 1
            rx, ry = x + dx - u0.flat[idx], y + dy - v0.flat[idx]
            det = a * d - b * c
            sx, sy = (d * rx - b * ry) / det, (a * ry - c * rx) / det
            n2, radius2 = sx * sx + sy * sy, np.maximum((x * x + y * y) * 0.01, 0.01)
            shrink = np.where(n2 > radius2, np.sqrt(radius2 / n2), 1.0)
            sx, sy = sx * shrink, sy * shrink
            u.flat[idx], v.flat[idx] = x - sx, y - sy
            done = ~(sx * sx + sy * sy >= 1e-10)  # converged, or NaN (left as NaN)
            active.flat[idx[done]] = False
    u[active], v[active] = np.nan, np.nan  # no convergence: no inverse there
    return u, v


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
    except (OSError, ValueError, KeyError, IndexError, OverflowError, struct.error, UnicodeDecodeError) as e:
        raise InputError(model_dir, f"unreadable COLMAP model ({type(e).__name__}: {e})") from None


def missing_camera(cams: dict[int, ColmapCamera], images: list[ColmapImage]) -> str | None:
    """The line for the first image (by name) whose camera id is not among ``cams``, else None."""
    im = min((im for im in images if im.camera_id not in cams), key=lambda im: im.name, default=None)
    return None if im is None else f"image {im.name} refers to camera {im.camera_id}, which is not in the model"


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
