"""Image sizes and EXIF orientations from file headers (PNG, JPEG, TIFF), with the standard
library only.

Blender's Python has no Pillow; the add-on imports scenes in-process and only
needs each view's width and height, which the file's headers hold, and the EXIF
orientation (tag 274: JPEG's APP1 Exif block, PNG's eXIf chunk, TIFF's first
directory) that the library's reader follows (``data.images``, through Pillow or
tifffile) and Blender, which loads the stored pixels, does not.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from ..data.images import oriented, upright_size

# JPEG start-of-frame markers (baseline, progressive, lossless, ...): every
# 0xC0-0xCF except DHT (C4), JPG (C8) and DAC (CC).
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_size(path: str | Path, orient: bool = True) -> tuple[int, int]:
    """(width, height) of a PNG, JPEG or TIFF file as a viewer shows it (EXIF orientation applied)
    with ``orient``, as stored without; InputError naming the file otherwise."""
    w, h, orientation = image_header(path)
    return upright_size(w, h, orientation) if orient else (w, h)


def image_header(path: str | Path) -> tuple[int, int, int]:
    """(stored width, stored height, EXIF orientation 1-8; 1 when absent or invalid) of a PNG, JPEG
    or TIFF file; InputError naming the file otherwise."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(32)
            if head.startswith(b"\x89PNG\r\n\x1a\n"):
                if head[12:16] != b"IHDR":
                    raise ValueError("PNG without an IHDR chunk")
                w, h = struct.unpack(">II", head[16:24])
                orientation = _png_orientation(f)
            elif head.startswith(b"\xff\xd8"):
                w, h, orientation = _jpeg_header(f)
            elif head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
                (w, h), orientation = _tiff_tags(f, head)
            else:
                raise ValueError("not a PNG, JPEG or TIFF file")
    except FileNotFoundError:
        raise InputError(path, "image file not found") from None
    except (OSError, ValueError, struct.error) as e:
        raise InputError(path, f"unreadable image header ({e})") from None
    if w < 1 or h < 1:
        raise InputError(path, f"image header gives a size of {w}x{h}")
    return int(w), int(h), orientation


def _orientation(value) -> int:
    return int(value) if isinstance(value, int) and 1 <= value <= 8 else 1


def _exif_orientation(block: bytes) -> int:
    """Orientation (tag 274) in the first directory of an EXIF block (a TIFF structure); 1 when
    absent or unreadable (a malformed EXIF block must not make a photo unreadable, as in the library)."""
    try:
        e = "<" if block[:2] == b"II" else ">"
        (ifd,) = struct.unpack_from(e + "I", block, 4)
        (n,) = struct.unpack_from(e + "H", block, ifd)
        for k in range(n):
            tag, typ, _count = struct.unpack_from(e + "HHI", block, ifd + 2 + 12 * k)
            if tag == 274 and typ == 3:  # SHORT
                return _orientation(struct.unpack_from(e + "H", block, ifd + 2 + 12 * k + 8)[0])
    except struct.error:
        pass
    return 1


def _png_orientation(f) -> int:
    """Orientation of a PNG's eXIf chunk (before or after its image data), 1 without one."""
    f.seek(8)
    while True:
        head = f.read(8)
        if len(head) < 8:
            return 1
        length, kind = struct.unpack(">I4s", head)
        if kind == b"eXIf":
            return _exif_orientation(f.read(length))
        if kind == b"IEND":
            return 1
        f.seek(length + 4, 1)  # data and CRC


def _jpeg_header(f) -> tuple[int, int, int]:
    f.seek(2)
    orientation, exif = 1, False
    while True:
        b = f.read(1)
        while b and b != b"\xff":  # skip to the next marker
            b = f.read(1)
        while b == b"\xff":  # fill bytes
            b = f.read(1)
        if not b:
            raise ValueError("JPEG without a frame header")
        marker = b[0]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            continue
        (length,) = struct.unpack(">H", f.read(2))
        if marker in _SOF:
            _precision, h, w = struct.unpack(">BHH", f.read(5))
            return w, h, orientation
        if marker == 0xE1 and not exif:  # APP1: the first EXIF block counts (as in Pillow); it precedes the frame
            data = f.read(length - 2)
            if data.startswith(b"Exif\x00\x00"):
                orientation, exif = _exif_orientation(data[6:]), True
            continue
        f.seek(length - 2, 1)


def _tiff_tags(f, head: bytes) -> tuple[tuple[int, int], int]:
    """((ImageWidth, ImageLength), Orientation) of a TIFF's first directory."""
    e = "<" if head[:2] == b"II" else ">"
    big = struct.unpack(e + "H", head[2:4])[0] == 43
    if big:  # BigTIFF: 8-byte offsets and counts, 20-byte entries
        f.seek(8)
        (ifd,) = struct.unpack(e + "Q", f.read(8))
        f.seek(ifd)
        (n,) = struct.unpack(e + "Q", f.read(8))
        entry, fmt = 20, e + "HHQ8s"
    else:
        (ifd,) = struct.unpack(e + "I", head[4:8])
        f.seek(ifd)
        (n,) = struct.unpack(e + "H", f.read(2))
        entry, fmt = 12, e + "HHI4s"
    sizes: dict[int, int] = {}
    data = f.read(n * entry)
    for k in range(n):
        tag, typ, _count, value = struct.unpack(fmt, data[k * entry:(k + 1) * entry])
        if tag in (256, 257, 274):  # ImageWidth, ImageLength (SHORT or LONG, LONG8 in BigTIFF), Orientation
            code = {3: "H", 4: "I", 16: "Q"}.get(typ)
            if code is None:
                if tag == 274:
                    continue
                raise ValueError(f"TIFF tag {tag} has type {typ}")
            sizes[tag] = struct.unpack(e + code, value[:struct.calcsize(code)])[0]
    if 256 not in sizes or 257 not in sizes:
        raise ValueError("TIFF without ImageWidth/ImageLength")
    return (sizes[256], sizes[257]), _orientation(sizes.get(274, 1))


def upright_pixels(pixels: np.ndarray, width: int, height: int, orientation: int) -> tuple[np.ndarray, int, int]:
    """A Blender image's flat RGBA ``pixels`` (rows bottom to top, as ``Image.pixels``) of a photo
    stored ``width`` x ``height`` with EXIF ``orientation``, turned as a viewer shows the photo:
    (flat pixels in Blender's order, width, height)."""
    a = np.asarray(pixels).reshape(height, width, -1)[::-1]  # rows top to bottom
    up = oriented(a, orientation)[::-1]
    return np.ascontiguousarray(up).ravel(), up.shape[1], up.shape[0]
