"""Scenes as RealityCapture (RealityScan) leaves them: an XMP sidecar beside each photo (Alignment >
Export > Registration > Metadata (XMP)), parsed with the standard library into the frames
:mod:`.frame_layouts` makes a scene of (the library's reader and the add-on's description share both).

Accepted layout: the photos with their ``NAME.xmp`` sidecars in ``images/`` (or ``Images/``) of the
scene folder, or in the scene folder itself; a photo without a sidecar is not a view. Masks as for
COLMAP (``masks/NAME.png`` beside the photos' folder).

Conventions (RealityCapture's ``xcr`` namespace): ``Rotation`` is the row-major 3x3 world-to-camera
rotation and ``Position`` the camera centre, with OpenCV camera axes (+x right, +y down, looking
along +z); ``FocalLength35mm`` is the focal length for a 36 mm wide frame on the photo's longer
side (f in pixels = FocalLength35mm / 36 x max(w, h)); ``PrincipalPointU`` / ``V`` are offsets from
the image centre in units of the longer side; ``DistortionCoeficients`` (sic) are k1, k2, k3, k4,
t1, t2, where t1 multiplies r^2 + 2x^2 (OpenCV's p2) and t2 the 2xy term (OpenCV's p1). Photos are
read as stored (drone photos carry no EXIF turn).
``DistortionModel`` ``perspective``, ``brown3``, ``brown3t2`` and ``brown4`` / ``brown4t2`` with
k4 = 0 are read; k4, the ``division`` model, a pixel aspect ratio other than 1 and a skew have no
COLMAP equivalent here and are refused. Only ``absolute`` coordinates (the registration's own
frame) are read.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from .images import IMAGE_EXTS, find_mask, image_named
from .photo_frame import PHOTO_FOLDERS, Frame

#: The namespace of RealityCapture's properties (its version, 1.1 today, is not checked).
XCR_NAMESPACE = "capturingreality.com/ns/xcr"
_MODELS = ("perspective", "brown3", "brown3t2", "brown4", "brown4t2")


def _is_rc(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return XCR_NAMESPACE.encode() in f.read(4096)
    except OSError:
        return False


def sidecars(folder: Path) -> list[Path]:
    """The RealityCapture XMP sidecars in ``folder`` (sorted; empty when it has none)."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() == ".xmp" and p.is_file() and _is_rc(p))


def find_realitycapture(root: str | Path) -> Path | None:
    """The folder of photos with RealityCapture sidecars in a scene folder (``images/``, else the
    folder itself), or None."""
    root = Path(root)
    return next((d for d in [root / f for f in PHOTO_FOLDERS] + [root] if sidecars(d)), None)


def _is_xcr(tag: str, key: str) -> bool:
    return tag.endswith("}" + key) and XCR_NAMESPACE in tag


def _value(desc: ET.Element, key: str) -> str | None:
    """An xcr property, written as an attribute or as a child element."""
    v = next((v for k, v in desc.attrib.items() if _is_xcr(k, key)), None)
    if v is None:
        v = next((c.text or "" for c in desc if _is_xcr(c.tag, key)), None)
    return None if v is None else v.strip()


def _numbers(desc: ET.Element, key: str, n: int, where: Path, default: list[float] | None = None) -> np.ndarray:
    v = _value(desc, key)
    if v is None:
        if default is None:
            raise InputError(where, f"no xcr:{key}")
        return np.asarray(default, np.float64)
    try:
        a = np.asarray([float(x) for x in v.split()], np.float64)
    except ValueError:
        raise InputError(where, f"xcr:{key} is not numbers: {v[:60]!r}") from None
    if a.size != n or not np.isfinite(a).all():
        raise InputError(where, f"xcr:{key}: expected {n} finite numbers, got {v[:80]!r}")
    return a


