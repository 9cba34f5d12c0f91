"""Photographs as users have them: COLMAP cameras with lens distortion (undistorted on load with
pycolmap, cached by content), JPEG with an EXIF rotation, any aspect ratio, photos of several sizes."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.common.errors import InputError
from dibrgs_core.data.colmap import read_colmap_cameras, read_colmap_scene
from dibrgs_core.data.levir import read_scene
from dibrgs_core.data.load import read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import H, W, pattern, write_distorted_model, write_turned_levir_scene  # noqa: E402
from paths import REPO  # noqa: E402

DISTORTED = [("SIMPLE_RADIAL", [80.0, W / 2, H / 2, -0.25]),
             ("RADIAL", [80.0, W / 2, H / 2, -0.25, -0.05]),
             ("OPENCV", [80.0, 80.0, W / 2, H / 2, -0.25, 0.05, 0.002, -0.002]),
             ("FULL_OPENCV", [80.0, 80.0, W / 2, H / 2, -0.25, 0.05, 0.002, -0.002, 0.01, 0.0, 0.0, 0.0])]


def _error_against_ideal(image: np.ndarray, Kc: np.ndarray, K: np.ndarray) -> tuple[float, float]:
    """Mean |image - ideal| where pinhole ``Kc``'s ray lands well inside the ideal image (``K``), and that share."""
    h, w = image.shape[:2]
    v_, u_ = np.mgrid[0:h, 0:w].astype(np.float64)
    px = K[0, 0] * (u_ + 0.5 - Kc[0, 2]) / Kc[0, 0] + K[0, 2] - 0.5
    py = K[1, 1] * (v_ + 0.5 - Kc[1, 2]) / Kc[1, 1] + K[1, 2] - 0.5
    inside = (px > 3) & (px < W - 4) & (py > 3) & (py < H - 4)
    want = pattern(W, H)[np.round(py[inside]).astype(int), np.round(px[inside]).astype(int)]
    return float(np.abs(image[inside] - want).mean()), float(inside.mean())


@pytest.mark.parametrize("model,params", DISTORTED, ids=[m for m, _ in DISTORTED])
def test_distorted_colmap_model_is_undistorted_on_load(tmp_path, monkeypatch, model, params):
    """The photos come back as pinhole images: the undistorted camera is pycolmap's, the poses are kept, and
    each pixel shows what the ideal pinhole image shows along the same ray (within resampling error)."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    root = tmp_path / model
    K, w2cs = write_distorted_model(root, model, params)
    s = read_colmap_scene(root)
    und = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(),
                                    pycolmap.Camera(model=model, width=W, height=H, params=params))
    for i, v in enumerate(s.views.values()):
        c = v.camera
        assert (c.width, c.height) == (und.width, und.height) and np.allclose(c.K, und.calibration_matrix())
        assert np.allclose(c.w2c, w2cs[i], atol=1e-9)
        assert v.image.shape == (c.height, c.width, 3)
        # Each undistorted pixel shows what the ideal pinhole image shows along its ray (resampling error only).
        err, share = _error_against_ideal(v.image, c.K, K)
        assert share > 0.5 and err < 0.02, (model, err, share)
    # The distorted photo taken as a pinhole is far off: the check above can tell undistorted from not.
    raw = np.asarray(Image.open(root / "images" / "v0.png"), np.float32) / 255.0
    raw_err, _ = _error_against_ideal(raw, K, K)
    assert raw_err > 3 * err, (raw_err, err)
    assert [c.width for c in read_colmap_cameras(root)] == [und.width] * 3


def test_undistortion_cache_is_keyed_by_content(tmp_path, monkeypatch):
    """The undistorted photos are cached; an edited photo or camera gets a new entry, never the old one."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("DIBRGS_CACHE", str(cache))
    root = tmp_path / "m"
    write_distorted_model(root, "OPENCV", DISTORTED[2][1])
    a = read_colmap_scene(root)
    entries = sorted((cache / "undistorted").glob("*.npy"))
    assert len(entries) == 1  # three identical photos of one camera: one entry
    b = read_colmap_scene(root)  # from the cache
    before = {k: v.image for k, v in a.views.items()}
    assert all(np.array_equal(before[k], b.views[k].image) for k in a.views)
    img = np.asarray(Image.open(root / "images" / "v1.png")).copy()
    img[:8] = 255
    Image.fromarray(img).save(root / "images" / "v1.png")
    c = read_colmap_scene(root)
    assert len(list((cache / "undistorted").glob("*.npy"))) == 2
    assert not np.array_equal(c.views["v1"].image, before["v1"])
    assert np.array_equal(c.views["v0"].image, before["v0"])
    # The scene read before the edit does not pass the new pixels off as the old ones.
    with pytest.raises(InputError, match="changed since the scene was read"):
        a.views["v1"].image
    # An unwritable cache is only a warning.
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "file"))
    (tmp_path / "file").write_text("not a folder")
    assert np.array_equal(read_colmap_scene(root).views["v0"].image, before["v0"])


