"""Scenes as Meshroom leaves them (an AliceVision SfMData cameras.sfm + photos): the cameras the
LEVIR reader gives for the same views in every file version, AliceVision's lens conventions (focal
length and principal point across versions, Brown distortion) as the pinhole and distortion COLMAP
undistorts, rigs, views without a pose, photos moved from where Meshroom read them, clear errors."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.frame_layouts import layout_frames
from dibrgs_core.data.load import read_any_cameras, read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import assert_projects_as_brown, levir_as_meshroom, reads_as_levir, sfm_intrinsic, sfm_pose  # noqa: E402

VERSIONS = [(1, 0, 0), (1, 2, 0), (1, 2, 1), (1, 2, 4), (1, 2, 10), (1, 2, 11)]


@pytest.mark.parametrize("version", VERSIONS, ids=lambda v: ".".join(map(str, v)))
def test_a_meshroom_project_reads_the_cameras_of_the_same_views(tiny_scene, tmp_path, caplog, version):
    """A project folder (MeshroomCache/StructureFromMotion/<id>/cameras.sfm, photos named by
    absolute path outside it) in each file version: the LEVIR scene's views, cameras and split."""
    out = tmp_path / "project"
    sfm = levir_as_meshroom(tiny_scene, out, version=version, photos=tmp_path / "shoot" / "DCIM")
    with caplog.at_level("INFO", logger="dibrgs"):
        assert reads_as_levir(out, tiny_scene, [sfm]).layout == "meshroom"
    assert "read meshroom layout" in caplog.text


@pytest.mark.parametrize("version,stored", [
    ((1, 2, 0), {"type": "radial3", "pxFocalLength": ["1000", "2000"], "principalPoint": ["2020", "1040"]}),
    ((1, 2, 1), {"type": "radial3", "pxFocalLength": ["1000", "2000"], "principalPoint": ["-26", "16"]}),
    ((1, 2, 4), {"type": "radial3", "focalLength": "8.7976539589442808", "pixelRatio": "0.5",
                 "principalPoint": ["-26", "16"]}),
    ((1, 2, 5), {"type": "radial3", "focalLength": "8.7976539589442808", "pixelRatio": "2",
                 "principalPoint": ["-26", "16"]}),
    ((1, 2, 8), {"type": "pinhole", "distortionType": "radialk3", "undistortionType": "none",
                 "focalLength": "8.7976539589442808", "pixelRatio": "2", "principalPoint": ["-26", "16"]}),
    ((1, 2, 11), {"type": "pinhole", "distortionType": "radialk3", "undistortionType": "none",
                  "focalLength": "17.595307917888562", "pixelRatio": "2", "principalPoint": ["-26", "16"]}),
], ids=lambda v: ".".join(map(str, v)) if isinstance(v, tuple) else "")
def test_every_file_version_gives_the_same_lens(tmp_path, version, stored):
    """One lens as AliceVision's compatibility scenes store it in each file version (fx 1000, fy 2000,
    principal point (2020, 1040) on a 4092x2048 image, radial k1 0.1, k2 0.05, k3 -0.001; the
    focal length's and pixelRatio's meaning changed at 1.2.2, 1.2.5 and 1.2.11, the principal
    point's origin at 1.2.1): the same COLMAP camera from each."""
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "a.jpg").write_bytes(b"")
    intr = {"intrinsicId": "0", "width": "4092", "height": "2048", "sensorWidth": "36",
            "distortionParams": ["0.10000000000000001", "0.050000000000000003", "-0.001"], **stored}
    data = {"version": [str(v) for v in version], "intrinsics": [intr],
            "views": [{"viewId": "1", "poseId": "1", "intrinsicId": "0", "path": "/elsewhere/a.jpg"}],
            "poses": [{"poseId": "1", "pose": {"transform": sfm_pose(np.eye(4))}}]}
    (tmp_path / "cameras.sfm").write_text(json.dumps(data))
    frame = layout_frames(tmp_path)[0]
    model, params = frame.camera_model(4092, 2048)
    assert model == "FULL_OPENCV"
    np.testing.assert_allclose(params[:9], [1000, 2000, 2020, 1040, 0.1, 0.05, 0, 0, -0.001], rtol=1e-12)


