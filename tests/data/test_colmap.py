"""COLMAP models (text and binary) through pycolmap, producing the same Scene as LEVIR."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.colmap import find_colmap_model, read_colmap_cameras, read_colmap_scene, write_colmap_model
from dibrgs_core.data.load import read_any_scene
from dibrgs_core.data.images import write_png

from test_levir import H, W, make_views

pycolmap = pytest.importorskip("pycolmap")


def colmap_dir(root: Path, binary: bool, sub: str = "sparse/0") -> Path:
    views, _ = make_views()
    cams = [v.camera for v in views.values()]
    rng = np.random.default_rng(0)
    write_colmap_model(cams, root / sub, binary=binary, points=rng.normal(size=(10, 3)),
                       colors=rng.integers(0, 255, (10, 3)))
    for v in views.values():
        write_png(root / "images" / f"{v.name}.png", v.image)
    return root


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_round_trip(tmp_path, binary):
    root = colmap_dir(tmp_path / "c", binary)
    model = root / "sparse" / "0"
    assert (model / ("cameras.bin" if binary else "cameras.txt")).is_file()
    views, _ = make_views()
    s = read_colmap_scene(root)
    assert list(s.views) == sorted(views)
    for k, v in views.items():
        c = s.views[k].camera
        assert np.abs(c.K - v.camera.K).max() < 1e-9
        # COLMAP stores the rotation as a quaternion: exact up to float rounding.
        assert np.abs(c.w2c - v.camera.w2c).max() < 1e-9 * 300
        assert (c.width, c.height) == (W, H)
        assert np.abs(s.views[k].image - v.image).max() < 1 / 255
        assert s.views[k].depth is None
    assert s.train == ["001", "008", "015"] and len(s.test) == 17
    assert len(read_colmap_cameras(root)) == 21
    # read_any_scene picks the layout.
    assert list(read_any_scene(root).views) == list(s.views)


def test_model_location_variants(tmp_path):
    root = colmap_dir(tmp_path / "flat", True, sub="sparse")
    assert find_colmap_model(root) == root / "sparse"
    assert len(read_colmap_scene(root, train_ids=["003"]).train) == 1
    assert find_colmap_model(tmp_path) is None
    with pytest.raises(InputError, match="not a scene"):
        read_any_scene(tmp_path)


def test_missing_model_file(tmp_path):
    root = colmap_dir(tmp_path / "c", True)
    (root / "sparse" / "0" / "images.bin").unlink()
    with pytest.raises(InputError, match="model file missing") as e:
        read_colmap_scene(root)
    assert e.value.path.name == "images.bin"


def test_corrupt_model(tmp_path):
    root = colmap_dir(tmp_path / "c", False)
    (root / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 24\n")
    with pytest.raises(InputError, match="unreadable COLMAP model"):
        read_colmap_scene(root)


def test_missing_image_and_size_mismatch(tmp_path):
    root = colmap_dir(tmp_path / "c", True)
    (root / "images" / "004.png").unlink()
    with pytest.raises(InputError, match="image file missing") as e:
        read_colmap_scene(root)
    assert e.value.path == root / "images" / "004.png"
    write_png(root / "images" / "004.png", np.zeros((H, W + 1, 3)))
    with pytest.raises(InputError, match=f"{W + 1}x{H} but its COLMAP camera is {W}x{H}"):
        read_colmap_scene(root)
    shutil.rmtree(root / "images")
    with pytest.raises(InputError, match="image folder not found"):
        read_colmap_scene(root)


def test_zero_distortion_loads_and_fisheye_is_refused(tmp_path):
    """A distortion model with all-zero parameters is a pinhole (no resampling); fisheye models are a
    clear error naming the model and what to do (distorted models: tests/data/test_undistort.py)."""
    root = colmap_dir(tmp_path / "c", True)
    model = root / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    cam = rec.cameras[1]
    f, cx, cy = cam.params[0], cam.params[2], cam.params[3]
    rec.cameras[1] = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=[f, cx, cy, 0.0],
                                     camera_id=1)
    rec.write_binary(str(model))
    # fx != fy in the fixture, so SIMPLE_RADIAL changes camera 1's fy; it still loads.
    s = read_colmap_scene(root)
    assert s.views["000"].camera.fy == pytest.approx(f)
    assert (s.views["000"].camera.width, s.views["000"].camera.height) == (W, H)
    rec.cameras[1] = pycolmap.Camera(model="OPENCV_FISHEYE", width=W, height=H,
                                     params=[f, f, cx, cy, 0, 0, 0, 0], camera_id=1)
    rec.write_binary(str(model))
    with pytest.raises(InputError, match="OPENCV_FISHEYE is a fisheye model.*image_undistorter"):
        read_colmap_scene(root)