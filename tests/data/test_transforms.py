"""Scenes in the transforms.json layout (instant-ngp, nerfstudio, Blender's NeRF exporters): the
cameras the LEVIR reader gives for the same views, OpenGL axes turned into OpenCV ones, lens
distortion undistorted as COLMAP's, the split of part files, clear errors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.load import read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import assert_same_views, levir_as_transforms, opengl_c2w  # noqa: E402


@pytest.mark.parametrize("per_frame", [False, True], ids=["shared-intrinsics", "per-frame"])
def test_transforms_json_reads_the_cameras_of_the_same_views(tiny_scene, tmp_path, per_frame):
    out = tmp_path / "ngp"
    levir_as_transforms(tiny_scene, out, per_frame)
    levir, ngp = read_any_scene(tiny_scene, load_depth=False), read_any_scene(out)
    assert_same_views(ngp, levir)
    assert ngp.train == levir.train
    # as cameras to render (`dibrgs render --cameras FOLDER`): the views' cameras, from the headers
    from dibrgs_core.data.load import read_any_cameras

    for where in (out, out / "transforms.json"):  # the folder or the file
        cams = read_any_cameras(where)
        assert [c.name for c in cams] == list(ngp.views)
        for c in cams:
            np.testing.assert_array_equal(c.K, ngp.views[c.name].camera.K)
            np.testing.assert_array_equal(c.w2c, ngp.views[c.name].camera.w2c)


def test_opengl_axes_put_the_world_where_the_photo_shows_it(tmp_path):
    """A camera 10 units above the origin looking down (-z) with +y up in the image: a point at +x
    lands right of the centre, one at +y above it (OpenGL axes; a reader that kept them as OpenCV's
    would put both behind the camera)."""
    from PIL import Image

    (tmp_path / "s").mkdir()
    Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(tmp_path / "s" / "a.png")
    Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(tmp_path / "s" / "b.png")
    m = np.eye(4)
    m[2, 3] = 10.0
    m2 = m.copy()
    m2[0, 3] = 1.0
    (tmp_path / "s" / "transforms.json").write_text(json.dumps(
        {"camera_angle_x": 1.0, "frames": [{"file_path": "a.png", "transform_matrix": m.tolist()},
                                           {"file_path": "b.png", "transform_matrix": m2.tolist()}]}))
    cam = read_any_scene(tmp_path / "s").views["a"].camera
    assert cam.K[0, 0] == pytest.approx(30.0 / np.tan(0.5))  # from camera_angle_x and the photo's width
    for point, right, up in (([1.0, 0, 0], True, None), ([0, 1.0, 0], None, True)):
        x = cam.K @ (cam.w2c[:3, :3] @ point + cam.w2c[:3, 3])
        assert x[2] > 0  # in front of the camera
        u, v = x[:2] / x[2]
        if right is not None:
            assert u > cam.K[0, 2] + 1
        if up is not None:
            assert v < cam.K[1, 2] - 1


def test_blender_synthetic_layout_splits_by_its_part_files(tmp_path):
    """transforms_train.json / transforms_test.json, file paths without extension, like-named photos
    in the part folders: ids by path, the parts' split unless split.json or --train say otherwise."""
    from PIL import Image

    from dibrgs_core.camera.pinhole import look_at

    root = tmp_path / "lego"
    for part, n in (("train", 3), ("test", 2), ("val", 1)):
        (root / part).mkdir(parents=True)
        frames = []
        for i in range(n):
            Image.fromarray(np.full((32, 32, 4), 40 * i, np.uint8)).save(root / part / f"r_{i}.png")
            w2c = look_at([4.0 * np.cos(i + len(part)), 4.0 * np.sin(i + len(part)), 2.0], [0, 0, 0], [0, 0, 1])
            frames.append({"file_path": f"./{part}/r_{i}", "transform_matrix": opengl_c2w(w2c)})
        (root / f"transforms_{part}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    s = read_any_scene(root)
    assert sorted(s.views) == ["test_r_0", "test_r_1", "train_r_0", "train_r_1", "train_r_2", "val_r_0"]
    assert s.train == ["train_r_0", "train_r_1", "train_r_2"] and s.test == ["test_r_0", "test_r_1"]
    assert s.split_source == "transforms_train.json + transforms_test.json"
    assert read_any_scene(root, train_ids=["train_r_0", "val_r_0"]).train == ["train_r_0", "val_r_0"]
    (root / "split.json").write_text('{"train": ["train_r_1", "test_r_0"], "test": ["val_r_0"]}')
    s = read_any_scene(root)
    assert (s.train, s.test) == (["train_r_1", "test_r_0"], ["val_r_0"]) and "split.json" in s.split_source


def test_opencv_distortion_is_undistorted_as_colmaps(tmp_path, monkeypatch):
    """k1, k2, p1, p2 (and k3) of nerfstudio's OPENCV camera: the pinhole of COLMAP's undistorter,
    the photo resampled to it; OPENCV_FISHEYE refused naming the file."""
    from PIL import Image

    from dibrgs_core.camera.pinhole import look_at

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    root = tmp_path / "ns"
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(3):
        Image.fromarray(np.random.default_rng(i).integers(0, 256, (64, 96, 3), dtype=np.uint8)).save(
            root / "images" / f"f{i}.jpg")
        frames.append({"file_path": f"images/f{i}.jpg",
                       "transform_matrix": opengl_c2w(look_at([10.0 * i, 0, 80], [10.0 * i, 0, 0], [0, 1.0, 0]))})
    intr = {"fl_x": 80.0, "fl_y": 81.0, "cx": 47.0, "cy": 33.0, "w": 96, "h": 64, "k1": -0.2, "k2": 0.05,
            "p1": 0.001, "p2": -0.002, "camera_model": "OPENCV"}
    for k3, model, params in ((0.0, "OPENCV", [80.0, 81.0, 47.0, 33.0, -0.2, 0.05, 0.001, -0.002]),
                              (0.01, "FULL_OPENCV", [80.0, 81.0, 47.0, 33.0, -0.2, 0.05, 0.001, -0.002, 0.01, 0, 0, 0])):
        (root / "transforms.json").write_text(json.dumps({**intr, "k3": k3, "frames": frames}))
        s = read_any_scene(root)
        want = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(),
                                         pycolmap.Camera(model=model, width=96, height=64, params=params))
        for v in s.views.values():
            assert (v.camera.width, v.camera.height) == (want.width, want.height) != (96, 64)
            np.testing.assert_array_equal(v.camera.K, want.calibration_matrix())
            assert v.image.shape == (want.height, want.width, 3)
    (root / "transforms.json").write_text(json.dumps({**intr, "camera_model": "OPENCV_FISHEYE", "frames": frames}))
    with pytest.raises(InputError, match="transforms.json: camera_model OPENCV_FISHEYE is not supported"):
        read_any_scene(root)


