"""Scenes in Bundler's format (bundle.out + list.txt, as Bundler writes and Metashape, RealityCapture
and OpenSfM export): the cameras the LEVIR reader gives for the same views (OpenGL camera axes turned
into OpenCV's), Bundler's radial lens as COLMAP undistorts it, unregistered cameras left out, clear
errors."""
from __future__ import annotations

import numpy as np
import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.load import read_any_cameras, read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import assert_same_views, levir_as_bundler  # noqa: E402


def test_bundle_out_reads_the_cameras_of_the_same_views(tiny_scene, tmp_path, caplog):
    out = tmp_path / "bundler"
    levir_as_bundler(tiny_scene, out, unregistered=2)
    levir = read_any_scene(tiny_scene, load_depth=False)
    with caplog.at_level("INFO", logger="dibrgs"):
        scene = read_any_scene(out)
    assert_same_views(scene, levir)
    assert "2 cameras not registered (f = 0) left out: images/lost0.png, images/lost1.png" in caplog.text
    for where in (out, out / "bundle.out"):  # `dibrgs render --cameras`: the folder or the file
        cams = read_any_cameras(where)
        assert [c.name for c in cams] == list(scene.views)
        np.testing.assert_array_equal(cams[7].w2c, scene.views[cams[7].name].camera.w2c)
    # in bundle/, the list naming photos by a path that no longer holds: found by name in images/
    (out / "bundle").mkdir()
    (out / "bundle.out").rename(out / "bundle" / "bundle.out")
    (out / "bundle" / "list.txt").write_text((out / "list.txt").read_text().replace("images/", "C:/flight/"))
    (out / "list.txt").unlink()
    assert_same_views(read_any_scene(out), levir)


def test_bundler_lens_projects_as_its_manual_says(tiny_scene, tmp_path, monkeypatch):
    """p' = f r(p) p about the image centre with y up, p = -P / P.z, r = 1 + k1 |p|^2 + k2 |p|^4: a
    point in front of the camera (P.z < 0) lands at (w / 2 + p'x, h / 2 - p'y) in pixels."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "bundler"
    k1, k2 = -0.12, 0.03
    levir_as_bundler(tiny_scene, out, k=(k1, k2))
    scene = read_any_scene(out)
    from dibrgs_core.data.frame_layouts import layout_frames

    frame = next(f for f in layout_frames(out) if f.name == "002.png")
    model, params = frame.camera_model(64, 64)
    cam = pycolmap.Camera(model=model, width=64, height=64, params=params)
    f = frame.intrinsics["fl_x"]
    flip = np.diag([1.0, -1.0, -1.0])
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-2, 2, (40, 2)), -rng.uniform(5, 9, 40)])  # Bundler camera coordinates
    p = -P[:, :2] / P[:, 2:]
    n2 = (p * p).sum(1, keepdims=True)
    pp = f * (1 + k1 * n2 + k2 * n2 * n2) * p
    want = np.column_stack([32 + pp[:, 0], 32 - pp[:, 1]])
    np.testing.assert_allclose(cam.img_from_cam(P @ flip.T), want, atol=1e-9)
    assert scene.views["002"].image.shape[:2] == (scene.views["002"].camera.height, scene.views["002"].camera.width)


@pytest.mark.parametrize("case", ["list", "count", "photo", "short", "none", "two"])
def test_bundler_files_we_cannot_read_are_named(tiny_scene, tmp_path, case):
    out = tmp_path / "bundler"
    levir_as_bundler(tiny_scene, out)
    text = (out / "bundle.out").read_text()
    expect = {"list": "no image list beside it", "count": "20 photos listed for 21 cameras",
              "photo": "camera 4: photo 004.png not found", "short": "21 cameras announced, 20 given",
              "none": "no registered cameras", "two": "several Bundler files (a.out, bundle.out)"}[case]
    if case == "list":
        (out / "list.txt").unlink()
    elif case == "count":
        (out / "list.txt").write_text("\n".join((out / "list.txt").read_text().splitlines()[:20]))
    elif case == "photo":
        (out / "images" / "004.png").unlink()
    elif case == "short":
        (out / "bundle.out").write_text("\n".join(text.splitlines()[:-5]))
    elif case == "none":
        lines = text.splitlines()
        for j in range(21):
            lines[2 + 5 * j] = "0 0 0"
        (out / "bundle.out").write_text("\n".join(lines))
    elif case == "two":
        (out / "a.out").write_text(text)
    with pytest.raises(InputError) as e:
        read_any_scene(out)
    assert expect in str(e.value)


def test_of_a_folder_holding_sidecars_and_a_bundle_file_the_sidecars_are_read(tiny_scene, tmp_path, caplog):
    """RealityCapture can export both: its XMP sidecars carry the principal point and tangential
    terms that Bundler's format lacks, so they are read."""
    from photo_synth import levir_as_realitycapture

    out = tmp_path / "both"
    levir_as_bundler(tiny_scene, out)
    levir_as_realitycapture(tiny_scene, out)  # sidecars beside the same photos in images/
    with caplog.at_level("INFO", logger="dibrgs"):
        read_any_scene(out)
    assert "read realitycapture layout" in caplog.text