def _photo_of(xmp: Path) -> Path | None:
    """The photo of a sidecar: ``NAME.EXT`` beside ``NAME.xmp`` (or ``NAME.EXT.xmp``)."""
    if Path(xmp.stem).suffix.lower() in IMAGE_EXTS and xmp.with_suffix("").is_file():
        return xmp.with_suffix("")
    return image_named(xmp.parent, xmp.stem)


def read_sidecar(xmp: Path, photo: Path) -> Frame:
    """The frame of one photo from its RealityCapture sidecar (InputError naming the XMP)."""
    try:
        root = ET.parse(xmp).getroot()
    except (OSError, ET.ParseError) as e:
        raise InputError(xmp, f"unreadable XMP ({e})") from None
    desc = next((d for d in root.iter("{http://www.w3.org/1999/02/22-rdf-syntax-ns#}Description")
                 if _value(d, "Rotation") is not None or _value(d, "Position") is not None), None)
    if desc is None:
        raise InputError(xmp, "no RealityCapture pose (xcr:Rotation and xcr:Position)")
    coords = (_value(desc, "Coordinates") or "absolute").lower()
    if coords != "absolute":
        raise InputError(xmp, f"xcr:Coordinates is {coords}: export the registration with absolute coordinates")
    model = (_value(desc, "DistortionModel") or "perspective").lower()
    if model not in _MODELS:
        raise InputError(xmp, f"distortion model {model} has no COLMAP equivalent (read are: {', '.join(_MODELS)}); "
                              "export the registration with a brown3 or brown3t2 lens model")
    f35 = float(_numbers(desc, "FocalLength35mm", 1, xmp)[0])
    aspect = float(_numbers(desc, "AspectRatio", 1, xmp, [1.0])[0])
    skew = float(_numbers(desc, "Skew", 1, xmp, [0.0])[0])
    pp = np.array([_numbers(desc, "PrincipalPointU", 1, xmp, [0.0])[0],
                   _numbers(desc, "PrincipalPointV", 1, xmp, [0.0])[0]])
    k = _numbers(desc, "DistortionCoeficients", 6, xmp, [0.0] * 6)
    if f35 <= 0.0:
        raise InputError(xmp, f"xcr:FocalLength35mm must be positive, got {f35}")
    if abs(aspect - 1.0) > 1e-9 or skew != 0.0:
        raise InputError(xmp, f"pixel aspect ratio {aspect} and skew {skew}: only square pixels without skew "
                              "are read")
    if k[3] != 0.0:
        raise InputError(xmp, "k4 has no equivalent in COLMAP's camera models (export with a brown3 or brown3t2 "
                              "lens model)")
    R = _numbers(desc, "Rotation", 9, xmp).reshape(3, 3)
    C = _numbers(desc, "Position", 3, xmp)
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ C
    intr = {"fl_long": f35 / 36.0, "cx_long": float(pp[0]), "cy_long": float(pp[1]),
            "k1": float(k[0]), "k2": float(k[1]), "k3": float(k[2]), "p1": float(k[5]), "p2": float(k[4])}
    return Frame(name=photo.name, photo=photo, w2c=w2c, size=None, intrinsics=intr, part=None)


def read_realitycapture_frames(path: str | Path) -> list[Frame]:
    """The frames of a scene folder of photos with RealityCapture sidecars, or of one sidecar."""
    path = Path(path)
    if path.is_file():
        folder, xmps = path.parent, [path]
    else:
        folder = find_realitycapture(path)
        if folder is None:
            raise InputError(path, "no RealityCapture XMP sidecars (in images/ or the folder)")
        xmps = sidecars(folder)
    frames = []
    for xmp in xmps:
        photo = _photo_of(xmp)
        if photo is None:
            raise InputError(xmp, f"no photo {xmp.stem} beside it ({', '.join(IMAGE_EXTS)})")
        fr = read_sidecar(xmp, photo)
        fr.mask = find_mask(folder, fr.name)
        frames.append(fr)
    return frames
