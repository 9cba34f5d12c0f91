"""Image sizes from file headers (PNG, JPEG, TIFF), with the standard library only.

Blender's Python has no Pillow; the add-on imports scenes in-process and only
needs each view's width and height, which the first bytes of the file hold.
"""
from __future__ import annotations

import struct
from pathlib import Path

from ..common.errors import InputError

# JPEG start-of-frame markers (baseline, progressive, lossless, ...): every
# 0xC0-0xCF except DHT (C4), JPG (C8) and DAC (CC).
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of a PNG, JPEG or TIFF file; InputError naming the file otherwise."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(32)
            if head.startswith(b"\x89PNG\r\n\x1a\n"):
                if head[12:16] != b"IHDR":
                    raise ValueError("PNG without an IHDR chunk")
                w, h = struct.unpack(">II", head[16:24])
            elif head.startswith(b"\xff\xd8"):
                w, h = _jpeg_size(f)
            elif head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
                w, h = _tiff_size(f, head)
            else:
                raise ValueError("not a PNG, JPEG or TIFF file")
    except FileNotFoundError:
        raise InputError(path, "image file not found") from None
    except (OSError, ValueError, struct.error) as e:
        raise InputError(path, f"unreadable image header ({e})") from None
    if w < 1 or h < 1:
        raise InputError(path, f"image header gives a size of {w}x{h}")
    return int(w), int(h)


def _jpeg_size(f) -> tuple[int, int]:
    f.seek(2)
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
            return w, h
        f.seek(length - 2, 1)


def _tiff_size(f, head: bytes) -> tuple[int, int]:
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
        if tag in (256, 257):  # ImageWidth, ImageLength: SHORT or LONG (LONG8 in BigTIFF)
            code = {3: "H", 4: "I", 16: "Q"}.get(typ)
            if code is None:
                raise ValueError(f"TIFF tag {tag} has type {typ}")
            sizes[tag] = struct.unpack(e + code, value[:struct.calcsize(code)])[0]
    if 256 not in sizes or 257 not in sizes:
        raise ValueError("TIFF without ImageWidth/ImageLength")
    return sizes[256], sizes[257]
