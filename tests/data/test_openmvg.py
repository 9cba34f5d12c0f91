"""Scenes as OpenMVG leaves them (an sfm_data.json + photos): the cameras the LEVIR reader gives
for the same views, cereal's polymorphic intrinsics (the type named once), OpenMVG's Brown lens as
the pinhole and distortion COLMAP undistorts, views without a pose, several reconstructions,
photos moved from where OpenMVG read them, clear errors."""
from __future__ import annotations

import json
import os

import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.frame_layouts import layout_frames
from dibrgs_core.data.load import read_any_cameras, read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import assert_projects_as_brown, levir_as_openmvg, reads_as_levir  # noqa: E402


def test_an_openmvg_output_folder_reads_the_cameras_of_the_same_views(tiny_scene, tmp_path, caplog):
    """An output folder (matches/sfm_data.json without poses, reconstruction_sequential/sfm_data.json
    with them; photos named by root_path outside it): the LEVIR scene's views, cameras and split,
    also from a second intrinsic that cereal gives by id only."""
    out = tmp_path / "omvg"
    sfm = levir_as_openmvg(tiny_scene, out, photos=tmp_path / "shoot")
    with caplog.at_level("INFO", logger="dibrgs"):
        assert reads_as_levir(out, tiny_scene, [sfm]).layout == "openmvg"
    assert "read openmvg layout" in caplog.text
    with pytest.raises(InputError, match="no reconstructed views"):  # the image listing: no poses
        read_any_cameras(out / "matches" / "sfm_data.json")


def test_brown_lenses_project_as_openmvg_says(tiny_scene, tmp_path, monkeypatch):
    """A point seen through the camera the reader makes of a pinhole_brown_t2 intrinsic lands where
    OpenMVG's distoFunction puts it: x' = x d_r + t2 (r^2 + 2 x^2) + 2 t1 x y,
    y' = y d_r + t1 (r^2 + 2 y^2) + 2 t2 x y, in pixels f x' + the principal point; the photos read
    at the undistorted camera's size."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    k1, k2, k3, t1, t2 = -0.12, 0.03, -0.004, 0.0015, -0.002
    out = tmp_path / "omvg"
    levir_as_openmvg(tiny_scene, out, camera="pinhole_brown_t2", disto=(k1, k2, k3, t1, t2))
    frame = layout_frames(out)[0]
    f, cx, cy = frame.intrinsics["fl_x"], frame.intrinsics["cx"], frame.intrinsics["cy"]
    assert_projects_as_brown(frame, (k1, k2, k3, t1, t2), (f, f), (cx, cy))
    view = read_any_scene(out).views["000"]
    assert view.image.shape[:2] == (view.camera.height, view.camera.width)


def test_unposed_views_moved_photos_and_the_newest_reconstruction(tiny_scene, tmp_path, caplog):
    """Views without a pose are left out and counted; photos whose root_path is gone (a Windows
    path) are found by name in images/ beside the output folder; of two reconstructions the newest
    is read and named."""
    out = tmp_path / "omvg"
    sfm = levir_as_openmvg(tiny_scene, out, unposed=3)
    data = json.loads(sfm.read_text())
    data["root_path"] = "D:\\flights\\park\\images"
    sfm.write_text(json.dumps(data))
    older = out / "reconstruction_global" / "sfm_data.json"
    older.parent.mkdir()
    older.write_text(json.dumps({**data, "extrinsics": data["extrinsics"][:5]}))
    os.utime(older, (1e9, 1e9))
    with caplog.at_level("INFO", logger="dibrgs"):
        scene = read_any_scene(out)
    assert len(scene.views) == 18 and "018" not in scene.views
    assert "3 views without a pose (not reconstructed) left out: 018.png, 019.png, 020.png" in caplog.text
    assert "2 reconstructions, reading the newest (reconstruction_sequential/sfm_data.json)" in caplog.text
    assert len(read_any_cameras(older.parent)) == 5


@pytest.mark.parametrize("case", ["fisheye", "binary", "rotation", "flat", "disto", "photo", "broken", "focal",
                                  "views"])
def test_sfm_data_files_we_cannot_read_are_named(tiny_scene, tmp_path, case):
    out = tmp_path / "omvg"
    sfm = levir_as_openmvg(tiny_scene, out, camera="fisheye" if case == "fisheye" else "pinhole_radial_k3",
                           disto=(0.0, 0.0, 0.0, 0.0) if case == "fisheye" else (0.0, 0.0, 0.0))
    data = json.loads(sfm.read_text())
    expect = {"fisheye": "view 000.png: camera model fisheye is not supported",
              "binary": "OpenMVG's binary format: convert it with openMVG_main_ConvertSfM_DataFormat",
              "rotation": "extrinsic 2: rotation is not a rotation matrix",
              "flat": "extrinsic 3: rotation (three rows of three) must be 9 finite numbers",
              "disto": "intrinsic 0: disto_k3 must be 3 finite numbers",
              "photo": "view 004.png: photo 004.png not found", "broken": "unreadable SfM_Data file",
              "focal": "view 000.png: intrinsic 0: focal length must be positive",
              "views": "views: expected a list of {\"key\", \"value\"} objects"}[case]
    if case == "binary":
        sfm.unlink()
        (sfm.parent / "sfm_data.bin").write_bytes(b"\0" * 64)
    elif case == "rotation":
        data["extrinsics"][2]["value"]["rotation"][0][0] = 2.0
    elif case == "flat":
        data["extrinsics"][3]["value"]["rotation"] = [1.0] * 9
    elif case == "disto":
        data["intrinsics"][0]["value"]["ptr_wrapper"]["data"]["disto_k3"] = [0.0, 0.0]
    elif case == "photo":
        (out / "images" / "004.png").unlink()
    elif case == "focal":
        data["intrinsics"][0]["value"]["ptr_wrapper"]["data"]["focal_length"] = -1.0
    elif case == "views":
        data["views"] = {"0": "x"}
    if case in ("rotation", "flat", "disto", "focal", "views"):
        sfm.write_text(json.dumps(data))
    if case == "broken":
        sfm.write_text(sfm.read_text()[:200])
    with pytest.raises(InputError) as e:
        read_any_scene(out)
    assert expect in str(e.value)
    if case == "binary":  # the add-on's reader says it alike
        from dibrgs_core.bridge.describe import describe_scene

        with pytest.raises(InputError, match="convert it with openMVG_main_ConvertSfM_DataFormat -i sfm_data.bin"):
            describe_scene(out)
