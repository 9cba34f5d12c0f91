"""Scenes as Agisoft Metashape exports them (File > Export > Export Cameras, "Agisoft XML"), parsed
with the standard library into the frames :mod:`.frame_layouts` makes a scene of (the library's
reader and the add-on's description share both).

Accepted layout: a scene folder holding the XML (``cameras.xml``, or the folder's only Metashape
XML) and the photos in ``images/`` beside it (else beside the XML), named by each camera's label
with or without its extension, also in subfolders where the name is unique. Masks as for COLMAP
(``masks/NAME.png`` beside the photos' folder).

Conventions (Metashape's, from the frame camera model of its manual, Appendix C): a camera's
``<transform>`` is a row-major 4x4 camera-to-chunk matrix with OpenCV camera axes (+x right, +y
down, looking along +z); a camera of a component (Metashape 2) is placed by the component's
``<transform>`` first; the chunk's ``<transform>`` (rotation, translation, scale) then takes both to
the world (geocentric metres in a georeferenced project, which the readers move near the origin:
``Scene.recentred``). Intrinsics of a ``frame`` sensor's calibration (the ``adjusted`` one when
there are several): ``f`` (pixels), ``cx``, ``cy`` (from the image centre), ``b1`` (fx = f + b1),
``b2`` (skew), radial ``k1``..``k4`` and tangential ``p1``, ``p2``, where Metashape's ``p1``
multiplies r^2 + 2x^2 (OpenCV's ``p2``) and its ``p2`` the 2xy term (OpenCV's ``p1``). ``k4``, higher
tangential terms and a skew that moves the image's edge by half a pixel or more have no COLMAP
equivalent and are refused, as are fisheye and spherical sensors. Cameras without a transform (not
aligned) and cameras disabled in Metashape (``enabled="false"``) are left out and counted in the log.
"""
from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from .images import find_mask
from .photo_frame import Frame, labelled_photo, layout_file, photo_folder

log = logging.getLogger("dibrgs.io_metashape")

METASHAPE_FILE = "cameras.xml"
#: A skew term (b2) shifting the image's top and bottom rows by less than this (pixels) is dropped.
MAX_SKEW_SHIFT_PX = 0.5


