"""Scenes as Meshroom (AliceVision) leaves them: an SfMData JSON file (``cameras.sfm``, the
StructureFromMotion node's "Views and Poses" output, or any ``.sfm`` / ``.json`` of that format),
parsed with the standard library into the frames :mod:`.frame_layouts` makes a scene of (the
library's reader and the add-on's description share both).

Accepted layouts: a folder holding ``cameras.sfm`` (else its only ``.sfm`` file or SfMData
``.json``, as the ConvertSfMFormat node writes it), or a Meshroom
project folder (``MeshroomCache/StructureFromMotion/<id>/cameras.sfm``; the newest of several,
named in the log). Photos: ``images/`` (or ``Images/``) beside the file or the project, by the file
name of each view's ``path`` (also in subfolders where the name is unique), else the ``path`` as
written (Meshroom writes where it read the photo). Masks as for COLMAP (``masks/NAME.png``).

Conventions (AliceVision's sfmDataIO, file versions 1.0 to 1.2.11; its ``jsonIO.cpp`` and
``CHANGES.md``): matrices are stored column-major (Eigen's order); a pose's ``rotation`` takes world
to camera coordinates with OpenCV axes (+x right, +y down, looking along +z) and ``center`` is the
camera centre in the world, so w2c = [R | -R C]; a view of a rig whose pose is not independent is
placed by its sub-pose after the rig's pose. Intrinsics: the principal point is in pixels from the
image centre since version 1.2.1 (from the top-left corner before), in COLMAP's convention once
w / 2 and h / 2 are added (AliceVision's own COLMAP export writes it so); the focal length is in
pixels (``pxFocalLength``) before 1.2.2 and in millimetres over ``sensorWidth`` (36 when absent)
across the image width since, with ``pixelRatio`` read as each version defines it. Distortion in
normalised camera coordinates: ``radialk1`` (k1), ``radialk3`` (k1, k2, k3) and ``brown`` (k1, k2,
k3, t1, t2, where t1 is OpenCV's p1 and t2 its p2); equidistant (fisheye) cameras, fisheye
distortions and 3DEqualizer undistortion models are refused when a reconstructed view uses them.
Views without a pose (not reconstructed) are left out and counted in the log.
"""
from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from .photo_frame import Frame, layout_json, photo_folder, posed_frame, reconstructed

log = logging.getLogger("dibrgs.io_meshroom")

MESHROOM_FILE = "cameras.sfm"
#: Where a Meshroom project keeps its reconstructions' cameras.
CACHE_GLOB = f"MeshroomCache/StructureFromMotion/*/{MESHROOM_FILE}"
#: The newest SfMData file version whose conventions this reader follows; newer files are read so.
KNOWN_VERSION = (1, 2, 11)
_DISTORTION_PARAMS = {"none": (), "radialk1": ("k1",), "radialk3": ("k1", "k2", "k3"),
                      "brown": ("k1", "k2", "k3", "p1", "p2")}
#: The single ``type`` string of files before version 1.2.8 -> (camera type, distortion, undistortion).
_OLD_TYPES = {"pinhole": ("pinhole", "none", "none"), "radial1": ("pinhole", "radialk1", "none"),
              "radial3": ("pinhole", "radialk3", "none"), "brown": ("pinhole", "brown", "none"),
              "fisheye4": ("pinhole", "fisheye", "none"), "fisheye1": ("pinhole", "fisheye1", "none"),
              "3deanamorphic4": ("pinhole", "none", "3deanamorphic4"), "equidistant": ("equidistant", "none", "none"),
              "equidistant_r3": ("equidistant", "radialk3pt", "none")}


def is_sfm_data(data: object) -> bool:
    """Whether parsed JSON is an AliceVision SfMData file (an object with "version" and "views")."""
    return isinstance(data, dict) and "version" in data and "views" in data


def cache_results(root: Path) -> list[Path]:
    """The ``cameras.sfm`` files of a Meshroom project's StructureFromMotion nodes, newest first."""
    return sorted(root.glob(CACHE_GLOB), key=lambda p: p.stat().st_mtime, reverse=True)


def _sniffed_sfm_data(path: Path) -> bool:
    """Whether a ``.json`` file starts as an AliceVision SfMData file does (its "version" and "views"
    come first, before any large structure)."""
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError:
        return False
    return head.lstrip().startswith(b"{") and b'"version"' in head and b'"views"' in head


