"""Images and depth maps on disk: PNG/JPEG images (Pillow), TIFF images of 8, 16 or 32 bits,
integer or float, any number of bands (tifffile), float32 depth as TIFF (tifffile) or EXR
(OpenEXR). Writers are atomic. Never torch or bpy.

Images are float32 (H, W, 3) RGB in [0, 1] as stored (sRGB-encoded), turned upright by their
EXIF orientation unless a reader asks for the stored pixel order (COLMAP), with a bool (H, W) map of
the pixels that hold data (:func:`read_pixels`: transparent, NaN and GDAL no-data pixels do not; a
mask image, :func:`read_mask`, can say so for any photo); depth maps float32 (H, W) z-depth in world
units, 0 = no depth.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..common.errors import InputError
from ..common.fileio import atomic_path

log = logging.getLogger("dibrgs.images")
#: Photos already reported as holding no-data pixels (one line a file).
_REPORTED: set[str] = set()


def _report_no_data(path: Path, valid: np.ndarray | None, what: str) -> np.ndarray | None:
    """``valid`` as a view holds it (None when every pixel is data), saying once a file what share of
    it is no data and that those pixels are left out."""
    if valid is None or valid.all():
        return None
    if str(path) not in _REPORTED:
        _REPORTED.add(str(path))
        log.info("%s: %.1f %% of its pixels are %s: left out of training, evaluation and geometry", path,
                 100.0 * (1.0 - valid.mean()), what)
    return valid


def fill_no_data(image: np.ndarray, valid: np.ndarray | None, value: float = 0.0) -> np.ndarray:
    """``image`` (H, W, C) with ``value`` (of its dtype: 0 as stored, NaN for the stages that test
    for it) where ``valid`` (H, W) is False; ``image`` itself when ``valid`` is None."""
    return image if valid is None else np.where(valid[..., None], image, np.asarray(value, image.dtype))


IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
_TIFF_EXTS = (".tif", ".tiff")
DEPTH_EXTS = (".tiff", ".tif", ".exr")


def image_named(folder: Path, base: str) -> Path | None:
    """The image file ``base`` + an image extension (either case: cameras write ``.JPG``) in
    ``folder``, or None."""
    for ext in IMAGE_EXTS + tuple(e.upper() for e in IMAGE_EXTS):
        if (folder / f"{base}{ext}").is_file():
            return folder / f"{base}{ext}"
    return None


#: EXIF orientations (tag 274) that swap width and height (transposed / rotated by 90 degrees).
TRANSPOSING = {5, 6, 7, 8}


def upright_size(width: int, height: int, orientation: int) -> tuple[int, int]:
    """(width, height) of a photo stored ``width`` x ``height``, as a viewer shows it under EXIF
    orientation ``orientation`` (1-8)."""
    return (height, width) if orientation in TRANSPOSING else (width, height)


def turned_to_fit(stored: tuple[int, int], upright: tuple[int, int], size: tuple[int, int]) -> bool | None:
    """Whether a photo must be turned upright (by its EXIF orientation) to be a camera's ``size``,
    for tools that read the stored pixel order (COLMAP, the NeRF tools): False when its stored
    pixels fit, True when only the upright ones do (a model made from turned copies), None when
    neither does."""
    if stored == size:
        return False
    return True if upright == size else None


def exif_orientation(im) -> int:
    """EXIF orientation (1-8) of an open PIL image; 1 (as stored) when absent or invalid."""
    try:
        o = int(im.getexif().get(0x0112, 1))
    except Exception:  # a malformed EXIF block must not make the photo unreadable
        return 1
    return o if 1 <= o <= 8 else 1


def _tiff(path: Path, pixels: bool):
    """A TIFF image's first image through tifffile (Pillow misreads 16-bit RGBA and cannot read float
    TIFFs, both common in remote sensing): ((H, W, bands) array, (W, H), orientation tag, alpha band
    index or None, GDAL no-data value or None). The array is None without ``pixels``, and when its
    compression needs the imagecodecs package (LZW, JPEG, ...), which needs numpy 2 (bpy needs numpy
    1) and is not a dependency: :func:`_tiff_image` then reads it with Pillow where Pillow reads it
    right (the no-data value then on Pillow's [0, 1] scale)."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tf:
            series, page = tf.series[0], tf.pages[0]
            tag = page.tags.get(0x0112)
            orientation = int(tag.value) if tag is not None and 1 <= int(tag.value) <= 8 else 1
            axes, shape = series.axes, series.shape
            if "Y" not in axes or "X" not in axes:
                raise ValueError(f"no image axes in {axes}")
            H, W = shape[axes.index("Y")], shape[axes.index("X")]
            if H <= 0 or W <= 0:
                raise ValueError(f"an image of {W}x{H} pixels")
            # the first extra sample marked as alpha, after the colour bands
            colour = 3 if int(page.photometric) == 2 else 1
            alpha = next((colour + k for k, e in enumerate(page.extrasamples or ()) if int(e) in (1, 2)), None)
            nodata = _gdal_nodata(page.tags.get(42113))
            if not pixels:
                return None, (W, H), orientation, alpha, nodata
            try:
                a = series.asarray()
            except ValueError as e:
                if "imagecodecs" not in str(e):
                    raise
                # 8-bit images of 1 to 4 bands and 16-bit grey are what Pillow reads right
                if page.bitspersample == 8 or (page.bitspersample == 16 and page.samplesperpixel == 1):
                    # the no-data value on Pillow's [0, 1] scale
                    unit = None if nodata is None else nodata / (2 ** page.bitspersample - 1)
                    return None, (W, H), orientation, alpha, unit
                raise InputError(path, f"{page.compression.name}-compressed {page.bitspersample}-bit TIFF of "
                                       f"{page.samplesperpixel} bands: tifffile needs the imagecodecs package "
                                       "for it and Pillow misreads it; save it uncompressed or "
                                       "deflate-compressed") from None
    except FileNotFoundError:
        raise InputError(path, "image file not found") from None
    except InputError:
        raise
    except Exception as e:  # tifffile raises many types for corrupt files (a zero division among them)
        raise InputError(path, f"unreadable or truncated image ({type(e).__name__}: {e})") from None
    # bands (samples, channels, pages) last, whatever order the file keeps them in
    a = np.moveaxis(a, [axes.index("Y"), axes.index("X")], [0, 1]).reshape(H, W, -1)
    return a, (W, H), orientation, alpha, nodata


def _gdal_nodata(tag) -> float | None:
    """The no-data value of GDAL's GDAL_NODATA tag (42113, ASCII: "0", "-9999", "nan"), or None."""
    if tag is None:
        return None
    try:
        return float(str(tag.value).strip().strip("\x00"))
    except ValueError:
        return None


def _tiff_image(path: Path, orient: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`read_pixels` of a TIFF: the first three bands as RGB (one band: grey), integers scaled
    by their type's maximum, floats taken as values in [0, 1]. No data: NaN in a float band, GDAL's
    no-data value in every colour band, an alpha band (TIFF extra sample) below half."""
    a, _, orientation, alpha, nodata = _tiff(path, pixels=True)
    if a is None:
        rgb, valid = _pillow_image(path, orient)
        if nodata is not None:  # here on [0, 1]: within half of the smallest step of 16 bits
            valid = (valid if valid is not None else True) & ~(np.abs(rgb - nodata) < 0.5 / 65535).all(axis=2)
            valid = _report_no_data(path, np.asarray(valid), "GDAL no-data")
            return fill_no_data(rgb, valid), valid
        return rgb, valid
    valid = np.ones(a.shape[:2], bool)
    what = []
    if alpha is not None and alpha < a.shape[2]:
        top = np.iinfo(a.dtype).max if np.issubdtype(a.dtype, np.integer) else 1.0
        valid &= np.nan_to_num(a[..., alpha].astype(np.float64)) > top / 2
        what.append("transparent")
    colour = a[..., :3] if a.shape[2] >= 3 and alpha != 1 else a[..., :1]
    if nodata is not None:
        valid &= ~(np.isnan(colour) if np.isnan(nodata) else colour == nodata).all(axis=2)
        what.append(f"GDAL no-data ({nodata:g})")
    if np.issubdtype(a.dtype, np.floating):
        valid &= np.isfinite(colour).all(axis=2)
        what.append("NaN")
    a = fill_no_data(colour if colour.shape[2] == 3 else np.repeat(colour, 3, axis=2), None if valid.all() else valid)
    if a.dtype == bool:
        a = a.astype(np.float32)
    elif np.issubdtype(a.dtype, np.integer):
        a = np.clip(a, 0, None).astype(np.float32) / np.float32(np.iinfo(a.dtype).max)
    else:
        a = np.nan_to_num(a.astype(np.float32), nan=0.0, posinf=np.inf, neginf=0.0)
        top = float(a.max(initial=0.0))
        if not np.isfinite(top) or top > 1.0 + 1e-6:
            raise InputError(path, f"floating-point image with values up to {top:g}; expected [0, 1] "
                                   "(reflectance): rescale it, or save it as 8- or 16-bit")
        a = np.clip(a, 0.0, 1.0)  # small negative reflectances (correction noise) are dark, not an error
    if orient:
        a, valid = oriented(a, orientation), oriented(valid, orientation)
    return np.ascontiguousarray(a), _report_no_data(path, np.ascontiguousarray(valid), " or ".join(what) or "no data")


def oriented(a: np.ndarray, orientation: int) -> np.ndarray:
    """``a`` (H, W, ...), rows top to bottom, as a viewer shows it under EXIF/TIFF orientation 1-8 (as
    Pillow's exif_transpose)."""
    return {1: lambda x: x, 2: lambda x: x[:, ::-1], 3: lambda x: x[::-1, ::-1], 4: lambda x: x[::-1],
            5: lambda x: np.swapaxes(x, 0, 1), 6: lambda x: np.rot90(x, -1),
            7: lambda x: np.swapaxes(x[::-1, ::-1], 0, 1), 8: lambda x: np.rot90(x, 1)}[orientation](a)


def image_size(path: str | Path, orient: bool = True) -> tuple[int, int]:
    """(width, height) from the image header, as displayed (EXIF orientation applied) with ``orient``."""
    from PIL import Image, UnidentifiedImageError

    if Path(path).suffix.lower() in _TIFF_EXTS:
        _, (w, h), orientation, _, _ = _tiff(Path(path), pixels=False)
        return upright_size(w, h, orientation) if orient else (w, h)
    try:
        with Image.open(path) as im:
            w, h = im.size
            return upright_size(w, h, exif_orientation(im)) if orient else (w, h)
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:  # as _pillow_image: a bad header
        raise InputError(path, f"unreadable image ({e})") from None


def read_image(path: str | Path, orient: bool = True) -> np.ndarray:
    """Float32 (H, W, 3) RGB in [0, 1]; 16-bit images are scaled by 1/65535, alpha is dropped.

    With ``orient`` the EXIF orientation of a photo is applied (the image as a viewer shows it);
    ``orient=False`` keeps the stored pixel order (what COLMAP reconstructs from).
    """
    return read_pixels(path, orient)[0]


def read_pixels(path: str | Path, orient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """(:func:`read_image`'s RGB, bool (H, W) valid pixels or None when all are): pixels are no
    data where transparent (alpha below half), NaN in a float TIFF, or GDAL's no-data value
    (GeoTIFF tag 42113) in every colour band. Their RGB is 0."""
    path = Path(path)
    if path.suffix.lower() in _TIFF_EXTS:
        return _tiff_image(path, orient)
    return _pillow_image(path, orient)


def read_mask(path: str | Path, size: tuple[int, int], orient: bool = True) -> np.ndarray:
    """A mask image as bool (H, W), True where it is not zero (COLMAP's convention: black pixels are
    ignored); it must be ``size`` (width, height) once turned upright with ``orient``."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            if orient and exif_orientation(im) != 1:
                im = ImageOps.exif_transpose(im)
            m = np.asarray(im.convert("L")) > 0
    except FileNotFoundError:
        raise InputError(path, "mask file not found") from None
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:
        raise InputError(path, f"unreadable mask ({e})") from None
    if (m.shape[1], m.shape[0]) != tuple(size):
        raise InputError(path, f"mask is {m.shape[1]}x{m.shape[0]} but its photo is {size[0]}x{size[1]}")
    return m


def read_masked(path: str | Path, mask: Path | None, orient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`read_pixels` of the photo at ``path``, with the pixels its ``mask`` image (if any,
    :func:`read_mask`) zeroes left out as well."""
    image, valid = read_pixels(path, orient)
    if mask is None:
        return image, valid
    m = read_mask(mask, (image.shape[1], image.shape[0]), orient)
    valid = _report_no_data(Path(mask), m if valid is None else valid & m, f"masked out for {Path(path).name}")
    return fill_no_data(image, valid), valid


#: Folder names of a scene's mask images, beside its photos' folder (COLMAP's ``--ImageReader.mask_path``
#: convention: the mask of ``NAME`` is ``NAME.png``).
MASK_FOLDERS = ("masks", "Masks")


def find_mask(photos: Path, name: str) -> Path | None:
    """The mask of the photo ``name`` (relative to the folder ``photos``) in a mask folder beside
    ``photos``: ``NAME.png`` as COLMAP names it, else the photo's name with ``.png`` for its
    extension; None when there is none."""
    for folder in MASK_FOLDERS:
        base = Path(photos).parent / folder
        for cand in (base / f"{name}.png", (base / name).with_suffix(".png")):
            if cand.is_file():
                return cand
    return None


def _pillow_image(path: Path, orient: bool) -> tuple[np.ndarray, np.ndarray | None]:
    from PIL import Image, ImageOps, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()  # decodes fully: truncated files fail here
            if orient and exif_orientation(im) != 1:
                im = ImageOps.exif_transpose(im)
            valid = None
            if "A" in im.getbands() or "transparency" in im.info:
                valid = _report_no_data(path, np.asarray(im.convert("RGBA").getchannel("A")) >= 128, "transparent")
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                rgb = np.repeat((np.asarray(im, dtype=np.float32) / 65535.0)[..., None], 3, axis=2)
            else:
                rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
            return fill_no_data(rgb, valid), valid
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