def test_fisheye_and_other_models_are_clear_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    for model, params, says in [("OPENCV_FISHEYE", [80, 80, W / 2, H / 2, 0.1, 0, 0, 0], "a fisheye model"),
                                ("SIMPLE_RADIAL_FISHEYE", [80, W / 2, H / 2, 0.1], "a fisheye model"),
                                ("FOV", [80, 80, W / 2, H / 2, 0.5], "a fisheye model")]:
        root = tmp_path / model
        write_distorted_model(root, model, params)
        with pytest.raises(InputError, match=f"{model} is {says}.*colmap image_undistorter") as e:
            read_any_scene(root)
        assert e.value.path == root / "sparse" / "0"


# -- JPEG photos with an EXIF orientation ------------------------------------------------------
@pytest.mark.parametrize("orientation", [6, 8, 3])
def test_jpeg_scene_with_exif_rotation(tmp_path, orientation):
    """A LEVIR-layout scene of 3:2 JPEG photos stored rotated with an EXIF orientation: read upright, at
    the cameras' size, with the pixels where the camera says."""
    root = tmp_path / "scene"
    ups = write_turned_levir_scene(root, [orientation, orientation, 1, orientation])
    (root / "split.json").write_text('{"train": ["000.jpg", "002.JPG", "003"], "test": ["001"]}')
    s = read_scene(root)
    assert list(s.sizes()) == [(W, H)] and s.train == ["000", "002", "003"] and s.test == ["001"]
    for k, v in s.views.items():
        assert v.image.shape == (H, W, 3)
        assert np.abs(v.image - ups[k]).mean() < 0.02, k  # JPEG loss only; a rotated read would be far off


