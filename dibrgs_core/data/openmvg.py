"""Scenes as OpenMVG leaves them: an ``sfm_data.json`` (cereal's JSON of OpenMVG's SfM_Data; the
reconstruction's binary ``sfm_data.bin`` converted with ``openMVG_main_ConvertSfM_DataFormat``),
parsed with the standard library into the frames :mod:`.frame_layouts` makes a scene of (the
library's reader and the add-on's description share both).

Accepted layouts: a folder holding ``sfm_data.json``, or an OpenMVG output folder whose
``reconstruction*/sfm_data.json`` holds the poses (the newest of several, named in the log).
Photos: ``images/`` (or ``Images/``) beside the file or the scene folder, by file name (also in
subfolders where the name is unique), else ``root_path/local_path/filename`` as written.

Conventions (OpenMVG's ``Pose3`` and camera classes and their cereal I/O, ``sfm_data_version`` 0.2
and 0.3): an extrinsic's ``rotation`` is row-major and takes world to camera coordinates with
OpenCV axes (+x right, +y down, looking along +z), ``center`` is the camera centre, so w2c =
[R | -R C]. Intrinsics: ``focal_length`` in pixels (square pixels), ``principal_point`` in pixels
in COLMAP's convention (OpenMVG's own COLMAP export writes it unchanged); ``pinhole``,
``pinhole_radial_k1`` (``disto_k1``), ``pinhole_radial_k3`` (``disto_k3``: k1, k2, k3) and
``pinhole_brown_t2`` (``disto_t2``: k1, k2, k3, t1, t2; t1 is OpenCV's p1) in normalised camera
coordinates; fisheye and spherical cameras are refused when a posed view uses them. cereal names a
polymorphic type once (``polymorphic_name`` with the id's high bit set) and refers to it by id
after. Views without a pose are left out and counted in the log.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from .photo_frame import Frame, layout_json, photo_folder, posed_frame, reconstructed

OPENMVG_FILE = "sfm_data.json"
#: cereal's flag on a polymorphic id that comes with its type's name (the type's first instance).
_NEW_TYPE = 0x80000000
_DISTORTION = {"pinhole": (None, ()), "pinhole_radial_k1": ("disto_k1", ("k1",)),
               "pinhole_radial_k3": ("disto_k3", ("k1", "k2", "k3")),
               "pinhole_brown_t2": ("disto_t2", ("k1", "k2", "k3", "p1", "p2"))}


def is_openmvg(data: object) -> bool:
    """Whether parsed JSON is an OpenMVG SfM_Data file (an object with "sfm_data_version")."""
    return isinstance(data, dict) and "sfm_data_version" in data


def reconstructions(root: Path) -> list[Path]:
    """The ``reconstruction*/sfm_data.json`` files of an OpenMVG output folder, newest first."""
    return sorted(root.glob(f"reconstruction*/{OPENMVG_FILE}"), key=lambda p: p.stat().st_mtime, reverse=True)


def find_openmvg(root: str | Path) -> Path | None:
    """The ``sfm_data.json`` of a scene folder, else the newest of its ``reconstruction*/``, else None."""
    root = Path(root)
    if (root / OPENMVG_FILE).is_file():
        return root / OPENMVG_FILE
    found = reconstructions(root)
    return found[0] if found else None


def binary_sfm_data(root: Path) -> InputError | None:
    """The error for a folder that holds OpenMVG's binary ``sfm_data.bin`` (its reconstruction's
    default) and no JSON: how to convert it; else None."""
    binary = sorted(root.glob("sfm_data.bin")) + sorted(root.glob("reconstruction*/sfm_data.bin"))
    if not binary:
        return None
    return InputError(binary[0], "OpenMVG's binary format: convert it with openMVG_main_ConvertSfM_DataFormat "
                                 f"-i {binary[0].name} -o {OPENMVG_FILE} (beside it)")


def _numbers(v: object, n: int, where: Path, what: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
        raise InputError(where, f"{what} must be {n} finite numbers, got {v!r}")
    return np.array(v, np.float64)


def _entries(data: dict, key: str, where: Path) -> list[tuple[int, dict]]:
    """(key, value) of a cereal map serialised as a list of {"key", "value"} objects."""
    items = data.get(key, [])
    if not isinstance(items, list) or not all(isinstance(i, dict) and isinstance(i.get("key"), int)
                                              and isinstance(i.get("value"), dict) for i in items):
        raise InputError(where, f"{key}: expected a list of {{\"key\", \"value\"}} objects with integer keys")
    return [(i["key"], i["value"]) for i in items]


def _pointer_data(value: dict, where: Path, what: str) -> dict:
    wrapper = value.get("ptr_wrapper")
    data = wrapper.get("data") if isinstance(wrapper, dict) else None
    if not isinstance(data, dict):
        raise InputError(where, f"{what}: no ptr_wrapper data")
    return data


def _intrinsics(data: dict, where: Path) -> dict[int, tuple[tuple[int, int], dict[str, float] | str]]:
    """Each intrinsic's ((width, height), intrinsics in pixels with OpenCV's distortion), or the
    reason it cannot be read (raised when a posed view uses it)."""
    names: dict[int, str] = {}
    out = {}
    for key, value in _entries(data, "intrinsics", where):
        pid = value.get("polymorphic_id")
        if not isinstance(pid, int):
            raise InputError(where, f"intrinsic {key}: polymorphic_id must be an integer, got {pid!r}")
        if "polymorphic_name" in value:
            names[pid & ~_NEW_TYPE] = str(value["polymorphic_name"])
        kind = names.get(pid & ~_NEW_TYPE)
        d = _pointer_data(value, where, f"intrinsic {key}")
        try:
            size = (int(d["width"]), int(d["height"]))
        except (KeyError, TypeError, ValueError, OverflowError):
            size = (0, 0)
        if min(size) <= 0:
            raise InputError(where, f"intrinsic {key}: width and height must be positive integers, got "
                                    f"{d.get('width')!r}, {d.get('height')!r}")
        if kind not in _DISTORTION:
            out[key] = size, (f"camera model {kind} is not supported (supported: {', '.join(_DISTORTION)}); "
                              "undistort fisheye and spherical photos first")
            continue
        f = float(_numbers([d.get("focal_length")], 1, where, f"intrinsic {key}: focal_length")[0])
        pp = _numbers(d.get("principal_point"), 2, where, f"intrinsic {key}: principal_point")
        if not f > 0.0:
            out[key] = size, f"intrinsic {key}: focal length must be positive, got {f}"
            continue
        field, keys = _DISTORTION[kind]
        k = _numbers(d.get(field), len(keys), where, f"intrinsic {key}: {field}") if field else []
        out[key] = size, {"fl_x": f, "fl_y": f, "cx": float(pp[0]), "cy": float(pp[1]),
                          **dict(zip(keys, map(float, k)))}
    return out


def read_openmvg_frames(path: str | Path) -> list[Frame]:
    """The frames of an OpenMVG ``sfm_data.json``, or of the one in a scene folder or OpenMVG output
    folder (InputError naming the file when malformed, or a view's photo when it is missing)."""
    path, root, data = layout_json(Path(path), find_openmvg, f"no OpenMVG {OPENMVG_FILE} (or "
                                   f"reconstruction*/{OPENMVG_FILE})", "SfM_Data", reconstructions, "reconstructions")
    if not is_openmvg(data):
        raise InputError(path, "expected an OpenMVG SfM_Data object with \"sfm_data_version\"")
    intrinsics = _intrinsics(data, path)
    poses = {}
    for key, value in _entries(data, "extrinsics", path):
        rows = value.get("rotation")
        rows_ok = isinstance(rows, list) and all(isinstance(r, list) for r in rows)
        flat = [x for r in rows for x in r] if rows_ok else None
        R = _numbers(flat, 9, path, f"extrinsic {key}: rotation (three rows of three)").reshape(3, 3)
        C = _numbers(value.get("center"), 3, path, f"extrinsic {key}: center")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0.0:
            raise InputError(path, f"extrinsic {key}: rotation is not a rotation matrix")
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ C
        poses[key] = w2c
    # images/ of the scene folder, of the file's folder or of the output folder above reconstruction*/
    folder = photo_folder([root, path.parent] + ([path.parent.parent] if path.parent.name.startswith("reconstruction")
                                                 else []))
    frames, unposed, index = [], [], {}
    for key, value in _entries(data, "views", path):
        v = _pointer_data(value, path, f"view {key}")
        filename = str(v.get("filename", ""))
        ids = v.get("id_pose"), v.get("id_intrinsic")
        if not all(isinstance(i, int) for i in ids):
            raise InputError(path, f"view {filename or key}: id_pose and id_intrinsic must be integers, got {ids}")
        pose = poses.get(v.get("id_pose"))
        if pose is None:
            unposed.append(filename or str(key))
            continue
        iid = v.get("id_intrinsic")
        lens = intrinsics.get(iid, ((0, 0), f"intrinsic {iid} is not in the file"))
        written = str(Path(str(data.get("root_path", ""))) / str(v.get("local_path", "")) / filename)
        frames.append(posed_frame(written, folder, path, f"view {filename}", index, pose, lens))
    return reconstructed(frames, unposed, path, f"read the reconstruction's {OPENMVG_FILE}, not the one "
                                                "SfMInit_ImageListing writes")
