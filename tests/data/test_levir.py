"""LEVIR-NVS I/O: round trips, split protocol, camera lists and every bad-input case."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.camera.serialize import camera_to_dict
from dibrgs_core.cli import main as dibrgs
from dibrgs_core.common.errors import InputError
from dibrgs_core.data.scene import View
from dibrgs_core.data.split import default_split
from dibrgs_core.data.levir import read_cameras, read_cams_file, read_scene, write_cams_file, write_scene
from dibrgs_core.data.images import read_depth, write_depth_exr, write_depth_tiff

W, H = 24, 16  # non-square on purpose


def make_views(n: int = 21, seed: int = 0) -> tuple[dict[str, View], list[Camera]]:
    """A 21-view orbit scene (000 near nadir) with random images and depths."""
    rng = np.random.default_rng(seed)
    K = np.array([[30.0, 0, 12.5], [0, 31.0, 7.25], [0, 0, 1]])  # fx != fy, off-centre
    views = {}
    for i in range(n):
        if i == 0:
            eye = [1.0, 0.5, 300.0]
        else:
            a = 2 * np.pi * (i - 1) / (n - 1)
            eye = [150 * np.cos(a), 150 * np.sin(a), 210.0]
        cam = Camera(K=K, w2c=look_at(eye, [0, 0, 0], [0, 0, 1]), width=W, height=H, name=f"{i:03d}",
                     depth_range=(100.0 + i, 400.0 + i / 3))
        img = rng.integers(0, 256, (H, W, 3)).astype(np.float32) / 255.0
        depth = rng.uniform(150, 350, (H, W)).astype(np.float32)
        views[cam.name] = View(cam, img, depth)
    track = [Camera(K=K, w2c=look_at([100 * np.cos(a), 100 * np.sin(a), 200], [0, 0, 0], [0, 0, 1]),
                    width=W, height=H, name=f"{k:03d}", depth_range=(1.0, 2.0))
             for k, a in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False))]
    return views, track


@pytest.fixture()
def scene_dir(tmp_path) -> Path:
    views, track = make_views()
    return write_scene(tmp_path / "scene", views, track)


def test_round_trip_exact(scene_dir):
    views, track = make_views()
    s = read_scene(scene_dir)
    assert list(s.views) == sorted(views)
    assert list(s.sizes()) == [(W, H)]
    for k, v in views.items():
        r = s.views[k]
        assert np.array_equal(r.camera.w2c, v.camera.w2c)  # repr() floats: bit-exact float64
        assert np.array_equal(r.camera.K, v.camera.K)
        assert r.camera.depth_range == v.camera.depth_range
        assert (r.camera.width, r.camera.height) == (W, H)
        assert r.image.dtype == np.float32 and r.image.shape == (H, W, 3)
        assert np.abs(r.image - v.image).max() < 0.5 / 255 + 1e-7
        assert np.array_equal(r.depth, v.depth)
    assert [c.name for c in s.track] == [c.name for c in track]
    assert np.array_equal(s.track[3].w2c, track[3].w2c)
    assert (s.track[0].width, s.track[0].height) == (W, H)


def test_default_protocol_and_custom_split(scene_dir):
    s = read_scene(scene_dir, load_depth=False)
    assert s.train == ["001", "008", "015"]
    assert len(s.test) == 17 and "000" not in s.test and not set(s.test) & set(s.train)
    assert all(v.depth is None for v in s.views.values())
    assert [v.name for v in s.train_views()] == s.train
    s2 = read_scene(scene_dir, train_ids=["2", "010", "000"])
    assert s2.train == ["002", "010", "000"]
    assert len(s2.test) == 18 and "010" not in s2.test
    s3 = read_scene(scene_dir, train_ids=["001"], test_ids=["005", "006"])
    assert s3.test == ["005", "006"]
    with pytest.raises(InputError, match="099"):
        read_scene(scene_dir, train_ids=["099"])
    # Generic orbits without a nadir view: indices ceil(i*n/3).
    assert default_split([f"{i:03d}" for i in range(9)])[0] == ["000", "003", "006"]


def test_read_cams_file_and_size_inference(scene_dir, tmp_path):
    cam = read_cams_file(scene_dir / "Cams" / "004.txt")
    assert (cam.width, cam.height, cam.name) == (W, H, "004")  # from Images/004.png
    lone = tmp_path / "lone" / "x.txt"
    lone.parent.mkdir()
    shutil.copy(scene_dir / "Cams" / "004.txt", lone)
    c2 = read_cams_file(lone)  # no image: 2*cx x 2*cy
    assert (c2.width, c2.height) == (25, 15)
    assert read_cams_file(lone, size=(7, 9)).width == 7


def test_read_cameras_file_folder_json(scene_dir, tmp_path):
    assert len(read_cameras(scene_dir / "Track")) == 6
    assert len(read_cameras(scene_dir)) == 21  # scene folder -> Cams/
    one = read_cameras(scene_dir / "Cams" / "003.txt")
    assert len(one) == 1 and one[0].name == "003"
    js = tmp_path / "cams.json"
    cams = read_cameras(scene_dir / "Track")
    js.write_text(json.dumps([camera_to_dict(c) for c in cams]))
    back = read_cameras(js)
    assert [c.name for c in back] == [c.name for c in cams]
    assert np.array_equal(back[2].w2c, cams[2].w2c)
    js.write_text(json.dumps({"cameras": [camera_to_dict(cams[0])]}))
    assert len(read_cameras(js)) == 1


@pytest.mark.parametrize("content,match", [
    ("{not json", "cannot read JSON"),
    ("[]", "non-empty"),
    ('[{"name": "a"}]', "entry 0"),
    ('[{"name":"a","width":4,"height":4,"K":[[1,0,2],[0,1,2],[0,0,1]],"w2c":[[1,0,0,0],[0,1,0,0],[0,0,0,0],[0,0,0,1]]}]',
     "singular"),
])
def test_read_cameras_bad_json(tmp_path, content, match):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(InputError, match=match) as e:
        read_cameras(p)
    assert e.value.path == p


def test_depth_tiff_exr_round_trip(tmp_path):
    d = np.random.default_rng(0).uniform(0, 500, (5, 7)).astype(np.float32)
    d[0, 0] = 0.0
    write_depth_tiff(tmp_path / "d.tiff", d)
    write_depth_exr(tmp_path / "d.exr", d)
    assert np.array_equal(read_depth(tmp_path / "d.tiff"), d)
    assert np.array_equal(read_depth(tmp_path / "d.exr"), d)
    d[1, 1] = np.nan
    write_depth_tiff(tmp_path / "n.tiff", d)
    r = read_depth(tmp_path / "n.tiff")
    assert r[1, 1] == 0 and np.isfinite(r).all()
    assert not list(tmp_path.glob(".*"))  # atomic writes leave no temporaries


# -- bad input: each raises InputError naming the offending file ----------------------
def _expect(root: Path, culprit: Path, match: str, **kw) -> None:
    with pytest.raises(InputError, match=match) as e:
        read_scene(root, **kw)
    assert e.value.path == culprit, f"error names {e.value.path}, expected {culprit}"
    assert str(culprit) in str(e.value)


def test_missing_folder_and_subfolders(tmp_path, scene_dir):
    _expect(tmp_path / "nope", tmp_path / "nope", "not found")
    shutil.rmtree(scene_dir / "Cams")
    _expect(scene_dir, scene_dir / "Cams", "missing folder")


def test_missing_files(scene_dir):
    (scene_dir / "Cams" / "005.txt").unlink()
    _expect(scene_dir, scene_dir / "Cams" / "005.txt", "camera file missing")


def test_missing_image(scene_dir):
    (scene_dir / "Images" / "006.png").unlink()
    _expect(scene_dir, scene_dir / "Images" / "006.png", "image missing")


def test_missing_depth(scene_dir):
    (scene_dir / "Depths" / "007.tiff").unlink()
    _expect(scene_dir, scene_dir / "Depths" / "007.tiff", "depth map missing")
    assert read_scene(scene_dir, load_depth=False).views["007"].depth is None


def test_truncated_image(scene_dir):
    p = scene_dir / "Images" / "003.png"
    p.write_bytes(p.read_bytes()[:60])
    _expect(scene_dir, p, "truncated")


def test_unreadable_image(scene_dir):
    p = scene_dir / "Images" / "003.png"
    p.write_bytes(b"this is not a png at all" * 10)
    _expect(scene_dir, p, "unreadable")


def test_images_of_different_sizes_are_each_read_at_their_own(scene_dir):
    """A photo of another size (here turned to portrait, with its camera) is read at its size; a photo
    resized by mistake (its camera's principal point off its middle) is an error naming the photo."""
    from PIL import Image

    from dibrgs_core.commands.info import summarize

    c = read_cams_file(scene_dir / "Cams" / "009.txt")
    K = np.array([[c.K[1, 1], 0, c.K[1, 2]], [0, c.K[0, 0], W - c.K[0, 2]], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3] = np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]]) @ c.w2c[:3]
    write_cams_file(scene_dir / "Cams" / "009.txt", Camera(K=K, w2c=w2c, width=H, height=W, name="009"))
    upright = np.random.default_rng(0).integers(0, 255, (W, H, 3), dtype=np.uint8)
    Image.fromarray(upright).save(scene_dir / "Images" / "009.png")
    depth = scene_dir / "Depths" / "009.tiff"
    write_depth_tiff(depth, np.ascontiguousarray(np.rot90(read_depth(depth))))
    scene = read_scene(scene_dir)
    assert scene.views["009"].image.shape == (W, H, 3) and np.array_equal(scene.views["009"].image * 255, upright)
    assert (scene.views["009"].camera.width, scene.views["009"].camera.height) == (H, W)
    assert scene.sizes() == {(W, H): [k for k in scene.views if k != "009"], (H, W): ["009"]}
    info = summarize(scene)
    assert info["resolution"] == [W, H] and info["sizes"][f"{H}x{W}"] == ["009"]
    p = scene_dir / "Images" / "010.png"
    Image.fromarray(np.zeros((H // 2, W // 2, 3), np.uint8)).save(p)
    _expect(scene_dir, p, f"image is {W // 2}x{H // 2} but its camera's principal point .* lies off its middle")


@pytest.mark.parametrize("edit,match", [
    (lambda t: t.replace("intrinsic", "intrinsic 1.0"), "found 12 values"),
    (lambda t: t.rsplit("\n", 2)[0] + "\n", "found 9 values"),
    (lambda t: t.replace("extrinsic\n", "extrinsic\n0.0 "), "16 values"),
    (lambda t: t.replace("intrinsic", "intrinsics_missing"), "'extrinsic' and 'intrinsic'"),
    (lambda t: t.replace("1.0\n\nintrinsic", "nan\n\nintrinsic"), "NaN"),
    (lambda t: t.replace("1.0\n\nintrinsic", "abc\n\nintrinsic"), "unexpected token"),
])
def test_bad_cams_file(scene_dir, edit, match):
    p = scene_dir / "Cams" / "012.txt"
    p.write_text(edit(p.read_text()))
    _expect(scene_dir, p, match)


def test_singular_matrices(scene_dir):
    p = scene_dir / "Cams" / "013.txt"
    cam = read_cams_file(p)
    bad = Camera(K=cam.K, w2c=cam.w2c.copy(), width=W, height=H, name="013", depth_range=cam.depth_range)
    bad.w2c[:3, :3] = 0.0
    write_cams_file(p, bad)
    _expect(scene_dir, p, "singular")
    bad.w2c = cam.w2c.copy()
    bad.w2c[:3, :3] *= 2.0  # invertible but not a rotation
    write_cams_file(p, bad)
    _expect(scene_dir, p, "not a rotation")
    bad.w2c = cam.w2c
    bad.K = np.zeros((3, 3))
    write_cams_file(p, bad)
    _expect(scene_dir, p, "intrinsic matrix is singular")


def test_depth_size_mismatch(scene_dir):
    p = scene_dir / "Depths" / "011.tiff"
    write_depth_tiff(p, np.ones((H + 1, W), np.float32))
    _expect(scene_dir, p, f"depth map is {W}x{H + 1} but its image 011.png is {W}x{H}")


def test_corrupt_depth(scene_dir):
    p = scene_dir / "Depths" / "011.tiff"
    p.write_bytes(b"II*\x00garbage")
    _expect(scene_dir, p, "unreadable depth")


# -- dibrgs info --------------------------------------------------------------
def test_info_command(scene_dir, capsys):
    assert dibrgs(["info", str(scene_dir)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["views"] == 21 and out["resolution"] == [W, H] and out["layout"] == "levir"
    assert out["train"] == ["001", "008", "015"] and len(out["test"]) == 17
    assert out["track_cameras"] == 6
    assert np.allclose(out["up"], [0, 0, 1], atol=0.01) and out["up_confidence"] > 0.5
    assert out["trajectory"]["kind"] == "orbit" and out["orbit"]["radius"] == pytest.approx(150.0, abs=1e-3)
    assert out["orbit"]["tilt_deg"] < 0.5 and out["orbit"]["views"] == 20
    assert 30 < out["nadir_angle_deg"] < 36
    lo, hi = out["depth_range_maps"]
    assert 150 <= lo < hi <= 350
    assert dibrgs(["info", str(scene_dir), "--train", "2,3,4"]) == 0
    assert json.loads(capsys.readouterr().out)["train"] == ["002", "003", "004"]


def test_info_bad_input_exit_2(scene_dir, capsys):
    p = scene_dir / "Cams" / "002.txt"
    p.write_text("extrinsic 1 2 3")
    assert dibrgs(["info", str(scene_dir)]) == 2
    err = capsys.readouterr().err
    assert str(p) in err and "error" in err
    assert dibrgs(["info", str(scene_dir / "missing")]) == 2
