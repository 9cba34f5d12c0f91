"""COLMAP models (text and binary) through pycolmap, producing the same Scene as LEVIR."""
from __future__ import annotations

import os
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
    assert list(s.views) == sorted(views) and s.layout == "colmap"
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


@pytest.mark.parametrize("binary", [True, False])
def test_of_several_models_the_largest_is_read_and_named(tmp_path, caplog, binary):
    """COLMAP's mapper writes one model a part of the flight it could join: of sparse/0 (3 photos) and
    sparse/1 (all 21) the larger is read, and the log lists them (sparse/0 was read, silently); a
    model's own folder reads that one, with the scene's photos and split.json two folders up."""
    import logging

    from dibrgs_core.bridge.describe import describe_scene  # the add-on reads the same model
    from dibrgs_core.data.colmap import colmap_models, image_count

    root = colmap_dir(tmp_path / "two", binary, sub="sparse/1")
    views, _ = make_views()
    small = [views[k].camera for k in sorted(views)[:3]]
    write_colmap_model(small, root / "sparse" / "0", binary=binary, points=np.zeros((0, 3)),
                       colors=np.zeros((0, 3), np.uint8))
    assert [(d.name, image_count(d)) for d in colmap_models(root)] == [("0", 3), ("1", 21)]
    assert find_colmap_model(root) == root / "sparse" / "1"
    with caplog.at_level(logging.WARNING, logger="dibrgs.io_colmap"):
        assert len(read_any_scene(root).views) == 21
    assert "holds 2 COLMAP models (0: 3 images, 1: 21 images): reading sparse/1" in caplog.text
    assert len(read_any_scene(root / "sparse" / "0").views) == 3
    (root / "split.json").write_text('{"train": ["000", "002"], "test": ["001"]}')  # the scene's, not the model's
    assert read_any_scene(root / "sparse" / "0").train == ["000", "002"]
    assert len(describe_scene(root)["views"]) == 21 and describe_scene(root / "sparse" / "0")["train"] == ["000", "002"]


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

def test_a_camera_rigs_folders_of_like_named_photos(tmp_path):
    """A rig writing the same file names into a folder per camera (left/0001.png, right/0001.png):
    every view is named by its path (left_0001), split.json may name them either way, and the add-on's
    description names them alike; names that still collide are one error naming the model."""
    import json

    from dibrgs_core.bridge.describe import describe_scene

    views, _ = make_views()
    cams = [v.camera for v in views.values()][:6]
    images = [v.image for v in views.values()][:6]
    rig = [f"{side}/{k:04d}" for side in ("left", "right") for k in range(3)]
    for c, name in zip(cams, rig):
        c.name = name
    root = tmp_path / "rig"
    write_colmap_model(cams, root / "sparse" / "0")
    for name, img in zip(rig, images):
        write_png(root / "images" / f"{name}.png", img)
    (root / "split.json").write_text(json.dumps({"train": ["left/0000.png", "right/0001", "left_0002"],
                                                 "test": ["right/0002.png"]}))
    s = read_colmap_scene(root)
    assert list(s.views) == [n.replace("/", "_") for n in rig]
    assert sorted(s.train) == ["left_0000", "left_0002", "right_0001"]
    assert s.test == ["right_0002"]
    for name, img in zip(rig, images):
        assert np.abs(s.views[name.replace("/", "_")].image - img).max() < 1 / 255
    desc = describe_scene(root)
    assert [v["name"] for v in desc["views"]] == list(s.views) and set(desc["train"]) == set(s.train)
    # a file name that is unique keeps its plain stem; paths that still collide are an error
    (root / "images" / "left_0000.png").write_bytes((root / "images" / "left" / "0000.png").read_bytes())
    cams[1].name = "left_0000"
    shutil.rmtree(root / "sparse")
    write_colmap_model(cams, root / "sparse" / "0")
    for read in (read_colmap_scene, describe_scene):
        with pytest.raises(InputError, match="images left/0000.png and left_0000.png share the view id 'left_0000'"):
            read(root)