def test_brown_lenses_project_as_alicevision_says(tiny_scene, tmp_path, monkeypatch):
    """A point seen through the camera the reader makes of a Brown intrinsic lands where
    AliceVision's DistortionBrown puts it: x' = x d_r + t2 (r^2 + 2 x^2) + 2 t1 x y,
    y' = y d_r + t1 (r^2 + 2 y^2) + 2 t2 x y, in pixels f x' + w / 2 + the principal point's offset;
    the file's photos read at that camera's undistorted size."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    k1, k2, k3, t1, t2 = -0.12, 0.03, -0.004, 0.0015, -0.002
    intr = sfm_intrinsic((1, 2, 11), 64, 64, 70.0, 71.0, 33.5, 30.25, "brown", (k1, k2, k3, t1, t2))
    out = tmp_path / "mr"
    levir_as_meshroom(tiny_scene, out, intrinsic=intr)
    assert_projects_as_brown(layout_frames(out)[0], (k1, k2, k3, t1, t2), (70.0, 71.0), (33.5, 30.25))
    view = read_any_scene(out).views["000"]
    assert view.image.shape[:2] == (view.camera.height, view.camera.width)


def test_rig_views_unposed_views_and_moved_photos(tiny_scene, tmp_path, caplog):
    """A view of a rig (not pose-independent) is its sub-pose after the rig's pose; a sub-pose not
    yet estimated and views without a pose are left out and counted (an intrinsic only they use
    may never have been estimated: focal length -1); photos whose written paths are gone (a Windows
    path) are found by name in images/ beside the project, also in a subfolder."""
    out = tmp_path / "mr"
    sfm = levir_as_meshroom(tiny_scene, out, unposed=2)
    levir = read_any_scene(tiny_scene, load_depth=False)
    data = json.loads(sfm.read_text())
    views = {os.path.basename(v["path"])[:-4]: v for v in data["views"]}
    poses = {p["poseId"]: p for p in data["poses"]}
    a, b, c = (levir.views[k].camera.w2c for k in ("003", "004", "005"))
    del poses[views["004"]["poseId"]]  # a rig's views share the rig's pose
    views["004"].update(rigId="0", subPoseId="1", isPoseIndependant="false", poseId=views["003"]["poseId"])
    views["005"].update(rigId="0", subPoseId="0", isPoseIndependant="false", poseId=views["003"]["poseId"])
    data["rigs"] = [{"rigId": "0", "subPoses": [{"status": "uninitialized", "pose": sfm_pose(np.eye(4))},
                                                {"status": "estimated", "pose": sfm_pose(b @ np.linalg.inv(a))}]}]
    data["poses"] = list(poses.values())
    data["intrinsics"].append({**data["intrinsics"][0], "intrinsicId": "8", "focalLength": "-1"})
    views["019"]["intrinsicId"] = "8"
    for v in data["views"]:
        v["path"] = "C:\\Users\\pilot\\Flight 3\\" + os.path.basename(v["path"])
    sfm.write_text(json.dumps(data))
    (out / "images" / "sub").mkdir()
    (out / "images" / "006.png").rename(out / "images" / "sub" / "006.png")
    with caplog.at_level("INFO", logger="dibrgs"):
        scene = read_any_scene(out)
    assert "3 views without a pose (not reconstructed) left out: 005.png, 019.png, 020.png" in caplog.text
    assert "005" not in scene.views and len(scene.views) == 18
    np.testing.assert_allclose(scene.views["004"].camera.w2c, b, atol=1e-9)
    np.testing.assert_array_equal(scene.views["006"].image, levir.views["006"].image)


@pytest.mark.parametrize("case", ["fisheye", "equidistant", "3de", "params", "version", "broken", "photo",
                                  "unposed", "several", "focal", "rotation"])
def test_sfm_files_we_cannot_read_are_named(tiny_scene, tmp_path, case):
    out = tmp_path / "mr"
    sfm = levir_as_meshroom(tiny_scene, out, version=(1, 2, 4) if case == "fisheye" else (1, 2, 11))
    data = json.loads(sfm.read_text())
    intr = data["intrinsics"][0]
    expect = {"fisheye": "view 000.png: distortion fisheye is not supported",
              "equidistant": "view 000.png: camera type equidistant (a fisheye lens) is not supported",
              "3de": "view 000.png: undistortion model 3deradial4 is not supported",
              "params": "intrinsic 7: distortion brown takes 5 distortionParams, got 3",
              "version": "version must be three numbers", "broken": "unreadable SfMData file",
              "photo": "view 004.png: photo 004.png not found",
              "unposed": "no reconstructed views (no view has a pose)",
              "several": "several Meshroom SfMData files (a.sfm, b.sfm)",
              "focal": "view 000.png: intrinsic 7: focal length must be positive",
              "rotation": "pose 5003: rotation is not a rotation matrix"}[case]
    if case == "fisheye":
        intr["type"] = "fisheye4"
    elif case == "equidistant":
        intr["type"] = "equidistant"
    elif case == "3de":
        intr["undistortionType"] = "3deradial4"
    elif case == "params":
        intr.update(distortionType="brown", distortionParams=["0", "0", "0"])
    elif case == "version":
        data["version"] = ["1", "2"]
    elif case == "photo":
        (out / "images" / "004.png").unlink()
    elif case == "unposed":
        data["poses"] = []
    elif case == "focal":
        intr["focalLength"] = "-1"
    elif case == "rotation":
        data["poses"][3]["pose"]["transform"]["rotation"][0] = "2.0"
    sfm.write_text(json.dumps(data))
    if case == "broken":
        sfm.write_text(sfm.read_text()[:100])
    if case == "several":
        (out / "a.sfm").write_text(sfm.read_text())
        (out / "b.sfm").write_text(sfm.read_text())
    with pytest.raises(InputError) as e:
        read_any_scene(out)
    assert expect in str(e.value)


def test_the_newest_of_several_results_is_read_and_named(tiny_scene, tmp_path, caplog):
    """Two StructureFromMotion results in a project: the newest is read and the log says so; a
    folder holding cameras.sfm itself (the node's own folder) reads it, and so does a folder holding
    ConvertSfMFormat's sfm.json beside other JSON files."""
    out = tmp_path / "mr"
    sfm = levir_as_meshroom(tiny_scene, out)
    old = sfm.parent.parent / "0a1b2c" / "cameras.sfm"
    old.parent.mkdir()
    data = json.loads(sfm.read_text())
    data["poses"] = data["poses"][:4]
    old.write_text(json.dumps(data))
    os.utime(old, (1e9, 1e9))
    with caplog.at_level("INFO", logger="dibrgs"):
        assert len(read_any_scene(out).views) == 21
    assert "2 StructureFromMotion results, reading the newest (MeshroomCache/StructureFromMotion/2f9c0e1d7a" \
        in caplog.text
    assert len(read_any_cameras(old.parent)) == 4
    convert = out / "MeshroomCache" / "ConvertSfMFormat" / "77ab"
    convert.mkdir(parents=True)
    (convert / "sfm.json").write_text(json.dumps(data))
    (convert / "notes.json").write_text(json.dumps({"views": "not this one"}))
    assert len(read_any_cameras(convert)) == 4
