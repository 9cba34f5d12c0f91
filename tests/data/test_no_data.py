"""Photos with pixels that hold no data (the black or transparent fill of a rectified or clipped
image, NaN or a GDAL no-data value in a GeoTIFF, a mask image beside the photos): read as a view's
``valid`` map, in every layout, through undistortion, and into the scene's digest."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import tifffile
from PIL import Image

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.common.errors import InputError
from dibrgs_core.data.colmap import read_colmap_scene
from dibrgs_core.data.images import read_masked, read_pixels
from dibrgs_core.data.levir import read_scene, write_scene
from dibrgs_core.data.scene import View
from dibrgs_core.data.frame_layouts import read_frames_scene

from photo_synth import H, W, pattern, save_turned_jpeg, write_distorted_model

RGB8 = (pattern(W, H) * 255).astype(np.uint8)


def _corner(h: int = H, w: int = W) -> np.ndarray:
    """bool (h, w), False over a triangle in the top-left corner (a rectified photo's fill), about 1/8 of it."""
    y, x = np.mgrid[0:h, 0:w]
    return x / w + y / h >= 0.5


def test_every_kind_of_no_data_reads_as_a_valid_map(tmp_path, caplog):
    """Alpha below half, NaN bands, GDAL's no-data tag and a TIFF alpha band mark pixels without data;
    their RGB reads 0, the rest as stored; opaque photos have no map; the log names each file once."""
    ok = _corner()
    alpha = np.where(ok, 255, 0).astype(np.uint8)
    Image.fromarray(np.dstack([RGB8, alpha])).save(tmp_path / "a.png")
    Image.fromarray(np.dstack([RGB8, np.full((H, W), 255, np.uint8)])).save(tmp_path / "opaque_rgba.png")
    Image.fromarray(RGB8).save(tmp_path / "opaque.jpg", quality=95)
    f = RGB8.astype(np.float32) / 255
    tifffile.imwrite(tmp_path / "nan.tif", np.where(ok[..., None], f, np.nan), photometric="rgb")
    # GDAL writes no-data as ASCII; a black pixel inside the data (one band 0) stays data
    gdal = np.where(ok[..., None], np.maximum(RGB8, 1), 0).astype(np.uint8)
    gdal[-1, -1] = (0, 5, 5)
    tifffile.imwrite(tmp_path / "gdal.tif", gdal, photometric="rgb", extratags=[(42113, "s", 0, "0", True)])
    tifffile.imwrite(tmp_path / "rgba16.tif", np.dstack([RGB8.astype(np.uint16) * 257, alpha.astype(np.uint16) * 257]),
                     photometric="rgb", extrasamples=["unassalpha"])
    # four bands with no alpha marked (red, green, blue, near infrared): all data
    tifffile.imwrite(tmp_path / "rgbn.tif", np.dstack([RGB8, np.zeros((H, W), np.uint8)]), photometric="rgb",
                     extrasamples=["unspecified"])
    with caplog.at_level(logging.INFO, logger="dibrgs.images"):
        for _ in range(2):
            for name in ("a.png", "nan.tif", "gdal.tif", "rgba16.tif"):
                image, valid = read_pixels(tmp_path / name)
                assert valid is not None and np.array_equal(valid, ok), name
                assert (image[~ok] == 0).all(), name
                stored = gdal if name == "gdal.tif" else RGB8
                assert np.abs(image[ok] - stored[ok] / 255.0).max() < 1e-6, name
            for name in ("opaque_rgba.png", "opaque.jpg", "rgbn.tif"):
                assert read_pixels(tmp_path / name)[1] is None, name
    # LZW-compressed (tifffile needs imagecodecs for it, so Pillow reads it): the tag still counts,
    # 8-bit RGB and 16-bit grey alike
    from PIL import TiffImagePlugin

    for name, data, value in (("lzw8.tif", gdal, "0"), ("lzw16.tif", np.where(ok, 1000, 7).astype(np.uint16), "7")):
        tags = TiffImagePlugin.ImageFileDirectory_v2()
        tags[42113], tags.tagtype[42113] = value, 2
        Image.fromarray(data).save(tmp_path / name, compression="tiff_lzw", tiffinfo=tags)
        image, valid = read_pixels(tmp_path / name)
        assert valid is not None and np.array_equal(valid, ok) and (image[~ok] == 0).all(), name
    lines = [r.getMessage() for r in caplog.records if "left out" in r.getMessage() and "lzw" not in r.getMessage()]
    share = f"{100 * (1 - ok.mean()):.1f} % of its pixels are"
    assert len(lines) == 4, lines
    assert f"a.png: {share} transparent: left out of training, evaluation and geometry" in lines[0]
    assert f"nan.tif: {share} NaN" in lines[1]
    assert f"gdal.tif: {share} GDAL no-data (0)" in lines[2]
    assert f"rgba16.tif: {share} transparent" in lines[3]


def _grid_cameras(n: int = 3) -> list[Camera]:
    K = np.array([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]])
    return [Camera(K=K, w2c=look_at([10.0 * i, 0, 100], [10.0 * i, 0, 0], [0, 1, 0]), width=W, height=H,
                   name=f"{i:03d}") for i in range(n)]