def find_meshroom(root: str | Path) -> Path | None:
    """The SfMData file of a scene folder: ``cameras.sfm``, else its only ``.sfm`` file or SfMData
    ``.json`` (ConvertSfMFormat's; InputError naming them when there are several), else the newest
    in its ``MeshroomCache``, else None."""
    root = Path(root)
    if (root / MESHROOM_FILE).is_file():
        return root / MESHROOM_FILE
    found = sorted(p for p in root.glob("*") if p.is_file() and (
        p.suffix.lower() == ".sfm" or (p.suffix.lower() == ".json" and _sniffed_sfm_data(p))))
    if len(found) > 1:
        raise InputError(root, f"several Meshroom SfMData files ({', '.join(p.name for p in found)}): "
                               f"name the one to read {MESHROOM_FILE}")
    if found:
        return found[0]
    cached = cache_results(root)
    return cached[0] if cached else None


def _number(v: object, where: Path, what: str) -> float:
    """A finite number as AliceVision writes it (a JSON string) or as other tools do (a number)."""
    if isinstance(v, str):
        try:
            v = float(v)
        except ValueError:
            pass
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(where, f"{what} must be a finite number, got {v!r}")
    return float(v)


def _numbers(v: object, n: int | None, where: Path, what: str) -> np.ndarray:
    """A list of ``n`` finite numbers (any count when ``n`` is None; "" is AliceVision's empty list)."""
    if v == "":
        v = []
    if not isinstance(v, list) or (n is not None and len(v) != n):
        raise InputError(where, f"{what} must be a list of {n if n is not None else 'some'} numbers, got {v!r}")
    return np.array([_number(x, where, what) for x in v], np.float64)


def _flag(v: object) -> bool:
    return str(v).strip().lower() in ("true", "1")


def _version(data: dict, where: Path) -> tuple[int, int, int]:
    try:
        version = tuple(int(str(x)) for x in data["version"])
    except (TypeError, ValueError):
        version = ()
    if len(version) != 3:
        raise InputError(where, f"version must be three numbers (major, minor, revision), got {data['version']!r}")
    if version > KNOWN_VERSION:
        log.info("%s: SfMData version %s is newer than %s, read with that version's conventions", where,
                 ".".join(map(str, version)), ".".join(map(str, KNOWN_VERSION)))
    return version


def _intrinsics(intr: dict, version: tuple[int, int, int],
                where: Path) -> tuple[tuple[int, int], dict[str, float] | str]:
    """((width, height), intrinsics in pixels with OpenCV's distortion) of an AliceVision intrinsic,
    or the reason it cannot be read as a string (raised when a reconstructed view uses it)."""
    iid = intr.get("intrinsicId", "?")

    def number(key: str, default: float | None = None) -> float:
        if key not in intr and default is not None:
            return default
        return _number(intr.get(key), where, f"intrinsic {iid}: {key}")

    w, h = int(number("width")), int(number("height"))
    if w <= 0 or h <= 0:
        raise InputError(where, f"intrinsic {iid}: width and height must be positive, got {w}x{h}")
    kind = str(intr.get("type", "")).lower()
    if version < (1, 2, 8):
        if kind not in _OLD_TYPES:
            return (w, h), f"camera type {kind!r} is not known"
        kind, dist, undist = _OLD_TYPES[kind]
    else:
        dist = str(intr.get("distortionType", "none")).lower()
        undist = str(intr.get("undistortionType", "none")).lower()
    if kind != "pinhole":
        return (w, h), f"camera type {kind} (a fisheye lens) is not supported: undistort the photos first"
    if dist not in _DISTORTION_PARAMS:
        return (w, h), (f"distortion {dist} is not supported (supported: {', '.join(_DISTORTION_PARAMS)}); "
                        "undistort fisheye photos first")
    if undist != "none":
        return (w, h), f"undistortion model {undist} is not supported"
    offset = _numbers(intr.get("principalPoint"), 2, where, f"intrinsic {iid}: principalPoint")
    if version < (1, 2, 1):  # from the top-left corner, not yet from the centre
        offset = offset - (w / 2.0, h / 2.0)
    if version < (1, 2, 2):
        px = intr.get("pxFocalLength")
        f = _numbers(px, 2, where, f"intrinsic {iid}: pxFocalLength") if isinstance(px, list) else \
            np.array([number("pxFocalLength")] * 2)
        fx, fy = float(f[0]), float(f[1])
    else:
        fmm, ratio, sensor = number("focalLength", 1.0), number("pixelRatio", 1.0), number("sensorWidth", 36.0)
        if not (ratio > 0.0 and sensor > 0.0):  # -1: a sensor Meshroom did not know
            return (w, h), f"intrinsic {iid}: pixelRatio and sensorWidth must be positive, got {ratio}, {sensor}"
        per_mm = w / sensor
        if version < (1, 2, 5):  # pixelRatio held fx / fy
            fx, fy = fmm * per_mm, fmm * per_mm / ratio
        elif version < (1, 2, 11):
            fx, fy = fmm * per_mm, fmm * ratio * per_mm
        else:
            fx, fy = fmm / ratio * per_mm, fmm * per_mm
    if not (fx > 0.0 and fy > 0.0 and math.isfinite(fx) and math.isfinite(fy)):  # -1: never estimated
        return (w, h), f"intrinsic {iid}: focal length must be positive, got {fx}, {fy}"
    keys = _DISTORTION_PARAMS[dist]
    k = _numbers(intr.get("distortionParams", ""), None, where, f"intrinsic {iid}: distortionParams")
    if len(k) != len(keys) and not (len(k) == 0 and not keys):
        raise InputError(where, f"intrinsic {iid}: distortion {dist} takes {len(keys)} distortionParams, got {len(k)}")
    out = {"fl_x": fx, "fl_y": fy, "cx": w / 2.0 + float(offset[0]), "cy": h / 2.0 + float(offset[1])}
    out.update(zip(keys, map(float, k)))
    return (w, h), out