def _is_metashape(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return b"<document" in head and b"<chunk" in head


def find_metashape(root: str | Path) -> Path | None:
    """The Metashape cameras XML of a scene folder: ``cameras.xml``, else its only Metashape XML
    (InputError naming them when there are several), else None."""
    root = Path(root)
    if (root / METASHAPE_FILE).is_file() and _is_metashape(root / METASHAPE_FILE):
        return root / METASHAPE_FILE
    found = sorted(p for p in root.glob("*") if p.suffix.lower() == ".xml" and p.is_file() and _is_metashape(p))
    if len(found) > 1:
        raise InputError(root, f"several Metashape camera files ({', '.join(p.name for p in found)}): "
                               f"name the one to read {METASHAPE_FILE}")
    return found[0] if found else None


def _numbers(el: ET.Element | None, n: int, where: Path, what: str) -> np.ndarray | None:
    if el is None or el.text is None or not el.text.strip():
        return None
    try:
        v = np.array([float(x) for x in el.text.split()], np.float64)
    except ValueError:
        raise InputError(where, f"{what}: not numbers: {el.text.strip()[:60]!r}") from None
    if v.size != n or not np.isfinite(v).all():
        raise InputError(where, f"{what}: expected {n} finite numbers, got {el.text.strip()[:80]!r}")
    return v


def _similarity(el: ET.Element | None, where: Path, what: str) -> np.ndarray:
    """The 4x4 matrix of a chunk's or component's ``<transform>`` (identity when absent)."""
    T = np.eye(4)
    if el is None:
        return T
    if len(el) == 0:  # a bare 4x4 matrix
        m = _numbers(el, 16, where, what)
        return T if m is None else m.reshape(4, 4)
    r = _numbers(el.find("rotation"), 9, where, f"{what} rotation")
    t = _numbers(el.find("translation"), 3, where, f"{what} translation")
    s = _numbers(el.find("scale"), 1, where, f"{what} scale")
    scale = 1.0 if s is None else float(s[0])
    if scale <= 0.0:
        raise InputError(where, f"{what} scale must be positive, got {scale}")
    T[:3, :3] = scale * (np.eye(3) if r is None else r.reshape(3, 3))
    if t is not None:
        T[:3, 3] = t
    return T


def _sensors(chunk: ET.Element, where: Path) -> dict[str, tuple[tuple[int, int], dict[str, float] | str]]:
    """Each sensor's id -> ((width, height), the frame's intrinsics in OpenCV's terms, or the reason
    the sensor cannot be read, raised when a camera uses it)."""
    out: dict[str, tuple[tuple[int, int], dict[str, float] | str]] = {}
    for s in chunk.findall("sensors/sensor"):
        sid, label = s.get("id", ""), s.get("label", s.get("id", "?"))
        calibs = s.findall("calibration")
        calib = next((c for c in calibs if c.get("class") == "adjusted"), calibs[0] if calibs else None)
        res = (calib.find("resolution") if calib is not None and calib.find("resolution") is not None
               else s.find("resolution"))
        try:
            size = (int(res.get("width")), int(res.get("height")))
        except (AttributeError, TypeError, ValueError):
            raise InputError(where, f"sensor {label}: no <resolution width= height=>") from None
        kind = s.get("type", "frame")
        if kind != "frame":
            out[sid] = (size, f"sensor {label} is a {kind} camera (only frame cameras are supported; "
                              "undistort the photos to a frame camera first)")
            continue
        if calib is None or calib.find("f") is None:
            out[sid] = (size, f"sensor {label} has no calibration (align the photos in Metashape first)")
            continue

        def value(key: str) -> float:
            v = _numbers(calib.find(key), 1, where, f"sensor {label} {key}")
            return 0.0 if v is None else float(v[0])

        f, w, h = value("f"), size[0], size[1]
        if f <= 0.0:
            raise InputError(where, f"sensor {label}: focal length f must be positive, got {f}")
        for key in ("k4", "p3", "p4"):
            if value(key) != 0.0:
                raise InputError(where, f"sensor {label}: {key} has no equivalent in COLMAP's camera models "
                                        f"(fix {key} at 0 in Metashape's camera calibration and optimise again)")
        if abs(value("b2")) * 0.5 * h / f >= MAX_SKEW_SHIFT_PX:
            raise InputError(where, f"sensor {label}: skew b2 = {value('b2')} moves the image's edge by half a "
                                    "pixel or more (fix b2 at 0 in Metashape's camera calibration and optimise again)")
        out[sid] = (size, {"fl_x": f + value("b1"), "fl_y": f, "cx": 0.5 * w + value("cx"),
                           "cy": 0.5 * h + value("cy"), "k1": value("k1"), "k2": value("k2"),
                           "k3": value("k3"), "p1": value("p2"), "p2": value("p1")})
    return out


def read_metashape_frames(path: str | Path) -> list[Frame]:
    """The frames of a Metashape cameras XML, or of the one in a scene folder (InputError naming the
    file when malformed, or a camera's photo when it is missing)."""
    path = Path(path)
    path = layout_file(path, find_metashape, f"no Metashape cameras XML ({METASHAPE_FILE})")
    try:
        doc = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        raise InputError(path, f"unreadable Metashape XML ({e})") from None
    chunks = doc.findall("chunk") if doc.tag == "document" else []
    if not chunks:
        raise InputError(path, "expected a Metashape <document> with a <chunk>")
    if len(chunks) > 1:
        log.warning("%s: %d chunks, reading the first (%s)", path, len(chunks), chunks[0].get("label", "?"))
    chunk = chunks[0]
    world = _similarity(chunk.find("transform"), path, "chunk transform")
    components = {c.get("id"): _similarity(c.find("transform"), path, f"component {c.get('label', c.get('id'))}")
                  for c in chunk.findall("components/component")}
    sensors = _sensors(chunk, path)
    folder = photo_folder([path.parent]) or path.parent
    frames, unaligned, disabled, index = [], [], [], {}
    for cam in chunk.iterfind("cameras//camera"):
        label = cam.get("label", cam.get("id", "?"))
        if cam.get("enabled", "true").lower() in ("false", "0"):  # unchecked in Metashape: left out there
            disabled.append(label)
            continue
        m = _numbers(cam.find("transform"), 16, path, f"camera {label} transform")
        if m is None:
            unaligned.append(label)
            continue
        if cam.get("sensor_id") not in sensors:
            raise InputError(path, f"camera {label}: sensor {cam.get('sensor_id')} is not in the file")
        size, intrinsics = sensors[cam.get("sensor_id")]
        if isinstance(intrinsics, str):
            raise InputError(path, f"camera {label}: {intrinsics}")
        c2w = world @ components.get(cam.get("component_id"), np.eye(4)) @ m.reshape(4, 4)
        scale = np.cbrt(np.linalg.det(c2w[:3, :3]))
        if not scale > 0.0:
            raise InputError(path, f"camera {label}: its transform is not a rotation and translation")
        R, C = c2w[:3, :3] / scale, c2w[:3, 3]
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R.T, -R.T @ C
        photo = labelled_photo(folder, label, path, f"camera {label}", index)
        name = photo.relative_to(folder).as_posix()
        frames.append(Frame(name=name, photo=photo, w2c=w2c, size=size, intrinsics=dict(intrinsics), part=None,
                            mask=find_mask(folder, name)))
    for what, labels in (("without a transform (not aligned)", unaligned), ("disabled in Metashape", disabled)):
        if labels:
            log.info("%s: %d cameras %s left out: %s%s", path, len(labels), what, ", ".join(labels[:5]),
                     " ..." if len(labels) > 5 else "")
    if not frames:
        raise InputError(path, "no aligned cameras (none has a <transform>)")
    return frames