@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_a_mask_turns_upright_with_its_photo(tmp_path, orientation):
    """A photo stored turned (a camera held on its side, EXIF orientation 3, 6 or 8) is read upright;
    its mask counts where it is upright too: a mask stored turned the same way with the same tag,
    and one saved upright without a tag, leave out the same pixels of the upright photo."""
    up = _corner()
    photo = tmp_path / "p.jpg"
    save_turned_jpeg(photo, pattern(W, H), orientation)
    im = Image.fromarray(np.where(up, 255, 0).astype(np.uint8))
    turn = {3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270}[orientation]
    stored = im.transpose(turn)
    exif = stored.getexif()
    exif[0x0112] = orientation
    stored.save(tmp_path / "turned.png", exif=exif)
    im.save(tmp_path / "upright.png")
    for mask in ("turned.png", "upright.png"):
        image, valid = read_masked(photo, tmp_path / mask)
        assert image.shape[:2] == (H, W) and valid is not None
        np.testing.assert_array_equal(valid, up, err_msg=mask)
        assert (image[~up] == 0).all()

def test_levir_masks_round_trip_and_change_the_digest(tmp_path):
    """A view's valid map is written as Masks/NNN.png and read back the same; a scene whose masks differ
    has another digest (caches never mix them), one without masks the digest it always had."""
    cams = _grid_cameras()
    img = RGB8.astype(np.float32) / 255
    masked = {c.name: View(c, np.where(_corner()[..., None], img, 0.0).astype(np.float32), valid=_corner())
              for c in cams}
    plain = {c.name: View(c, img) for c in cams}
    write_scene(tmp_path / "m", masked)
    write_scene(tmp_path / "p", plain)
    assert sorted(p.name for p in (tmp_path / "m" / "Masks").iterdir()) == ["000.png", "001.png", "002.png"]
    assert not (tmp_path / "p" / "Masks").exists()
    sm, sp = read_scene(tmp_path / "m"), read_scene(tmp_path / "p")
    for k in masked:
        assert np.array_equal(sm.views[k].valid, _corner())
        assert sp.views[k].valid is None
    assert sm.digest() != sp.digest()
    # dibrgs info names the share of each photo without data (none for the plain scene)
    from dibrgs_core.commands.info import summarize

    share = round(float(1 - _corner().mean()), 4)
    assert summarize(sm)["no_data"] == {"000": share, "001": share, "002": share}
    assert "no_data" not in summarize(sp)
    # the digest of a scene without masks is that of its views' pixels alone, as before masks existed
    from dibrgs_core.data.scene import pixels_digest

    assert sp.views["000"].pixels_digest() == pixels_digest(sp.views["000"].image)


def test_colmap_masks_folder_and_undistortion(tmp_path, monkeypatch):
    """COLMAP's convention (masks/NAME.png, black = no data) gives the valid map, and a distorted camera's
    map goes through the same undistortion as its photo: invalid exactly where the undistorted photo
    draws on masked pixels (checked against undistorting the mask alone)."""
    import pycolmap

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    root = tmp_path / "s"
    params = [80.0, W / 2, H / 2, -0.25]
    write_distorted_model(root, "SIMPLE_RADIAL", params)
    (root / "masks").mkdir()
    Image.fromarray(np.where(_corner(), 255, 0).astype(np.uint8)).save(root / "masks" / "v0.png.png")
    Image.fromarray(np.where(_corner(), 255, 0).astype(np.uint8)).save(root / "masks" / "v1.png")  # stem.png
    for _ in range(2):  # the second read comes from the undistortion cache
        s = read_colmap_scene(root)
        v0, v1, v2 = s.views.values()
        assert v2.valid is None
        cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=params)
        bitmap, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(),
                                             pycolmap.Bitmap.from_array(np.where(_corner(), 255, 0).astype(np.uint8)), cam)
        want = np.asarray(bitmap.to_array()).reshape(v0.camera.height, v0.camera.width, -1)[..., 0] == 255
        for v in (v0, v1):
            assert np.array_equal(v.valid, want)
            assert (v.image[~want] == 0).all() and v.image[want].mean() > 0.2
        assert 0.05 < 1 - want.mean() < 0.3