def test_colmap_photos_keep_colmaps_pixel_order(tmp_path, monkeypatch):
    """COLMAP ignores EXIF orientation, so a COLMAP model of rotated JPEGs describes the stored pixels; an
    EXIF tag is followed only when the stored pixels do not fit the camera and the upright ones do."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    root = tmp_path / "m"
    write_distorted_model(root, "PINHOLE", [80.0, 80.0, W / 2, H / 2])
    stored = np.asarray(Image.open(root / "images" / "v0.png"), np.float32) / 255.0
    for i in range(3):  # the same pixels as JPEG, tagged "rotate 90": COLMAP would still see W x H
        img = Image.open(root / "images" / f"v{i}.png")
        exif = img.getexif()
        exif[0x0112] = 6
        img.save(root / "images" / f"v{i}.jpg", quality=95, exif=exif)
        (root / "images" / f"v{i}.png").unlink()
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    for im in rec.images.values():
        im.name = im.name.replace(".png", ".jpg")
    rec.write_text(str(root / "sparse" / "0"))
    s = read_colmap_scene(root)
    assert s.views["v0"].image.shape == (H, W, 3)
    assert np.abs(s.views["v0"].image - stored).mean() < 0.02
    # A model whose camera is the upright size (made from rotated copies) gets the upright photos.
    rec.cameras[1] = pycolmap.Camera(model="PINHOLE", width=H, height=W, params=[80.0, 80.0, H / 2, W / 2],
                                     camera_id=1)
    rec.write_text(str(root / "sparse" / "0"))
    s = read_colmap_scene(root)
    assert s.views["v0"].image.shape == (W, H, 3)
    assert np.abs(s.views["v0"].image - np.rot90(stored, -1)).mean() < 0.02


def test_a_scene_of_many_photos_holds_its_cameras_not_its_pixels(tmp_path):
    """Reading decodes each photo once, one at a time, and keeps none of them: a COLMAP project of
    hundreds of 20 MP photos must not need their float32 copies (24 GB for 100) in memory. A view's
    image is read from its file when used, equal to the photo.

    Measured in a fresh process after a first read of another project: in the test process, a
    process-wide table (Python's interned strings) could grow inside the traced read, by more than
    the photos, depending on the tests that ran before."""
    from dibrgs_core.data.colmap import write_colmap_model

    w, h, n = 480, 320, 12
    one = w * h * 3 * 4  # one float32 photo
    cams = [Camera(K=np.array([[400.0, 0, w / 2], [0, 400.0, h / 2], [0, 0, 1]]),
                   w2c=look_at([3.0 * i, 0.0, 50.0], [3.0 * i, 0.0, 0.0], [0, 1.0, 0]), width=w, height=h,
                   name=f"p{i:02d}") for i in range(n)]

    def project(root: Path, seed: int) -> dict[str, np.ndarray]:
        write_colmap_model(cams, root / "sparse" / "0")
        rng = np.random.default_rng(seed)
        (root / "images").mkdir()
        photos = {}
        for c in cams:
            photos[c.name] = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            Image.fromarray(photos[c.name]).save(root / "images" / f"{c.name}.png")
        return photos

    root = tmp_path / "project"
    photos = project(root, 0)
    project(tmp_path / "other", 1)
    # The first read loads what any read needs on first use; the second is this scene's.
    code = ("import json, sys, tracemalloc\n"
            "from dibrgs_core.data.load import read_any_scene\n"
            "read_any_scene(sys.argv[1])\n"
            "tracemalloc.start()\n"
            "scene = read_any_scene(sys.argv[2])\n"
            "print(json.dumps(tracemalloc.get_traced_memory()))\n")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "other"), str(root)], capture_output=True,
                         text=True, timeout=300, check=False, cwd=REPO)
    assert out.returncode == 0, out.stderr
    held, peak = json.loads(out.stdout.strip().splitlines()[-1])
    assert held < one / 2, f"the scene holds {held / one:.1f} photos' worth of memory"
    assert peak < 6 * one, f"reading peaked at {peak / one:.1f} photos' worth"
    scene = read_any_scene(root)
    assert all(np.array_equal(scene.views[k].image, photos[k] / np.float32(255)) for k in ("p00", "p07"))


def test_photos_of_different_sizes_are_each_read_at_their_own(tmp_path, capsys):
    """Two COLMAP cameras of different sizes (a portrait camera among landscape ones): each photo is read
    at its camera's size, with its own pixels, and ``dibrgs info`` lists the sizes."""
    from dibrgs_core.cli import main
    from dibrgs_core.data.colmap import write_colmap_model

    cams = [Camera(K=np.array([[80.0, 0, w / 2], [0, 80.0, h / 2], [0, 0, 1]]),
                   w2c=look_at([10.0 * i, 0.0, 100.0], [10.0 * i, 0.0, 0.0], [0, 1.0, 0]), width=w, height=h,
                   name=f"v{i}") for i, (w, h) in enumerate(((96, 64), (64, 96), (96, 64)))]
    root = tmp_path / "m"
    write_colmap_model(cams, root / "sparse" / "0")
    (root / "images").mkdir()
    for c in cams:
        photo = np.round(pattern(c.width, c.height) * 255).astype(np.uint8)
        Image.fromarray(photo).save(root / "images" / f"{c.name}.png")
    scene = read_colmap_scene(root)
    for c in cams:
        v = scene.views[c.name]
        assert (v.camera.width, v.camera.height) == (c.width, c.height) and np.allclose(v.camera.K, c.K)
        assert np.abs(v.image - pattern(c.width, c.height)).max() <= 0.5 / 255 + 1e-6
    assert scene.sizes() == {(96, 64): ["v0", "v2"], (64, 96): ["v1"]}
    assert main(["info", str(root)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["resolution"] == [96, 64] and info["sizes"] == {"96x64": ["v0", "v2"], "64x96": ["v1"]}


def test_tiff_photos_of_any_depth_and_band_layout(tmp_path):
    """TIFF photos as remote sensing has them: 16-bit RGB and RGBA (Pillow gave RGB values off by up to
    0.98), band-sequential multi-band, 16-bit grey, float reflectance with NaN no-data; 8-bit TIFFs read
    as Pillow read them, orientation tag included; a float image outside [0, 1] is an error naming it."""
    import tifffile
    from PIL import ImageOps

    from dibrgs_core.data.images import image_size, read_image

    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 65536, (20, 30, 4), dtype=np.uint16)
    cases = {"rgb16.tif": (rgba[..., :3], {"photometric": "rgb"}),
             "rgba16.tif": (rgba, {"photometric": "rgb", "extrasamples": ["unassalpha"]}),
             "bands4.tif": (np.moveaxis(rgba, 2, 0), {"photometric": "minisblack", "planarconfig": "separate"}),
             "grey16.tif": (rgba[..., 0], {"photometric": "minisblack"})}
    for name, (data, kw) in cases.items():
        tifffile.imwrite(tmp_path / name, data, **kw)
        want = rgba[..., :3] if name != "grey16.tif" else np.repeat(rgba[..., :1], 3, axis=2)
        if name == "rgba16.tif":  # pixels under half opaque hold no data (tests/data/test_no_data.py)
            want = np.where(rgba[..., 3:] > 65535 / 2, want, 0)
        got = read_image(tmp_path / name)
        assert got.shape == (20, 30, 3) and np.abs(got - want / 65535.0).max() < 1e-6, name
        assert image_size(tmp_path / name) == (30, 20)
    refl = rng.random((20, 30, 3)).astype(np.float32)
    refl[0, 0] = np.nan
    refl[1, 1] = -0.002
    tifffile.imwrite(tmp_path / "refl.tif", refl, photometric="rgb")
    got = read_image(tmp_path / "refl.tif")
    assert got[0, 0].tolist() == [0, 0, 0] and got[1, 1].tolist() == [0, 0, 0]
    assert np.array_equal(got[2:], refl[2:])
    tifffile.imwrite(tmp_path / "radiance.tif", refl * 300, photometric="rgb")
    with pytest.raises(InputError, match="values up to 2.*expected \\[0, 1\\]") as e:
        read_image(tmp_path / "radiance.tif")
    assert e.value.path == tmp_path / "radiance.tif"
    # LZW (as most GeoTIFFs): tifffile needs imagecodecs (numpy 2 only), so Pillow reads what it reads right
    grey16 = rgba[..., 0]
    Image.fromarray(grey16).save(tmp_path / "grey16_lzw.tif", compression="tiff_lzw")
    assert np.array_equal(read_image(tmp_path / "grey16_lzw.tif")[..., 1] * np.float32(65535), grey16)
    rgb8 = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    Image.fromarray(rgb8).save(tmp_path / "rgb8_lzw.tif", compression="tiff_lzw")
    assert np.array_equal(read_image(tmp_path / "rgb8_lzw.tif"), rgb8 / np.float32(255))
    # ... and what Pillow would misread is an error that says what to do (the tag says LZW)
    f = tmp_path / "rgba16_lzw.tif"
    shutil.copy(tmp_path / "rgba16.tif", f)
    with tifffile.TiffFile(f) as tf:
        at = tf.pages[0].tags["Compression"].valueoffset
    with open(f, "r+b") as fh:
        fh.seek(at)
        fh.write((5).to_bytes(2, "little"))
    with pytest.raises(InputError, match="LZW-compressed 16-bit TIFF of 4 bands: .*save it uncompressed"):
        read_image(f)
    for o in range(1, 9):
        f = tmp_path / f"o{o}.tif"
        tifffile.imwrite(f, rgb8, photometric="rgb", extratags=[(274, "H", 1, o, True)])
        with Image.open(f) as im:
            pillow = np.asarray(ImageOps.exif_transpose(im).convert("RGB"), np.float32) / 255.0
        assert np.array_equal(read_image(f), pillow) and image_size(f) == pillow.shape[1::-1], o
        assert np.array_equal(read_image(f, orient=False), rgb8 / np.float32(255))
