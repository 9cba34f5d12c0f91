"""Scenes as RealityCapture leaves them (an XMP sidecar beside each photo): the cameras the LEVIR
reader gives for the same views, RealityCapture's lens (a 35 mm focal length on the longer side,
the principal point from the centre, its t1 / t2 order) as the pinhole and distortion COLMAP
undistorts, clear errors; other tools' XMP sidecars are no scene."""
from __future__ import annotations

import numpy as np
import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.load import read_any_cameras, read_any_scene

pycolmap = pytest.importorskip("pycolmap")

from photo_synth import assert_same_views, levir_as_realitycapture  # noqa: E402


@pytest.mark.parametrize("folder", ["images", "."], ids=["images-folder", "scene-folder"])
def test_xmp_sidecars_read_the_cameras_of_the_same_views(tiny_scene, tmp_path, folder):
    out = tmp_path / "rc"
    levir_as_realitycapture(tiny_scene, out, folder=folder)
    levir, rc = read_any_scene(tiny_scene, load_depth=False), read_any_scene(out)
    assert_same_views(rc, levir)
    assert rc.train == levir.train
    for where in (out, out / folder / "004.xmp"):  # `dibrgs render --cameras`: the folder or one sidecar
        cams = read_any_cameras(where)
        assert [c.name for c in cams] == (list(rc.views) if where == out else ["004"])
        np.testing.assert_array_equal(cams[-1].w2c, rc.views[cams[-1].name].camera.w2c)


def test_realitycapture_lens_projects_as_its_model_says(tiny_scene, tmp_path, monkeypatch):
    """brown3t2 on a 64 x 48 photo: a point lands at w / 2 + U s + f x_d, h / 2 + V s + f y_d (s the
    longer side, f = FocalLength35mm / 36 s), with Brown-Conrady's x_d = x d_r + t1 (r^2 + 2 x^2) +
    2 t2 x y and y_d = y d_r + t2 (r^2 + 2 y^2) + 2 t1 x y."""
    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    from PIL import Image

    from dibrgs_core.data.frame_layouts import layout_frames

    k = [-0.1, 0.02, 0.003, 0.0, 0.002, -0.001]
    xcr = {"DistortionModel": "brown3t2", "FocalLength35mm": "40.0", "PrincipalPointU": "0.01",
           "PrincipalPointV": "-0.02", "DistortionCoeficients": " ".join(map(str, k))}
    out = tmp_path / "rc"
    levir_as_realitycapture(tiny_scene, out, xcr=xcr)
    for p in (out / "images").glob("*.png"):
        Image.open(p).crop((0, 8, 64, 56)).save(p)
    frame = next(f for f in layout_frames(out) if f.name == "000.png")
    model, params = frame.camera_model(64, 48)
    xy = np.random.default_rng(0).uniform(-0.4, 0.4, (50, 2))
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    dr = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    xd = x * dr + k[4] * (r2 + 2 * x * x) + 2 * k[5] * x * y
    yd = y * dr + k[5] * (r2 + 2 * y * y) + 2 * k[4] * x * y
    f = 40.0 / 36.0 * 64
    got = pycolmap.Camera(model=model, width=64, height=48, params=params).img_from_cam(
        np.column_stack([xy, np.ones(len(xy))]))
    np.testing.assert_allclose(got, np.column_stack([32 + 0.01 * 64 + f * xd, 24 - 0.02 * 64 + f * yd]), atol=1e-9)
    view = read_any_scene(out).views["000"]
    assert view.image.shape[:2] == (view.camera.height, view.camera.width)


@pytest.mark.parametrize("case", ["k4", "division", "aspect", "relative", "photo", "broken", "pose"])
def test_sidecars_we_cannot_read_are_named(tiny_scene, tmp_path, case):
    out = tmp_path / "rc"
    xcr = {"k4": {"DistortionModel": "brown4", "DistortionCoeficients": "0.1 0 0 0.01 0 0"},
           "division": {"DistortionModel": "division"}, "aspect": {"AspectRatio": "1.1"},
           "relative": {"Coordinates": "relative"}}.get(case)
    levir_as_realitycapture(tiny_scene, out, xcr=xcr)
    xmp = out / "images" / "005.xmp"
    expect = {"k4": "k4 has no equivalent", "division": "distortion model division has no COLMAP equivalent",
              "aspect": "pixel aspect ratio 1.1", "relative": "xcr:Coordinates is relative",
              "photo": "no photo 005 beside it", "broken": "unreadable XMP",
              "pose": "xcr:Rotation: expected 9 finite numbers"}[case]
    if case == "photo":
        (out / "images" / "005.png").unlink()
    elif case == "broken":
        xmp.write_text(xmp.read_text()[:200])
    elif case == "pose":
        text = xmp.read_text()
        start = text.index("<xcr:Rotation>") + len("<xcr:Rotation>")
        xmp.write_text(text[:start] + "1 0 0 " + text[text.index("</xcr:Rotation>"):])
    with pytest.raises(InputError) as e:
        read_any_scene(out)
    assert expect in str(e.value)


def test_other_tools_sidecars_are_no_scene(tiny_scene, tmp_path):
    """Lightroom's XMP sidecars (no xcr namespace) beside photos: not a RealityCapture scene."""
    out = tmp_path / "lr" / "images"
    out.mkdir(parents=True)
    (out / "a.png").write_bytes((tiny_scene / "Images" / "000.png").read_bytes())
    (out / "a.xmp").write_text('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
                               'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description '
                               'xmlns:crs="http://ns.adobe.com/camera-raw-settings/1.0/" crs:Exposure2012="+0.5"/>'
                               "</rdf:RDF></x:xmpmeta>")
    with pytest.raises(InputError, match="not a scene"):
        read_any_scene(out.parent)


def test_sidecars_in_other_serialisations_read_alike(tiny_scene, tmp_path):
    """A property written as an element instead of an attribute, another version of the xcr
    namespace, and a sidecar named NAME.png.xmp: the same cameras."""
    import re

    out = tmp_path / "rc"
    levir_as_realitycapture(tiny_scene, out)
    xmp = out / "images" / "006.xmp"
    text = xmp.read_text().replace("ns/xcr/1.1#", "ns/xcr/1.2#")
    focal = re.search(r' xcr:FocalLength35mm="([^"]+)"', text)
    text = text.replace(focal.group(0), "").replace(
        "<xcr:Rotation>", f"<xcr:FocalLength35mm>{focal.group(1)}</xcr:FocalLength35mm><xcr:Rotation>")
    xmp.unlink()
    (out / "images" / "006.png.xmp").write_text(text)
    assert_same_views(read_any_scene(out), read_any_scene(tiny_scene, load_depth=False))