def test_transforms_mask_path_and_a_bad_mask(tmp_path):
    """nerfstudio's per-frame mask_path is read, and masks/NAME.png beside the photos' folder; a missing
    mask file or one of another size is one clear error."""
    (tmp_path / "images").mkdir()
    (tmp_path / "m").mkdir()
    frames = []
    for i in range(3):
        Image.fromarray(RGB8).save(tmp_path / "images" / f"f{i}.png")
        c2w = np.eye(4)
        c2w[:3, 3] = [10.0 * i, 0, 100]
        fr = {"file_path": f"images/f{i}.png", "transform_matrix": c2w.tolist()}
        if i == 1:
            Image.fromarray(np.where(_corner(), 255, 0).astype(np.uint8)).save(tmp_path / "m" / "f1.png")
            fr["mask_path"] = "m/f1.png"
        frames.append(fr)
    meta = {"fl_x": 80.0, "fl_y": 80.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    (tmp_path / "masks").mkdir()  # COLMAP's naming, beside the photos' folder
    Image.fromarray(np.where(~_corner(), 255, 0).astype(np.uint8)).save(
        tmp_path / "masks" / "f2.png.png")
    s = read_frames_scene(tmp_path)
    valid = [v.valid for v in s.views.values()]
    assert valid[0] is None and np.array_equal(valid[1], _corner()) and np.array_equal(valid[2], ~_corner())
    Image.fromarray(np.zeros((H // 2, W // 2), np.uint8)).save(tmp_path / "m" / "f1.png")
    with pytest.raises(InputError, match=r"f1.png.*mask is 48x32 but its photo is 96x64"):
        read_frames_scene(tmp_path)
    frames[1]["mask_path"] = "m/gone.png"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="mask_path m/gone.png not found"):
        read_frames_scene(tmp_path)


def test_a_training_photo_without_a_pixel_of_data_is_a_clear_error(tmp_path, capsys):
    """`dibrgs train` on a split whose training photo is masked everywhere: one line naming it, exit 2,
    nothing trained (it trained on nothing, every loss 0)."""
    from dibrgs_core.cli import main

    cams = _grid_cameras()
    img = RGB8.astype(np.float32) / 255
    views = {c.name: View(c, img) for c in cams}
    views["001"] = View(cams[1], np.zeros_like(img), valid=np.zeros((H, W), bool))
    write_scene(tmp_path / "s", views)
    code = main(["train", str(tmp_path / "s"), "--out", str(tmp_path / "w"), "--preset", "test",
                 "--train", "000,001", "--test", "002"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "training photo 001 holds no pixel of data" in err[-1] and "--train" in err[-1], err
    assert not (tmp_path / "w" / "model.pt").exists()


def test_frames_weigh_a_pixel_only_where_all_it_is_drawn_from_holds_data():
    """At half resolution a frame pixel drawn from any pixel without data weighs 0 (its colour is mixed
    with the fill), the others 1; a view without such pixels gets no mask; a frame with none left is
    not one to score."""
    from dibrgs_core.training.frames import frame_valid, has_data, views_to_frames

    cam = _grid_cameras(1)[0]
    img = RGB8.astype(np.float32) / 255
    ok = np.ones((H, W), bool)
    ok[:9, :9] = False  # odd: the half-resolution pixels (0..4, 0..4) each draw on some of it
    masked, plain, empty = views_to_frames([View(cam, img, valid=ok), View(cam, img),
                                            View(cam, img, valid=np.zeros((H, W), bool))], 0.5)
    want = np.ones((H // 2, W // 2), bool)
    want[:5, :5] = False
    assert np.array_equal(frame_valid(masked), want) and set(np.unique(masked.mask.numpy())) == {0.0, 1.0}
    assert plain.mask is None and frame_valid(plain) is None
    assert has_data(masked) and has_data(plain) and not has_data(empty)
