"""Photos, masks and depth maps with random bytes changed or cut short (PNG, JPEG, RGBA PNG, 16-bit,
float, LZW and deflate TIFF, a mask, TIFF and EXR depth): the readers the library and the add-on
use give pixels or an InputError naming the file, never another exception (fixed seeds; these
mutations found a zero division inside tifffile, an empty TIFF reshaped after its read, and a
truncated PNG header that escaped the size reader)."""
from __future__ import annotations

import random

import numpy as np
import pytest
from PIL import Image

from dibrgs_core.bridge.imagesize import image_header
from dibrgs_core.common.errors import InputError
from dibrgs_core.data import images as im

tifffile = pytest.importorskip("tifffile")
# robustness sweeps: the full suite runs them, the quick tier does not
pytestmark = pytest.mark.slow
MUTATIONS = 150


def _write(kind: str, folder) -> tuple:
    """(file, readers) of one kind of file."""
    rng = np.random.default_rng(0)
    img = (rng.random((40, 56, 3)) * 255).astype(np.uint8)
    photo = (im.read_pixels, im.image_size, image_header)
    if kind == "png":
        Image.fromarray(img).save(p := folder / "a.png")
    elif kind == "jpeg":
        Image.fromarray(img).save(p := folder / "a.jpg", quality=90)
    elif kind == "rgba":
        Image.fromarray(np.dstack([img, np.full((40, 56), 200, np.uint8)])).save(p := folder / "rgba.png")
    elif kind == "tiff16":
        tifffile.imwrite(p := folder / "a16.tif", img.astype(np.uint16) * 257)
    elif kind == "tiff_float":
        tifffile.imwrite(p := folder / "f32.tif", img.astype(np.float32) / 255, photometric="rgb")
    elif kind == "tiff_lzw":
        Image.fromarray(img).save(p := folder / "lzw.tif", compression="tiff_lzw")
    elif kind == "tiff_grey_deflate":
        tifffile.imwrite(p := folder / "g16.tif", img[..., 0].astype(np.uint16) * 257, compression="zlib")
    elif kind == "mask":
        Image.fromarray((img[..., 0] > 128).astype(np.uint8) * 255).save(p := folder / "m.png")
        return p, (lambda q: im.read_mask(q, (56, 40)),)
    elif kind == "depth_tiff":
        im.write_depth_tiff(p := folder / "d.tif", rng.random((40, 56)).astype(np.float32) + 1)
        return p, (im.read_depth,)
    else:
        im.write_depth_exr(p := folder / "d.exr", rng.random((40, 56)).astype(np.float32) + 1)
        return p, (im.read_depth,)
    return p, photo


@pytest.mark.parametrize("kind", ["png", "jpeg", "rgba", "tiff16", "tiff_float", "tiff_lzw", "tiff_grey_deflate",
                                  "mask", "depth_tiff", "depth_exr"])
def test_a_damaged_image_reads_or_is_named(tmp_path, kind):
    path, readers = _write(kind, tmp_path)
    good = path.read_bytes()
    rng = random.Random(kind)
    refused = 0
    for i in range(MUTATIONS):
        b = bytearray(good)
        if rng.random() < 0.3:
            b = b[: rng.randrange(1, len(b))]
        else:  # most of the damage near the start, where the headers are
            for _ in range(rng.randint(1, 8)):
                b[rng.randrange(min(len(b), 400) if i % 2 else len(b))] = rng.randrange(256)
        path.write_bytes(bytes(b))
        for read in readers:
            try:
                read(path)
            except InputError as e:
                assert str(path) in str(e)
                refused += 1
    assert refused > 0  # the damage reaches the readers' checks
