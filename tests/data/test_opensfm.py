"""Scenes as OpenDroneMap and OpenSfM leave them (reconstruction.json + photos): the cameras the
LEVIR reader gives for the same views, OpenSfM's normalised camera models (the larger side as unit,
the centre as origin; Brown distortion) as the pinhole and distortion COLMAP undistorts, the largest
of several reconstructions, clear errors."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.load import read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import levir_as_opensfm, reads_as_levir  # noqa: E402


@pytest.mark.parametrize("odm", [True, False], ids=["odm-project", "opensfm-dataset"])
def test_reconstruction_json_reads_the_cameras_of_the_same_views(tiny_scene, tmp_path, caplog, odm):
    out = tmp_path / "odm"
    levir_as_opensfm(tiny_scene, out, odm=odm)
    rec = out / "opensfm" / "reconstruction.json" if odm else out / "reconstruction.json"
    with caplog.at_level("INFO", logger="dibrgs"):
        reads_as_levir(out, tiny_scene, [rec])
    assert "2 reconstructions (21, 2 shots), reading the largest" in caplog.text


def test_opensfm_camera_models_project_as_its_documentation_says(tiny_scene, tmp_path, monkeypatch):
    """A point seen through the camera the reader makes of a Brown camera lands where OpenSfM's
    "Geometric Models" put it: normalised u = f_x (d_r x + 2 p1 x y + p2 (r^2 + 2 x^2)) + c_x, in
    pixels w / 2 + max(w, h) u; a perspective camera (f, k1, k2) likewise."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    from dibrgs_core.data.frame_layouts import layout_frames

    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.4, 0.4, (50, 2))
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    brown = {"focal_x": 1.1, "focal_y": 1.05, "c_x": 0.02, "c_y": -0.03, "k1": -0.1, "k2": 0.02, "k3": 0.003,
             "p1": 0.002, "p2": -0.001, "width": 64, "height": 48}
    persp = {"projection_type": "perspective", "focal": 0.9, "k1": -0.05, "k2": 0.01, "width": 64, "height": 48}
    for k, cam in enumerate((brown, persp)):
        out = tmp_path / f"odm{k}"
        levir_as_opensfm(tiny_scene, out, camera=cam)
        for p in (out / "images").iterdir():  # the photos at the camera's size
            from PIL import Image

            Image.open(p).crop((0, 8, 64, 56)).save(p)
        frame = layout_frames(out)[0]
        model, params = frame.camera_model(*frame.size)
        got = pycolmap.Camera(model=model, width=64, height=48, params=params).img_from_cam(
            np.column_stack([xy, np.ones(len(xy))]))
        c = {"focal_x": cam.get("focal"), "focal_y": cam.get("focal"), "c_x": 0.0, "c_y": 0.0, "k3": 0.0, "p1": 0.0,
             "p2": 0.0, **cam}
        dr = 1 + c["k1"] * r2 + c["k2"] * r2**2 + c["k3"] * r2**3
        u = c["focal_x"] * (dr * x + 2 * c["p1"] * x * y + c["p2"] * (r2 + 2 * x * x)) + c["c_x"]
        v = c["focal_y"] * (dr * y + 2 * c["p2"] * x * y + c["p1"] * (r2 + 2 * y * y)) + c["c_y"]
        np.testing.assert_allclose(got, np.column_stack([32 + 64 * u, 24 + 64 * v]), atol=1e-9)
        view = read_any_scene(out).views["000"]
        assert view.image.shape[:2] == (view.camera.height, view.camera.width)


@pytest.mark.parametrize("case", ["fisheye", "photo", "broken", "shape", "camera", "empty", "images"])
def test_reconstructions_we_cannot_read_are_named(tiny_scene, tmp_path, case):
    out = tmp_path / "odm"
    levir_as_opensfm(tiny_scene, out, camera={"projection_type": "fisheye"} if case == "fisheye" else None)
    rec = out / "opensfm" / "reconstruction.json"
    data = json.loads(rec.read_text())
    expect = {"fisheye": "camera v2 synth: projection fisheye is not supported",
              "photo": "shot 004.png: photo 004.png not found", "broken": "unreadable reconstruction file",
              "shape": "shot 003.png: rotation and translation must be three finite numbers",
              "camera": "shot 002.png: camera 'other' is not in the reconstruction",
              "empty": "expected a list of reconstructions", "images": "image folder not found"}[case]
    if case == "photo":
        (out / "images" / "004.png").unlink()
    elif case == "broken":
        rec.write_text(rec.read_text()[:100])
    elif case == "shape":
        data[0]["shots"]["003.png"]["rotation"] = [0.1, 0.2]
    elif case == "camera":
        data[0]["shots"]["002.png"]["camera"] = "other"
    elif case == "empty":
        data = []
    elif case == "images":
        (out / "images").rename(out / "photos")
    if case in ("shape", "camera", "empty"):
        rec.write_text(json.dumps(data))
    with pytest.raises(InputError) as e:
        read_any_scene(out)
    assert expect in str(e.value)


def test_odm_masks_beside_the_photos_mark_pixels_without_data(tiny_scene, tmp_path):
    """OpenDroneMap's masks (NAME_mask.EXT beside the photo, black = left out): the view's pixels
    under black are without data, the others are the photo's."""
    from PIL import Image

    out = tmp_path / "odm"
    levir_as_opensfm(tiny_scene, out)
    mask = np.full((64, 64), 255, np.uint8)
    mask[:, :16] = 0
    Image.fromarray(mask).save(out / "images" / "003_mask.png")
    scene, levir = read_any_scene(out), read_any_scene(tiny_scene, load_depth=False)
    valid = scene.views["003"].valid
    assert valid is not None and not valid[:, :16].any() and valid[:, 16:].all()
    np.testing.assert_array_equal(scene.views["003"].image[:, 16:], levir.views["003"].image[:, 16:])
    assert scene.views["004"].valid is None  # no mask: every pixel holds data