def test_bad_transforms_files_are_one_clear_error(tmp_path):
    from PIL import Image

    root = tmp_path / "bad"
    root.mkdir()
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(root / "a.png")
    ok = {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}
    cases = {"{": "unreadable transforms file",
             json.dumps({"fl_x": 5.0}): 'expected an object with a "frames" list',
             json.dumps({"fl_x": 5.0, "frames": [{"file_path": "a.png"}]}): "frame 0: needs file_path and transform_matrix",
             json.dumps({"fl_x": 5.0, "frames": [{**ok, "file_path": "nowhere.png"}]}): "frame 0: photo nowhere.png not found",
             json.dumps({"fl_x": 5.0, "frames": [{**ok, "transform_matrix": [[1, 0], [0, 1]]}]}): "finite 4x4",
             json.dumps({"fl_x": "wide", "frames": [ok]}): "fl_x must be a finite number",
             json.dumps({"frames": [ok]}): "neither fl_x nor camera_angle_x",
             json.dumps({"fl_x": 5.0, "w": 9, "h": 8, "frames": [ok]}): "image is 8x8 but its camera entry says 9x8",
             json.dumps({"fl_x": 5.0, "frames": [{**ok, "k4": 0.01}]}): "k4 is a fisheye coefficient"}
    for text, msg in cases.items():
        (root / "transforms.json").write_text(text)
        with pytest.raises(InputError, match=msg):
            read_any_scene(root)


@pytest.mark.slow
def test_the_real_flight_through_scripts_colmap_to_transforms(tmp_path):
    """brighton_north written by scripts/colmap_to_transforms.py reads back with its COLMAP cameras
    and split; with nerfstudio's axes, the same cameras in a world turned about the origin."""
    import subprocess
    import sys

    from paths import shared_file

    repo = Path(__file__).resolve().parents[2]
    scene = shared_file("data/brighton_north")
    want = read_any_scene(scene, load_depth=False)
    for axes in ([], ["--nerfstudio-axes"]):
        out = tmp_path / ("ns" if axes else "plain")
        r = subprocess.run([sys.executable, str(repo / "scripts" / "colmap_to_transforms.py"), str(scene), str(out),
                            *axes], capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        got = read_any_scene(out, load_depth=False)
        assert (got.train, got.test) == (want.train, want.test) and "split.json" in got.split_source
        turn = np.eye(4) if not axes else np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
        for vid, v in got.views.items():
            w = want.views[vid].camera
            np.testing.assert_allclose(v.camera.K, w.K, rtol=1e-12)
            np.testing.assert_allclose(v.camera.w2c @ turn, w.w2c, atol=1e-9)  # world point X: turn @ X here
    r = subprocess.run([sys.executable, str(repo / "scripts" / "colmap_to_transforms.py"), str(scene), str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "exists" in r.stderr
