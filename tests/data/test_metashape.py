"""Scenes as Agisoft Metashape exports them (cameras XML + photos): the cameras the LEVIR reader
gives for the same views through a chunk's and a component's transforms, Metashape's lens model
(f, cx, cy from the centre, b1, its p1 / p2 order) as the pinhole and distortion COLMAP undistorts,
clear errors."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.load import read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import assert_same_views, levir_as_metashape, reads_as_levir  # noqa: E402


def _similarity(scale: float, euler_deg, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = scale * Rotation.from_euler("xyz", euler_deg, degrees=True).as_matrix()
    T[:3, 3] = t
    return T


def test_metashape_xml_reads_the_cameras_of_the_same_views(tiny_scene, tmp_path, caplog):
    """Cameras stored in a chunk's frame (a scaled, turned, shifted one, as a georeferenced project
    has), inside a component and a camera group, two cameras not aligned and one disabled: the world
    cameras of the LEVIR files, the split of the LEVIR default (no split.json), the photos' pixels."""
    out = tmp_path / "ms"
    levir_as_metashape(tiny_scene, out, chunk=_similarity(2.5, [10, -30, 70], [100.0, -40.0, 7.0]),
                       component=_similarity(0.5, [0, 0, 20], [1.0, 2.0, 3.0]), unaligned=2)
    levir = read_any_scene(tiny_scene, load_depth=False)
    with caplog.at_level("INFO", logger="dibrgs"):
        reads_as_levir(out, tiny_scene, [out / "cameras.xml"])
    assert "2 cameras without a transform (not aligned) left out: dropped0, dropped1" in caplog.text
    assert "1 cameras disabled in Metashape left out: unchecked" in caplog.text
    # any name: the folder's only Metashape XML; photos in the card's folders (labels carry no folder)
    (out / "cameras.xml").rename(out / "flight 3 export.xml")
    (out / "images" / "101MEDIA").mkdir()
    for p in sorted((out / "images").glob("01*.png")):
        p.rename(out / "images" / "101MEDIA" / p.name)
    assert_same_views(read_any_scene(out), levir)


def test_metashape_lens_model_projects_as_its_manual_says(tiny_scene, tmp_path, monkeypatch):
    """A point seen through the camera the reader makes of a Metashape calibration lands where the
    frame camera model of Metashape's manual puts it (u = w/2 + cx + x'(f + b1) + y' b2,
    v = h/2 + cy + y' f, with P1 on r^2 + 2x^2 in x' and P2 on 2xy); the photo is undistorted."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    cal = {"f": 70.0, "cx": 1.5, "cy": -2.0, "b1": 0.8, "b2": 0.2, "k1": -0.12, "k2": 0.03, "k3": 0.004,
           "p1": 0.002, "p2": -0.003}
    out = tmp_path / "ms"
    levir_as_metashape(tiny_scene, out, calibration=cal)
    from dibrgs_core.data.frame_layouts import layout_frames

    frame = layout_frames(out)[0]
    model, params = frame.camera_model(*frame.size)
    cam = pycolmap.Camera(model=model, width=frame.size[0], height=frame.size[1], params=params)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.4, 0.4, (50, 2))
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + cal["k1"] * r2 + cal["k2"] * r2**2 + cal["k3"] * r2**3
    xd = x * radial + cal["p1"] * (r2 + 2 * x * x) + 2 * cal["p2"] * x * y
    yd = y * radial + cal["p2"] * (r2 + 2 * y * y) + 2 * cal["p1"] * x * y
    w, h = frame.size
    u = 0.5 * w + cal["cx"] + xd * (cal["f"] + cal["b1"]) + yd * cal["b2"]
    v = 0.5 * h + cal["cy"] + yd * cal["f"]
    got = cam.img_from_cam(np.column_stack([xy, np.ones(len(xy))]))
    # b2 is dropped (it moves the image's edge by 0.2 x 32 / 70 = 0.09 px), everything else is exact
    np.testing.assert_allclose(got, np.column_stack([u - yd * cal["b2"], v]), atol=1e-9)
    assert np.abs(yd * cal["b2"]).max() < 0.1
    view, photo = read_any_scene(out).views["000"], read_any_scene(tiny_scene, load_depth=False).views["000"]
    assert view.image.shape[:2] == (view.camera.height, view.camera.width)
    assert np.abs(view.image - photo.image).mean() > 0.01  # undistorted


@pytest.mark.parametrize("case", ["k4", "skew", "fisheye", "uncalibrated", "photo", "same-name", "broken", "two",
                                  "none"])
def test_metashape_files_we_cannot_read_are_named(tiny_scene, tmp_path, case):
    out = tmp_path / "ms"
    levir_as_metashape(tiny_scene, out, calibration={"k4": 0.01} if case == "k4" else
                       {"b2": 2.0} if case == "skew" else None, unaligned=0)
    xml = out / "cameras.xml"
    text = xml.read_text()
    expect = {"k4": "k4 has no equivalent", "skew": "skew b2 = 2.0 moves the image's edge",
              "fisheye": "sensor synth is a fisheye camera", "uncalibrated": "sensor synth has no calibration",
              "photo": "camera 004: photo 004 not found", "broken": "unreadable Metashape XML",
              "same-name": "camera 004: several photos of that name (100MEDIA/004.png, 101MEDIA/004.png)",
              "two": "several Metashape camera files (a.xml, b.xml)",
              "none": "no aligned cameras"}[case]
    if case == "fisheye":
        xml.write_text(text.replace('type="frame">', 'type="fisheye">', 1))
    elif case == "uncalibrated":
        start, end = text.index("<calibration"), text.rindex("</calibration>") + len("</calibration>")
        xml.write_text(text[:start] + text[end:])
    elif case == "photo":
        (out / "images" / "004.png").unlink()
    elif case == "same-name":  # a drone numbering its photos again on a new card folder
        for d in ("100MEDIA", "101MEDIA"):
            (out / "images" / d).mkdir()
            shutil.copyfile(out / "images" / "004.png", out / "images" / d / "004.png")
        (out / "images" / "004.png").unlink()
    elif case == "broken":
        xml.write_text(text[: len(text) // 2])
    elif case == "two":
        shutil.copyfile(xml, out / "a.xml")
        xml.rename(out / "b.xml")
    elif case == "none":
        import re

        xml.write_text(re.sub(r"<transform>[^<]*</transform>", "", text))
    with pytest.raises(InputError) as e:
        read_any_scene(out)
    assert expect in str(e.value) and (out.name in str(e.value))