@pytest.mark.parametrize("binary", [True, False])
def test_a_model_of_cameras_and_poses_only(tmp_path, binary):
    """No points3D file (known cameras and poses, as some exporters write them): read as the model
    with its points, by the library and by the add-on's description alike; images still required."""
    from dibrgs_core.bridge.describe import describe_scene

    root = colmap_dir(tmp_path / "c", binary)
    full = read_colmap_scene(root)
    (root / "sparse" / "0" / ("points3D.bin" if binary else "points3D.txt")).unlink()
    bare = read_colmap_scene(root)
    assert list(bare.views) == list(full.views)
    for k in full.views:
        assert np.array_equal(bare.views[k].camera.w2c, full.views[k].camera.w2c)
        assert np.array_equal(bare.views[k].camera.K, full.views[k].camera.K)
    assert [v["name"] for v in describe_scene(root)["views"]] == list(full.views)
    (root / "sparse" / "0" / ("images.bin" if binary else "images.txt")).unlink()
    with pytest.raises(InputError, match="COLMAP model file missing"):
        read_colmap_scene(root)


def test_a_damaged_points_file_is_not_read(tmp_path):
    """The pipeline never uses a model's points: a points3D.bin whose count says 2^40 points (on
    which pycolmap reads on without end) or that is garbage does not stop the cameras being read
    (a real subprocess, so a reader that hangs fails the test instead of the suite)."""
    import struct
    import subprocess
    import sys

    root = colmap_dir(tmp_path / "c", binary=True)
    points = root / "sparse" / "0" / "points3D.bin"
    body = points.read_bytes()
    for damaged in (struct.pack("<Q", 2**40) + body[8:], b"\xff" * 40):
        points.write_bytes(damaged)
        code = (f"from dibrgs_core.data.colmap import read_colmap_scene; "
                f"print(len(read_colmap_scene({str(root)!r}).views))")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0 and r.stdout.strip() == str(len(make_views()[0])), r.stderr[-2000:]


_DAMAGE = """
import random, sys
from pathlib import Path
from dibrgs_core.bridge.describe import describe_scene
from dibrgs_core.common.errors import InputError
from dibrgs_core.data.colmap import read_colmap_scene
root = Path(sys.argv[1])
files = sorted((root / "sparse" / "0").glob("*.bin"))
files = [f for f in files if f.stem != "points3D"]
good = {f: f.read_bytes() for f in files}
rng = random.Random(7)
for i in range(int(sys.argv[2])):
    f = rng.choice(files)
    b = bytearray(good[f])
    if rng.random() < 0.3:
        b = b[: rng.randrange(0, len(b))]
    else:
        for _ in range(rng.randint(1, 6)):
            b[rng.randrange(len(b))] = rng.randrange(256)
    f.write_bytes(bytes(b))
    for read in (read_colmap_scene, describe_scene):
        try:
            read(root)
        except InputError:
            pass
    f.write_bytes(good[f])
print("ok")
"""


@pytest.mark.slow
def test_a_damaged_binary_model_is_named_in_one_line(tmp_path):
    """cameras, images, rigs and frames files of a binary model with random bytes changed or cut short,
    through the library's reader (pycolmap) and the add-on's: each read gives the scene or one
    InputError, quickly (a count of frames' data ids, images' points or rigs' sensors beyond the
    file's end is refused before pycolmap would read past the end for minutes). A real subprocess
    with a timeout, so that a reader that hangs fails the test instead of the suite."""
    import subprocess
    import sys

    root = colmap_dir(tmp_path / "c", binary=True)
    r = subprocess.run([sys.executable, "-c", _DAMAGE, str(root), "120"], capture_output=True, text=True,
                       timeout=300, env={**os.environ, "DIBRGS_CACHE": str(tmp_path / "cache")})
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-3000:]