def _w2c(pose: object, where: Path, what: str) -> np.ndarray:
    """World-to-camera 4x4 of an AliceVision pose (column-major world-to-camera rotation, centre)."""
    if not isinstance(pose, dict):
        raise InputError(where, f"{what}: expected rotation and center")
    R = _numbers(pose.get("rotation"), 9, where, f"{what}: rotation").reshape(3, 3).T
    C = _numbers(pose.get("center"), 3, where, f"{what}: center")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0.0:
        raise InputError(where, f"{what}: rotation is not a rotation matrix")
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ C
    return w2c


def _by_id(items: object, key: str, where: Path) -> dict[str, dict]:
    if items in (None, ""):
        return {}
    if not isinstance(items, list) or not all(isinstance(i, dict) and key in i for i in items):
        raise InputError(where, f"expected a list of objects with {key!r}")
    return {str(i[key]): i for i in items}


def read_meshroom_frames(path: str | Path) -> list[Frame]:
    """The frames of an AliceVision SfMData JSON file, or of the one in a scene folder or Meshroom
    project (InputError naming the file when malformed, or a view's photo when it is missing)."""
    path, root, data = layout_json(Path(path), find_meshroom, f"no Meshroom SfMData file ({MESHROOM_FILE}, or "
                                   f"{CACHE_GLOB})", "SfMData", cache_results, "StructureFromMotion results")
    if not is_sfm_data(data):
        raise InputError(path, "expected an AliceVision SfMData object with \"version\" and \"views\"")
    version = _version(data, path)
    intrinsics = {i: _intrinsics(d, version, path)
                  for i, d in _by_id(data.get("intrinsics"), "intrinsicId", path).items()}
    poses = _by_id(data.get("poses"), "poseId", path)
    rigs = _by_id(data.get("rigs"), "rigId", path)
    # images/ of the scene folder, of the file's folder or of the Meshroom project
    folder = photo_folder([root, path.parent, *(p.parent for p in path.parents if p.name == "MeshroomCache")])
    frames, unposed, index = [], [], {}
    for view in _by_id(data.get("views"), "viewId", path).values():
        written = str(view.get("path", ""))
        label = re.split(r"[\\/]", written)[-1] or str(view["viewId"])
        w2c = _view_pose(view, poses, rigs, path)
        if w2c is None:
            unposed.append(label)
            continue
        iid = str(view.get("intrinsicId"))
        lens = intrinsics.get(iid, ((0, 0), f"intrinsic {iid} is not in the file"))
        frames.append(posed_frame(written, folder, path, f"view {label}", index, w2c, lens))
    return reconstructed(frames, unposed, path, f"read the StructureFromMotion node's {MESHROOM_FILE}")


def _view_pose(view: dict, poses: dict[str, dict], rigs: dict[str, dict], where: Path) -> np.ndarray | None:
    """A view's world-to-camera 4x4, or None when it has no pose; a rig's view (not independent) is
    its sub-pose after the rig's pose (AliceVision's ``SfMData::getPose``)."""
    pose = poses.get(str(view.get("poseId")))
    if pose is None:
        return None
    body = pose.get("pose")
    w2c = _w2c(body.get("transform") if isinstance(body, dict) else None, where, f"pose {view.get('poseId')}")
    if "rigId" not in view or _flag(view.get("isPoseIndependant", "true")):
        return w2c
    rig = rigs.get(str(view["rigId"]))
    try:
        sub = rig["subPoses"][int(str(view.get("subPoseId")))]
    except (TypeError, KeyError, IndexError, ValueError):
        raise InputError(where, f"view {view.get('viewId')}: sub-pose {view.get('subPoseId')} of rig "
                                f"{view['rigId']} is not in the file") from None
    if str(sub.get("status", "")).lower() == "uninitialized":
        return None
    return _w2c(sub.get("pose"), where, f"rig {view['rigId']} sub-pose {view.get('subPoseId')}") @ w2c
