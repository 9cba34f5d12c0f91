"""The add-on in Blender, without torch: scene import, cameras, path, compositor, polls, job state.

Nothing here needs the training interpreter, so the same file runs with bpy 5.0.1 (the project's
environment) and with bpy 4.2 LTS in a second environment that has numpy and nothing else of the
library's dependencies (``.ci/run``): the 4.2 compositor branch (``scene.use_nodes``,
``scene.node_tree``, Composite node) runs for real there. That environment gets its scene from
``$DIBRGS_TEST_SCENE`` (made by ``scripts/make_scene.py`` in the main environment).

The repository is loaded the way Blender loads the extension (``tests/addon/conftest.py``).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from paths import shared_file

bpy = pytest.importorskip("bpy")

REPO = Path(__file__).resolve().parents[2]
#: What Blender's own Python does not have: the add-on must work without importing any of it.
BLOCKED = ("torch", "PIL", "pycolmap", "scipy", "tifffile", "OpenEXR", "trimesh", "skimage", "matplotlib",
           "transformers", "cv2")


@pytest.fixture
def scene64(request) -> Path:
    """A 64x64 generated city: $DIBRGS_TEST_SCENE, else the session's tiny_scene."""
    if os.environ.get("DIBRGS_TEST_SCENE"):
        return Path(os.environ["DIBRGS_TEST_SCENE"])
    return request.getfixturevalue("tiny_scene")


def _mod(name: str):
    return sys.modules[f"dibrgs_ext.addon.{name}"]


def _view_objects() -> dict[str, bpy.types.Object]:
    return {o["dibrgs_view"]: o for o in bpy.data.objects if "dibrgs_view" in o}


def _datablock_counts() -> dict[str, int]:
    return {k: len(getattr(bpy.data, k)) for k in ("objects", "collections", "cameras", "images", "texts",
                                                   "curves", "node_groups")}


def _cams_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(w2c, K) of a LEVIR Cams file, parsed here rather than by the code under test."""
    t = path.read_text().split()
    ie, ii = t.index("extrinsic"), t.index("intrinsic")
    return np.array(t[ie + 1:ie + 17], float).reshape(4, 4), np.array(t[ii + 1:ii + 10], float).reshape(3, 3)


def _pixels(path: Path) -> np.ndarray:
    """8-bit RGB values of a PNG as Blender reads them (no colour conversion for byte images)."""
    img = bpy.data.images.load(str(path))
    try:
        w, h = img.size
        px = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(px)
        return np.round(px.reshape(h, w, 4)[..., :3] * 255).astype(int)
    finally:
        bpy.data.images.remove(img)


def test_register_unregister_twice(ext):
    for _ in range(2):
        ext.unregister()
        assert not hasattr(bpy.types.Scene, "dibrgs")
        assert not hasattr(bpy.types, "DIBRGS_PT_main")
        assert sys.modules["dibrgs_ext.addon"]._cli_handle is None
        ext.register()
        assert hasattr(bpy.types.Scene, "dibrgs")
        assert bpy.types.DIBRGS_PT_main.bl_category == "DIBR-GS"
        assert bpy.ops.dibrgs.train.idname() == "DIBRGS_OT_train"
        assert sys.modules["dibrgs_ext.addon"]._cli_handle is not None  # `blender -c dibrgs`
        assert _mod("operators")._load_post in bpy.app.handlers.load_post
    # The add-on resolved the extension's own dibrgs_core, not the top-level one.
    assert _mod("_core").CORE_PACKAGE == "dibrgs_ext.dibrgs_core"
    assert _mod("_core").pinhole.__name__ == "dibrgs_ext.dibrgs_core.camera.pinhole"


def test_import_says_when_training_leaves_pseudo_views_out(scene64, fresh, tmp_path):
    """Twelve training views: training's ``auto`` leaves pseudo views out (dense enough); the import
    says so beside the path it still draws, so that an edited path is not expected to count."""
    import shutil

    assert bpy.ops.dibrgs.import_scene(directory=str(scene64)) == {"FINISHED"}
    assert "leaves pseudo views out" not in fresh.dibrgs.message  # three training views: used
    dense = Path(shutil.copytree(scene64, tmp_path / "dense"))
    ids = sorted(p.stem for p in (dense / "Cams").glob("*.txt"))
    (dense / "split.json").write_text(json.dumps({"train": ids[:12], "test": ids[12:15]}))
    assert bpy.ops.dibrgs.import_scene(directory=str(dense)) == {"FINISHED"}
    assert "12 training" in fresh.dibrgs.message
    assert "training leaves pseudo views out: 12 training views are dense enough (>= 10)" in fresh.dibrgs.message


def test_import_scene_reproduces_every_camera(scene64, fresh):
    assert bpy.ops.dibrgs.import_scene(directory=str(scene64)) == {"FINISHED"}
    sb = _mod("scene_build")
    objs = _view_objects()
    ids = sorted(p.stem for p in (scene64 / "Cams").glob("*.txt"))
    assert sorted(objs) == ids
    r = fresh.render
    assert (r.resolution_x, r.resolution_y, r.resolution_percentage) == (64, 64, 100)
    centres = []
    for vid, obj in objs.items():
        w2c, K = _cams_file(scene64 / "Cams" / f"{vid}.txt")
        centres.append(-w2c[:3, :3].T @ w2c[:3, 3])
        cam = sb.camera_from_object(obj, fresh)  # through cameras.from_blender on the bpy data
        assert (cam.width, cam.height) == (64, 64)
        np.testing.assert_allclose(cam.K, K, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(cam.R, w2c[:3, :3], atol=1e-5)
        # Blender stores matrices in float32: positions are exact to 1e-5 of the scene's extent.
        np.testing.assert_allclose(cam.center, centres[-1], atol=1e-5 * np.abs(centres[-1]).max())
    train = [o for o in objs.values() if o["dibrgs_split"] == "train"]
    assert [o.name for o in train] == ["001", "008", "015"]  # the 3-view protocol
    assert all(o.users_collection[0].name == sb.TRAIN_COLLECTION for o in train)
    for o in objs.values():
        bgs = o.data.background_images
        assert len(bgs) == (1 if o in train else 0)
        if bgs:
            want = (scene64 / "Images" / f"{o.name}.png").resolve()
            assert Path(bpy.path.abspath(bgs[0].image.filepath)).resolve() == want
    assert fresh.camera == objs["001"]
    props = fresh.dibrgs
    assert props.path_curve is not None and props.path_curve.type == "CURVE" and props.path_target is not None


def test_wrong_folder_reports_an_error_and_creates_nothing(fresh, tmp_path):
    junk = tmp_path / "not_a_scene"
    (junk / "photos").mkdir(parents=True)
    (junk / "photos" / "a.png").write_bytes(b"not an image")
    before = _datablock_counts()
    with pytest.raises(RuntimeError, match="Cannot import .*not_a_scene: not a scene"):
        bpy.ops.dibrgs.import_scene(directory=str(junk))
    assert "not a scene" in fresh.dibrgs.error
    with pytest.raises(RuntimeError, match="not a folder"):
        bpy.ops.dibrgs.import_scene(directory=str(tmp_path / "missing"))
    assert _datablock_counts() == before


def test_editing_the_curve_moves_the_pseudo_views(scene64, fresh):
    bpy.ops.dibrgs.import_scene(directory=str(scene64))
    sb = _mod("scene_build")
    props = fresh.dibrgs
    n = 16
    before = sb.path_cameras(bpy.context, n, "pseudo")
    assert not sb.path_edited(bpy.context)  # as drawn: training samples the trajectory itself
    # The generated scene's cameras are on an orbit: the path starts on the circle fitted to them.
    plan = sb.plan_path(sb.scene_description())
    assert plan.kind == "orbit" and props.path_curve[sb.TRAJECTORY_KEY] == "orbit"
    assert sb.curve_polylines(bpy.context, props.path_curve)[1] == [True]  # one closed spline
    orbit = plan.orbit
    radii = [np.linalg.norm(c.center - orbit.center) for c in before]
    np.testing.assert_allclose(radii, orbit.radius, rtol=1e-3)
    # Lift control point 0 (where sample 0 sits) along the scene up axis.
    up = np.array(props.scene_up)
    bp = props.path_curve.data.splines[0].bezier_points[0]
    lift = 0.3 * orbit.radius
    for attr in ("co", "handle_left", "handle_right"):
        setattr(bp, attr, np.array(getattr(bp, attr)) + lift * up)
    after = sb.path_cameras(bpy.context, n, "pseudo")
    assert sb.path_edited(bpy.context)  # the user's path now: training takes these cameras
    assert (after[0].center - before[0].center) @ up > 0.5 * lift  # the sample at the edited point follows it up
    # The far side of the path only slides along the old circle (arc-length spacing), it does not rise.
    far = after[n // 2].center
    assert abs((far - before[n // 2].center) @ up) < 1e-3 * lift
    assert abs(np.linalg.norm(far - orbit.center) - orbit.radius) < 1e-3 * orbit.radius
    # Moving the look-at Empty turns the cameras towards it (and is an edit of the path).
    assert bpy.ops.dibrgs.reset_path() == {"FINISHED"} and not sb.path_edited(bpy.context)
    props.path_target.location = np.array(props.path_target.location) + [0.2 * orbit.radius, 0, 0]
    bpy.context.view_layer.update()
    turned = sb.path_cameras(bpy.context, n, "pseudo")
    uv, _ = turned[3].project(np.array(props.path_target.location)[None])
    np.testing.assert_allclose(uv[0], [turned[3].cx, turned[3].cy], atol=1e-6)
    assert sb.path_edited(bpy.context)


class _Layout:
    """Stands in for a panel's ``UILayout``: records label texts, accepts everything else."""

    def __init__(self, labels: list[str]):
        self.labels = labels

    def label(self, text: str = "", **_):
        self.labels.append(text)

    def operator(self, *_, **__):
        return type("Op", (), {})()

    def __getattr__(self, name):
        if name in ("box", "row", "column"):
            return lambda *a, **k: _Layout(self.labels)
        return lambda *a, **k: None


def _panel_labels() -> list[str]:
    labels: list[str] = []
    _mod("panel").DIBRGS_PT_main.draw(type("P", (), {"layout": _Layout(labels)})(), bpy.context)
    return labels


def test_strip_flight_path_follows_the_strips(fresh, tmp_path):
    """A real mapping flight (one photo of each of three strips): the path is the line through the
    training cameras, continued past its ends, with nadir cameras oriented like the photos - not
    a circle fitted through three nearly collinear cameras (views of padding)."""
    scene = shared_file("data/brighton_north")
    assert bpy.ops.dibrgs.import_scene(directory=str(scene)) == {"FINISHED"}
    sb = _mod("scene_build")
    props = fresh.dibrgs
    desc = sb.scene_description()
    train = sb.described_cameras(desc, "train")
    assert props.path_target is None and sb.TARGET_NAME not in bpy.data.objects
    assert props.path_curve[sb.TRAJECTORY_KEY] == "strips" and "strips" in props.message
    polys, closed = sb.curve_polylines(bpy.context, props.path_curve)
    assert len(polys) == 1 and closed == [False]
    C = np.stack([c.center for c in train])
    d = C[-1] - C[0]
    d /= np.linalg.norm(d)
    along = sorted(float((c - C[0]) @ d) for c in C)
    ends = sorted(float((p - C[0]) @ d) for p in polys[0][[0, -1]])
    assert ends[0] < along[0] - 0.2 * (along[1] - along[0]) and ends[1] > along[-1] + 0.2 * (along[-1] - along[-2])
    cams = sb.path_cameras(bpy.context, 12, "pseudo")
    spread = np.linalg.norm(C[-1] - C[0])
    for cam in cams:
        off = cam.center - C[0]
        assert np.linalg.norm(off - (off @ d) * d) < 0.1 * spread  # on the line through the cameras
        nearest = min(train, key=lambda t: np.linalg.norm(t.center - cam.center))
        turn = np.degrees(np.arccos(np.clip((np.trace(nearest.R @ cam.R.T) - 1) / 2, -1, 1)))
        assert turn < 5.0  # oriented as the photos (nadir, same heading)
    # At a training camera the path camera is that camera's pose.
    at = sb.path_mod.path_cameras([C[[0, 1]]], 2, None, props.scene_up, train[0], False, follow=train)
    np.testing.assert_allclose(at[0].w2c, train[0].w2c, atol=1e-9)
    np.testing.assert_allclose(at[1].w2c, train[1].w2c, atol=1e-9)
    # A curve of several splines (here the line continued by a second spline drawn back towards
    # it): pseudo views stay on the splines, a fly-through takes one route through them without
    # jumping back (spline by spline it would run out along the line, jump, and come back).
    sp = props.path_curve.data.splines.new("POLY")
    sp.points.add(1)
    far = polys[0][-1] if (polys[0][-1] - polys[0][0]) @ d > 0 else polys[0][0]
    sp.points[0].co, sp.points[1].co = (*(far + 0.5 * spread * d), 1.0), (*far, 1.0)
    two, _ = sb.curve_polylines(bpy.context, props.path_curve)
    assert len(two) == 2
    fly = [c.center for c in sb.path_cameras(bpy.context, 20, "fly", route=True)]
    along_fly = [float((c - C[0]) @ d) for c in fly]
    assert all(b >= a - 1e-9 for a, b in zip(along_fly, along_fly[1:])) or \
        all(b <= a + 1e-9 for a, b in zip(along_fly, along_fly[1:]))  # one way along the line
    props.path_curve.data.splines.remove(sp)
    # What changes the path's cameras is an edit: the spline's type, the curve's resolution, the
    # scene's up axis; a bevel is not (the centre line is read), and is not one.
    for change, undo in ((lambda: setattr(props.path_curve.data.splines[0], "type", "NURBS"),
                          lambda: setattr(props.path_curve.data.splines[0], "type", "POLY")),
                         (lambda: setattr(props.path_curve.data, "resolution_u", 5),
                          lambda: setattr(props.path_curve.data, "resolution_u", 32)),
                         (lambda: setattr(props, "scene_up", (0.0, 0.0, 1.0)),
                          lambda: setattr(props, "scene_up", plan_up))):
        plan_up = tuple(props.scene_up)
        assert not sb.path_edited(bpy.context)
        change()
        assert sb.path_edited(bpy.context)
        undo()
    assert not sb.path_edited(bpy.context)
    props.path_curve.data.bevel_depth = 0.05
    bevelled, _ = sb.curve_polylines(bpy.context, props.path_curve)
    assert len(bevelled) == 1 and np.allclose(bevelled[0], polys[0], atol=1e-6)
    assert props.path_curve.data.bevel_depth == pytest.approx(0.05)  # left as the user set it
    props.path_curve.data.bevel_depth = 0.0
    # Far from the origin (map coordinates) a small move is still an edit.
    props.path_curve.location = (5e6, -3e6, 0.0)
    bpy.context.view_layer.update()
    props.path_curve[sb.FINGERPRINT_KEY] = sb.path_fingerprint(props.path_curve, None, props.scene_up)
    props.path_curve.data.splines[0].points[1].co[0] += 1e-3 * spread
    assert sb.path_edited(bpy.context)
    # Resuming a run that started with a path keeps giving it one (runs the add-on began before
    # it sampled the trajectory itself), an unedited path otherwise gives none.
    assert bpy.ops.dibrgs.reset_path() == {"FINISHED"}
    work = tmp_path
    (work / "config.json").write_text(json.dumps({"config": {"pseudo_path": str(work / "pseudo_path.json")}}))
    assert sb.training_takes_path(bpy.context, work, resume=True)
    assert not sb.training_takes_path(bpy.context, work, resume=False)
    (work / "config.json").write_text(json.dumps({"config": {"pseudo_path": None}}))
    assert not sb.training_takes_path(bpy.context, work, resume=True)
    # Reset Path draws the same path again after an edit; the panel says which path training takes.
    assert not sb.path_edited(bpy.context)
    assert "As drawn: training samples the strips" in _panel_labels()
    props.path_curve.data.splines[0].points[0].co[2] += 1.0
    assert sb.path_edited(bpy.context)
    assert "Edited: training uses its cameras" in _panel_labels()
    assert bpy.ops.dibrgs.reset_path() == {"FINISHED"} and not sb.path_edited(bpy.context)
    again, _ = sb.curve_polylines(bpy.context, props.path_curve)
    np.testing.assert_allclose(again[0], polys[0], atol=1e-6)


# ---------------------------------------------------------------------------
# Blender's Python has no torch, Pillow or pycolmap: import works without them
# ---------------------------------------------------------------------------
_NO_TORCH_DRIVER = """
import json, sys
BLOCKED = set(sys.argv[1].split(","))
attempts = []
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            attempts.append(name)
            raise ModuleNotFoundError(f"No module named {name!r} (blocked: Blender's Python has none)")
sys.meta_path.insert(0, Block())
import importlib.util
from pathlib import Path
import bpy
repo, scene, colmap, init, out = (Path(a) if a else None for a in sys.argv[2:7])
spec = importlib.util.spec_from_file_location("dibrgs_ext", repo / "__init__.py",
                                              submodule_search_locations=[str(repo)])
ext = importlib.util.module_from_spec(spec); sys.modules["dibrgs_ext"] = ext; spec.loader.exec_module(ext)
bpy.ops.wm.read_factory_settings(use_empty=True)
ext.register()
C = bpy.context
res = {}
if colmap:
    assert bpy.ops.dibrgs.import_scene(directory=str(colmap)) == {"FINISHED"}
    res["colmap_views"] = sum("dibrgs_view" in o for o in bpy.data.objects)
assert bpy.ops.dibrgs.import_scene(directory=str(scene)) == {"FINISHED"}
res["levir_views"] = sum("dibrgs_view" in o for o in bpy.data.objects)
assert bpy.ops.dibrgs.reset_path() == {"FINISHED"}
sb = sys.modules["dibrgs_ext.addon.scene_build"]
results = sys.modules["dibrgs_ext.addon.results"]
comp = sys.modules["dibrgs_ext.addon.compositor"]
res["pseudo"] = len(sb.path_cameras(C, 8, "pseudo"))
names = results.load_renders(C.scene, scene / "Images", ["002", "003"], "heldout")
results.show_all(C.scene, names[1])
res["wired"] = comp.wired_image(C.scene)
res["points"] = results.load_init(C, init)
res["height_map"] = sb.HEIGHT_NAME in bpy.data.objects
ext.unregister()
res["attempts"] = sorted(set(attempts))
res["loaded"] = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
out.write_text(json.dumps(res))
"""


def test_strip_flight_path_gains_the_headings_when_the_dense_points_arrive(fresh, tmp_path):
    """One photo a strip: once initialisation brings the dense points (here a ground plane written
    as the init folder's points.ply), the unedited path is drawn again with a line along each
    camera's heading, as long as the image's ground extent; a path the user edited is kept."""
    scene = shared_file("data/brighton_north")
    assert bpy.ops.dibrgs.import_scene(directory=str(scene)) == {"FINISHED"}
    sb, results = _mod("scene_build"), _mod("results")
    props = fresh.dibrgs
    train = sb.described_cameras(sb.scene_description(), "train")
    depth = 5.0
    pts = []
    for c in train:  # the ground each training photo sees, `depth` in front of it
        for u in np.linspace(0, c.width, 7):
            for v in np.linspace(0, c.height, 5):
                ray = c.R.T @ np.linalg.solve(c.K, [u, v, 1.0])
                pts.append(c.center + depth / ray @ c.R.T[:, 2] * ray)
    init = tmp_path / "init"
    init.mkdir()
    (init / "points.ply").write_text("ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
                                     "property float z\nend_header\n" % len(pts)
                                     + "".join("%.6f %.6f %.6f\n" % tuple(p) for p in pts))
    assert len(sb.curve_polylines(bpy.context, props.path_curve)[0]) == 1
    assert results.load_init(bpy.context, init) == len(pts)
    polys, _ = sb.curve_polylines(bpy.context, props.path_curve)
    assert len(polys) == 1 + len(train) and not sb.path_edited(bpy.context)
    C = np.stack([c.center for c in train])
    for c in train:
        head = min(polys, key=lambda p: np.linalg.norm(p.mean(0) - c.center))
        length = np.linalg.norm(head[-1] - head[0])
        assert length == pytest.approx(c.height / c.K[1, 1] * depth, rel=0.05)  # median depth of all photos
        up = -c.R[1] / np.linalg.norm(c.R[1])
        assert abs((head[-1] - head[0]) @ up) / length > 0.99  # along the photo's image up
    # edited by the user: loading the points again keeps the user's path
    sp = props.path_curve.data.splines[0]
    sp.points[0].co = (*(C[0] + [0.1, 0.1, 0.0]), 1.0)
    assert sb.path_edited(bpy.context)
    results.load_init(bpy.context, init)
    assert len(sb.curve_polylines(bpy.context, props.path_curve)[0]) == 1 + len(train)
    assert sb.path_edited(bpy.context)


def test_init_points_of_a_far_scene_land_where_its_cameras_are(fresh, tmp_path):
    """A scene far from its coordinate origin trains in a frame of its own (``scene_origin`` of
    init_report.json): its points and height map are placed at that origin, so that they lie
    under the cameras the add-on imported from the scene's files."""
    import json

    from dibrgs_core.geometry.height_map import HeightMap

    scene = shared_file("data/brighton_north")
    assert bpy.ops.dibrgs.import_scene(directory=str(scene)) == {"FINISHED"}
    sb, results = _mod("scene_build"), _mod("results")
    train = sb.described_cameras(sb.scene_description(), "train")
    world = np.array([c.center - 5.0 * c.R[2] for c in train])  # 5 units in front of each photo
    origin = np.array([-2.0, 3.0, 1.0])  # as if the run's frame were moved (exact in float32 here)
    init = tmp_path / "init"
    init.mkdir()
    local = world - origin
    (init / "points.ply").write_text("ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
                                     "property float z\nend_header\n" % len(local)
                                     + "".join("%.6f %.6f %.6f\n" % tuple(p) for p in local))
    (init / "init_report.json").write_text(json.dumps({"decisions": [], "values": {"scene_origin": origin.tolist()}}))
    HeightMap(up_frame=np.eye(3), origin=np.zeros(3), cell=1.0, x0=-1.0, y0=-1.0,
              bounds=np.ones((2, 2))).save(init / "height_map.npz")
    assert results.load_init(bpy.context, init) == len(world)
    assert np.allclose(sb.dense_points(), world, atol=1e-5)
    hm = bpy.data.objects[sb.HEIGHT_NAME]
    assert tuple(hm.location) == pytest.approx(tuple(origin))


def _save_with_blender(path: Path, rgb: np.ndarray, fmt: str = "PNG") -> None:
    """Write float RGB rows top to bottom as a PNG or JPEG with Blender (the 4.x test environments
    have no Pillow)."""
    h, w = rgb.shape[:2]
    img = bpy.data.images.new(path.stem, w, h)
    img.pixels.foreach_set(np.concatenate([rgb, np.ones((h, w, 1))], axis=2)[::-1].astype(np.float32).ravel())
    img.filepath_raw, img.file_format = str(path), fmt
    if fmt == "JPEG":
        bpy.context.scene.render.image_settings.quality = 95
    img.save()
    bpy.data.images.remove(img)


def _tag_orientation(path: Path, orientation: int) -> None:
    """Give a JPEG an EXIF block holding only its orientation (tag 274), after its JFIF header."""
    data = path.read_bytes()
    at = 2 + (2 + int.from_bytes(data[4:6], "big") if data[2:4] == b"\xff\xe0" else 0)
    tiff = b"II*\x00" + (8).to_bytes(4, "little") + (1).to_bytes(2, "little") \
        + (274).to_bytes(2, "little") + (3).to_bytes(2, "little") + (1).to_bytes(4, "little") \
        + orientation.to_bytes(2, "little") + b"\x00\x00" + (0).to_bytes(4, "little")
    block = b"Exif\x00\x00" + tiff
    path.write_bytes(data[:at] + b"\xff\xe1" + (len(block) + 2).to_bytes(2, "big") + block + data[at:])


def _pattern(w: int, h: int, shift: int = 0) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([0.5 + 0.45 * np.sin((x + shift) / 7.0) * np.cos(y / 9.0), x / w * 0.9 + 0.05,
                     y / h * 0.9 + 0.05], -1)


@pytest.mark.parametrize("unit", [1e-3, 1.0, 1e3])
def test_a_colmap_project_in_any_units_is_not_clipped_away(fresh, tmp_path, unit):
    """A COLMAP model has no depth ranges and arbitrary units: the cameras and the 3D views clip at
    1/100 and 100 x the distance the photos' spacing implies, not at Blender's 0.1-1000 (a flight
    100 m high in millimetres, or in kilometres, was cut away: nothing seen through its cameras)."""
    root = tmp_path / "colmap_project"
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").mkdir()
    (root / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 96 64 80 80 48 32\n")
    lines = []
    for i in range(3):  # looking straight down from 100 m, 40 m apart: photos overlapping by a half
        lines += [f"{i + 1} 0 1 0 0 {-40.0 * i * unit} 0 {100.0 * unit} 1 v{i}.png", ""]
        _save_with_blender(root / "images" / f"v{i}.png", _pattern(96, 64, 7 * i))
    (root / "sparse" / "0" / "images.txt").write_text("\n".join(lines) + "\n")
    assert bpy.ops.dibrgs.import_scene(directory=str(root)) == {"FINISHED"}
    depth = 100.0 * unit
    for obj in _view_objects().values():
        assert obj.data.clip_start < 0.1 * depth and obj.data.clip_end > 10 * depth
        assert obj.data.clip_end / obj.data.clip_start < 1.01e4  # no deeper than Blender's own range
        # drawn at the scene's size (Blender allows 0.01-1000), not at 1 unit
        assert min(0.01 * depth, 1000.0) <= obj.data.display_size <= max(0.5 * depth, 0.01)
    spaces = [sp for sc in bpy.data.screens for a in sc.areas for sp in a.spaces if sp.type == "VIEW_3D"]
    assert spaces and all(sp.clip_start < depth < sp.clip_end for sp in spaces)


def test_a_colmap_project_with_lens_distortion_imports_with_the_cameras_training_uses(fresh, tmp_path):
    """COLMAP's default camera model has radial distortion: the import gives each view the undistorted
    pinhole the library trains with (the add-on refused such projects before 2026-11-25)."""
    from dibrgs_core.bridge.colmap_model import ColmapCamera

    root = tmp_path / "colmap_project"
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").mkdir()
    (root / "sparse" / "0" / "cameras.txt").write_text("1 SIMPLE_RADIAL 96 64 80 48 32 -0.25\n")
    lines = []
    for i in range(3):  # looking straight down from 100 units, 10 units apart
        lines += [f"{i + 1} 0 1 0 0 {-10.0 * i} 0 100 1 v{i}.png", ""]
        _save_with_blender(root / "images" / f"v{i}.png", _pattern(96, 64, 7 * i))
    (root / "sparse" / "0" / "images.txt").write_text("\n".join(lines) + "\n")
    assert bpy.ops.dibrgs.import_scene(directory=str(root)) == {"FINISHED"}
    want = ColmapCamera(1, "SIMPLE_RADIAL", 96, 64, np.array([80.0, 48, 32, -0.25])).pinhole(root)
    try:  # where pycolmap is installed (bpy 5.0's environment), it agrees
        import pycolmap
    except ImportError:
        pass
    else:
        ref = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), pycolmap.Camera(
            model="SIMPLE_RADIAL", width=96, height=64, params=[80.0, 48, 32, -0.25]))
        assert (ref.width, ref.height) == (want.width, want.height)
        np.testing.assert_array_equal(ref.calibration_matrix(), want.K())
    assert (want.width, want.height) != (96, 64)  # undistorted: another size
    sb = _mod("scene_build")
    objs = _view_objects()
    assert sorted(objs) == ["v0", "v1", "v2"]
    for vid, obj in objs.items():
        cam = sb.camera_from_object(obj, fresh)
        assert (cam.width, cam.height) == (want.width, want.height), vid
        np.testing.assert_allclose(cam.K, want.K(), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(cam.center, [10.0 * int(vid[1]), 0, 100], atol=1e-4)
    assert (fresh.render.resolution_x, fresh.render.resolution_y) == (want.width, want.height)
    assert "3 cameras undistorted as training reads them" in fresh.dibrgs.message


def test_photos_stored_turned_import_upright(fresh, tmp_path):
    """Photos from a camera held on its side (JPEG with an EXIF orientation): Blender loads the stored
    pixels and ignores the tag, the library turns them upright; the view objects get the upright
    photos' cameras and the training views' backgrounds show the photos upright."""
    from dibrgs_core.camera.pinhole import Camera, look_at
    from dibrgs_core.data.levir import write_cams_file

    root = tmp_path / "turned"
    (root / "Images").mkdir(parents=True)
    K = np.array([[80.0, 0, 48], [0, 80.0, 32], [0, 0, 1]])
    ups = {}
    # stored pixels of a photo whose EXIF orientation is o, rows top to bottom (o turns them upright)
    stored = {1: lambda a: a, 3: lambda a: a[::-1, ::-1], 6: lambda a: np.rot90(a, 1), 8: lambda a: np.rot90(a, -1)}
    for i, o in enumerate([6, 8, 1, 3]):
        write_cams_file(root / "Cams" / f"{i:03d}.txt",
                        Camera(K=K, w2c=look_at([20.0 * i, 0, 100], [20.0 * i, 0, 0], [0, 1.0, 0]), width=96,
                               height=64, name=f"{i:03d}", depth_range=(50.0, 150.0)))
        ups[f"{i:03d}"] = _pattern(96, 64, 7 * i)
        _save_with_blender(root / "Images" / f"{i:03d}.jpg", np.ascontiguousarray(stored[o](ups[f"{i:03d}"])), "JPEG")
        if o != 1:
            _tag_orientation(root / "Images" / f"{i:03d}.jpg", o)
    (root / "split.json").write_text('{"train": ["000", "001", "002"], "test": ["003"]}')
    assert bpy.ops.dibrgs.import_scene(directory=str(root)) == {"FINISHED"}
    sb = _mod("scene_build")
    objs = _view_objects()
    for vid, obj in objs.items():
        cam = sb.camera_from_object(obj, fresh)
        assert (cam.width, cam.height) == (96, 64), vid
        np.testing.assert_allclose(cam.K, K, rtol=1e-5, atol=1e-5)
    for vid in ("000", "001", "002"):
        img = objs[vid].data.background_images[0].image
        assert tuple(img.size) == (96, 64), vid
        px = np.empty(96 * 64 * 4, np.float32)
        img.pixels.foreach_get(px)
        shown = px.reshape(64, 96, 4)[::-1, :, :3]
        assert np.abs(shown - ups[vid]).mean() < 0.02, vid  # JPEG loss only; a turned photo would be far off
    assert "3 photos turned upright by their EXIF orientation" in fresh.dibrgs.message
    assert objs["000"].data.background_images[0].image.packed_file is not None  # the copy is saved with the file
    assert objs["002"].data.background_images[0].image.filepath  # an upright photo is the file itself
    # a new import replaces the copies (named by view: a rig's photos may share file names)
    assert bpy.ops.dibrgs.import_scene(directory=str(root)) == {"FINISHED"}
    copies = sorted(i.name for i in bpy.data.images if i.name.endswith(" upright"))
    assert copies == ["DIBR-GS 000 upright", "DIBR-GS 001 upright"]
    assert _view_objects()["001"].data.background_images[0].image.name == "DIBR-GS 001 upright"


def test_the_split_is_chosen_by_moving_view_cameras(scene64, fresh, monkeypatch):
    """A camera moved into Train views trains, into Held-out views is held out, elsewhere is left out;
    jobs get that split, the path follows its training cameras, a re-import starts afresh."""
    monkeypatch.setenv("DIBRGS_PYTHON", sys.executable)
    assert bpy.ops.dibrgs.import_scene(directory=str(scene64)) == {"FINISHED"}
    sb, ops = _mod("scene_build"), _mod("operators")
    assert sb.split_summary().endswith("(as imported)") and ops._run(bpy.context).split is None
    objs = _view_objects()
    train, held, root = (bpy.data.collections[n] for n in (sb.TRAIN_COLLECTION, sb.TEST_COLLECTION, sb.ROOT_COLLECTION))
    held.objects.unlink(objs["004"])
    train.objects.link(objs["004"])  # trains now
    train.objects.unlink(objs["015"])
    root.objects.link(objs["015"])  # left out
    dup = objs["010"].copy()  # a duplicate in Train makes its view train
    train.objects.link(dup)
    desc = sb.scene_description()
    assert desc["train"] == ["001", "004", "008", "010"] and desc["split_source"] == sb.SPLIT_MOVED
    # 000 (the near-nadir view of a LEVIR scene) is left out by the scene's own split
    assert desc["test"] == [f"{i:03d}" for i in range(2, 21) if i not in (4, 8, 10, 15)]
    assert {v["name"]: v["split"] for v in desc["views"]}["015"] == "other"
    assert sb.scene_description(imported=True)["train"] == ["001", "008", "015"]
    assert sb.split_summary() == "Split: 4 training, 15 held-out, 2 left out (moved in Blender)"
    assert sb.split_summary() in _panel_labels()
    assert ops._run(bpy.context).split == (desc["train"], desc["test"])
    assert [c.name for c in sb.described_cameras(desc, "train")] == ["001", "004", "008", "010"]
    assert bpy.ops.dibrgs.reset_path() == {"FINISHED"}  # drawn along the cameras that train now
    bpy.data.objects.remove(objs["020"])  # a deleted camera's view is left out
    assert sb.split_summary() == "Split: 4 training, 14 held-out, 3 left out (moved in Blender)"
    # nothing in Train views: the jobs refuse, saying what to do
    for o in list(train.objects):
        train.objects.unlink(o)
        root.objects.link(o)
    with pytest.raises(_mod("operators").UserError, match="no view camera in the 'DIBR-GS Train views'"):
        ops._run(bpy.context)
    text = bpy.data.texts[sb.SCENE_TEXT].as_string()
    bpy.data.texts[sb.SCENE_TEXT].from_string("{")  # a description edited by hand: the panel still draws
    assert "Split: the imported description is damaged; import again" in _panel_labels()
    bpy.data.texts[sb.SCENE_TEXT].from_string(text)
    # a re-import brings the scene's own split back, and no camera of the old import stays
    assert bpy.ops.dibrgs.import_scene(directory=str(scene64)) == {"FINISHED"}
    assert sorted(_view_objects()) == [f"{i:03d}" for i in range(21)]
    assert len([o for o in bpy.data.objects if "dibrgs_view" in o]) == 21  # the moved ones and the duplicate gone
    assert sb.scene_description()["train"] == ["001", "008", "015"] and ops._run(bpy.context).split is None


def _imports_with_the_cams_files_cameras(root, scene64, fresh, layout_name: str) -> None:
    """Import ``root`` (the generated scene in another layout): the message names the layout and
    every view object has the Cams file's camera."""
    assert bpy.ops.dibrgs.import_scene(directory=str(root)) == {"FINISHED"}
    assert f"views from {root.name} ({layout_name}): " in fresh.dibrgs.message
    sb = _mod("scene_build")
    objs = _view_objects()
    assert sorted(objs) == sorted(p.stem for p in (scene64 / "Cams").glob("*.txt"))
    for vid, obj in objs.items():
        w2c, K = _cams_file(scene64 / "Cams" / f"{vid}.txt")
        cam = sb.camera_from_object(obj, fresh)
        np.testing.assert_allclose(cam.K, K, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(cam.R, w2c[:3, :3], atol=1e-5)


def test_a_transforms_json_scene_imports_with_its_cameras(scene64, fresh, tmp_path):
    """The generated scene written as a transforms.json (OpenGL camera-to-world, as instant-ngp and
    nerfstudio write it): every view object has the Cams file's camera."""
    root = tmp_path / "ngp"
    (root / "images").mkdir(parents=True)
    frames = []
    for cams in sorted((scene64 / "Cams").glob("*.txt")):
        w2c, K = _cams_file(cams)
        (root / "images" / f"{cams.stem}.png").symlink_to(scene64 / "Images" / f"{cams.stem}.png")
        c2w = np.linalg.inv(w2c)
        c2w[:3, 1:3] *= -1.0  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"images/{cams.stem}.png", "transform_matrix": c2w.tolist()})
    (root / "transforms.json").write_text(json.dumps({"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2],
                                                      "cy": K[1, 2], "w": 64, "h": 64, "frames": frames}))
    _imports_with_the_cams_files_cameras(root, scene64, fresh, "transforms.json")


def test_a_metashape_export_imports_with_its_cameras(scene64, fresh, tmp_path):
    """The generated scene as Metashape's camera export (cameras.xml with the cameras in a chunk frame
    that a scaled, turned, shifted chunk transform takes to the world; photos in images/ named by
    label): every view object has the Cams file's camera."""
    root = tmp_path / "metashape"
    (root / "images").mkdir(parents=True)
    c, s = np.cos(0.7), np.sin(0.7)
    chunk = np.array([[2 * c, -2 * s, 0, 30.0], [2 * s, 2 * c, 0, -12.0], [0, 0, 2, 5.0], [0, 0, 0, 1]])
    cameras = []
    for k, cams in enumerate(sorted((scene64 / "Cams").glob("*.txt"))):
        w2c, K = _cams_file(cams)
        (root / "images" / f"{cams.stem}.png").symlink_to(scene64 / "Images" / f"{cams.stem}.png")
        m = np.linalg.inv(chunk) @ np.linalg.inv(w2c)
        cameras.append(f'<camera id="{k}" sensor_id="0" label="{cams.stem}"><transform>'
                       + " ".join(repr(float(v)) for v in m.ravel()) + "</transform></camera>")
    rot = " ".join(repr(float(v)) for v in (chunk[:3, :3] / 2).ravel())
    (root / "cameras.xml").write_text(
        '<?xml version="1.0"?><document version="2.0.0"><chunk><sensors><sensor id="0" type="frame">'
        f'<resolution width="64" height="64"/><calibration type="frame" class="adjusted"><f>{K[1, 1]!r}</f>'
        f"<cx>{K[0, 2] - 32!r}</cx><cy>{K[1, 2] - 32!r}</cy><b1>{K[0, 0] - K[1, 1]!r}</b1></calibration></sensor>"
        f"</sensors><cameras>{''.join(cameras)}</cameras><transform><rotation>{rot}</rotation>"
        "<translation>30 -12 5</translation><scale>2</scale></transform></chunk></document>")
    _imports_with_the_cams_files_cameras(root, scene64, fresh, "Metashape camera export")


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """The axis-angle vector of a rotation matrix (through its unit quaternion; no scipy in Blender)."""
    w = np.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if w < 0.5:  # near a half turn: the axis from the largest diagonal entry
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        q = np.empty(3)
        q[i] = np.sqrt(max(0.0, 1.0 + R[i, i] - R[j, j] - R[k, k])) / 2.0
        q[j], q[k] = (R[j, i] + R[i, j]) / (4 * q[i]), (R[k, i] + R[i, k]) / (4 * q[i])
        w = (R[k, j] - R[j, k]) / (4 * q[i])
        v = q * np.sign(w or 1.0)
        w = abs(w)
    else:
        v = v / (4 * w)
    s = np.linalg.norm(v)
    return np.zeros(3) if s < 1e-15 else v / s * 2.0 * np.arctan2(s, w)


@pytest.mark.parametrize("layout", ["bundler", "realitycapture", "opendronemap", "meshroom", "openmvg"])
def test_other_photogrammetry_exports_import_with_their_cameras(scene64, fresh, tmp_path, layout):
    """The generated scene as a Bundler file (OpenGL camera axes, list.txt), as RealityCapture's XMP
    sidecars (world-to-camera rotation, centre, 35 mm focal length), as an OpenDroneMap project
    (axis-angle poses, a normalised camera), as a Meshroom project (column-major world-to-camera
    rotations, centres, a focal length in mm) and as OpenMVG's sfm_data.json (row-major rotations,
    cereal's polymorphic intrinsic): every view object has the Cams file's camera."""
    root = tmp_path / layout
    (root / "images").mkdir(parents=True)
    num = lambda a: " ".join(repr(float(v)) for v in np.ravel(a))  # noqa: E731
    cams, names, shots, views, poses = [], [], {}, [], []
    for cams_file in sorted((scene64 / "Cams").glob("*.txt")):
        w2c, K = _cams_file(cams_file)
        vid = cams_file.stem
        (root / "images" / f"{vid}.png").symlink_to(scene64 / "Images" / f"{vid}.png")
        assert K[0, 0] == K[1, 1] and K[0, 2] == 32 and K[1, 2] == 32  # what both formats can say
        if layout == "bundler":
            flip = np.diag([1.0, -1.0, -1.0])
            cams.append(f"{K[0, 0]!r} 0 0\n" + "\n".join(num(r) for r in flip @ w2c[:3, :3]) + "\n"
                        + num(flip @ w2c[:3, 3]))
            names.append(f"images/{vid}.png")
        elif layout == "opendronemap":
            shots[f"{vid}.png"] = {"rotation": _rotation_vector(w2c[:3, :3]).tolist(),
                                   "translation": w2c[:3, 3].tolist(), "camera": "c"}
        elif layout == "meshroom":
            R = w2c[:3, :3]
            views.append({"viewId": vid, "poseId": vid, "intrinsicId": "0", "path": f"/shoot/{vid}.png"})
            poses.append({"poseId": vid, "pose": {"transform": {"rotation": [str(v) for v in R.T.ravel()],
                                                                "center": [str(v) for v in -R.T @ w2c[:3, 3]]}}})
        elif layout == "openmvg":
            k = len(views)
            view = {"local_path": "", "filename": f"{vid}.png", "width": 64, "height": 64, "id_view": k,
                    "id_intrinsic": 0, "id_pose": k}
            views.append({"key": k, "value": {"polymorphic_id": 0x40000000,
                                              "ptr_wrapper": {"id": 0x80000001 + k, "data": view}}})
            poses.append({"key": k, "value": {"rotation": w2c[:3, :3].tolist(),
                                              "center": (-w2c[:3, :3].T @ w2c[:3, 3]).tolist()}})
        else:
            R, C = w2c[:3, :3], -w2c[:3, :3].T @ w2c[:3, 3]
            (root / "images" / f"{vid}.xmp").write_text(
                '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
                '<rdf:Description xmlns:xcr="http://www.capturingreality.com/ns/xcr/1.1#" xcr:Coordinates="absolute" '
                f'xcr:DistortionModel="brown3" xcr:FocalLength35mm="{K[0, 0] / 64 * 36!r}">'
                f"<xcr:Rotation>{num(R)}</xcr:Rotation><xcr:Position>{num(C)}</xcr:Position>"
                "</rdf:Description></rdf:RDF></x:xmpmeta>")
    if layout == "bundler":
        (root / "bundle.out").write_text(f"# Bundle file v0.3\n{len(cams)} 0\n" + "\n".join(cams) + "\n")
        (root / "list.txt").write_text("\n".join(names) + "\n")
    if layout == "opendronemap":
        (root / "opensfm").mkdir()
        cam = {"projection_type": "perspective", "width": 64, "height": 64, "focal": K[0, 0] / 64}
        (root / "opensfm" / "reconstruction.json").write_text(json.dumps([{"cameras": {"c": cam}, "shots": shots}]))
    if layout == "meshroom":
        node = root / "MeshroomCache" / "StructureFromMotion" / "9d1e"
        node.mkdir(parents=True)
        intr = {"intrinsicId": "0", "width": "64", "height": "64", "sensorWidth": "6.4", "type": "pinhole",
                "distortionType": "none", "undistortionType": "none", "focalLength": str(K[0, 0] / 10),
                "pixelRatio": "1", "principalPoint": ["0", "0"], "distortionParams": ""}
        (node / "cameras.sfm").write_text(json.dumps({"version": ["1", "2", "11"], "views": views,
                                                      "intrinsics": [intr], "poses": poses}))
    if layout == "openmvg":
        lens = {"width": 64, "height": 64, "focal_length": K[0, 0], "principal_point": [32, 32]}
        intr = {"key": 0, "value": {"polymorphic_id": 0x80000001, "polymorphic_name": "pinhole",
                                    "ptr_wrapper": {"id": 0x80001000, "data": lens}}}
        (root / "reconstruction_global").mkdir()
        (root / "reconstruction_global" / "sfm_data.json").write_text(json.dumps({
            "sfm_data_version": "0.3", "root_path": "/elsewhere", "views": views, "intrinsics": [intr],
            "extrinsics": poses}))
    names = {"bundler": "Bundler file", "realitycapture": "RealityCapture sidecars", "meshroom": "Meshroom project",
             "opendronemap": "OpenDroneMap / OpenSfM reconstruction", "openmvg": "OpenMVG reconstruction"}
    _imports_with_the_cams_files_cameras(root, scene64, fresh, names[layout])


def test_photos_of_different_sizes_each_keep_their_camera(scene64, fresh, tmp_path):
    """A training photo cut to 64x48 and a held-out one to 48x64 among 64x64 photos: the render size is
    the scene camera's (the first training view) and each view object gives back its own camera."""
    import shutil

    from dibrgs_core.data.levir import read_cams_file, write_cams_file

    mixed = tmp_path / "mixed"
    shutil.copytree(scene64, mixed)
    cut = {"008": (0, 8, 64, 48), "004": (8, 0, 48, 64)}
    for vid, (x0, y0, w, h) in cut.items():
        c = read_cams_file(mixed / "Cams" / f"{vid}.txt", size=(64, 64))
        c.K[0, 2] -= x0
        c.K[1, 2] -= y0
        write_cams_file(mixed / "Cams" / f"{vid}.txt", c)
        img = bpy.data.images.new(f"cut_{vid}", w, h)  # Blender writes the PNG: no Pillow in its Python
        img.filepath_raw, img.file_format = str(mixed / "Images" / f"{vid}.png"), "PNG"
        img.save()
        bpy.data.images.remove(img)
    assert bpy.ops.dibrgs.import_scene(directory=str(mixed)) == {"FINISHED"}
    sb = _mod("scene_build")
    r = fresh.render
    assert fresh.camera["dibrgs_view"] == "001" and (r.resolution_x, r.resolution_y) == (64, 64)
    for vid, obj in _view_objects().items():
        want = read_cams_file(mixed / "Cams" / f"{vid}.txt", size=cut.get(vid, (0, 0, 64, 64))[2:])
        cam = sb.camera_from_object(obj, fresh)
        assert (cam.width, cam.height) == (want.width, want.height), vid
        np.testing.assert_allclose(cam.K, want.K, rtol=1e-5, atol=1e-5)
    held = {c.name: (c.width, c.height) for c in sb.described_cameras(sb.scene_description(), "test")}
    assert held["004"] == (48, 64) and held["005"] == (64, 64)


def test_a_far_scene_lives_near_blenders_origin_and_goes_back_in_its_own_frame(scene64, fresh, tmp_path):
    """A scene 1e7 off its coordinate origin (georeferenced) is imported relative to a point near
    its cameras (float32 would round its positions by a unit): camera objects as precise as in
    place; cameras written for the command line are in the files' frame again; the run's points
    (relative to the same point) land at Blender's origin."""
    import json
    import shutil

    from dibrgs_core.bridge.path import write_camera_list
    from dibrgs_core.data.levir import read_cameras, read_cams_file, write_cams_file

    far = tmp_path / "far"
    shutil.copytree(scene64, far)
    offset = np.array([1.0e7, -4.0e6, 2.5e5])
    for f in (far / "Cams").glob("*.txt"):  # the size given: Blender's Python has no Pillow to read it
        write_cams_file(f, read_cams_file(f, size=(64, 64)).translated(offset))
    assert bpy.ops.dibrgs.import_scene(directory=str(far)) == {"FINISHED"}
    sb, results = _mod("scene_build"), _mod("results")
    origin = np.array(sb.scene_origin())
    assert np.linalg.norm(origin - offset) < 1e3  # a rounded point near the cameras
    objs = _view_objects()
    for vid, obj in objs.items():
        file_cam = read_cams_file(far / "Cams" / f"{vid}.txt", size=(64, 64))
        cam = sb.camera_from_object(obj, fresh)
        local = file_cam.center - origin
        np.testing.assert_allclose(cam.center, local, atol=1e-5 * np.abs(local).max())
        np.testing.assert_allclose(cam.R, file_cam.R, atol=1e-5)
    cams = [sb.camera_from_object(o, fresh) for o in objs.values()]
    back = read_cameras(write_camera_list(tmp_path / "cams.json", cams, sb.scene_description()["origin"]))
    for c, b in zip(cams, back):
        np.testing.assert_allclose(b.center, c.center + origin, rtol=0, atol=1e-3)
    init = tmp_path / "init"
    init.mkdir()
    (init / "points.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                                     "property float z\nend_header\n0.5 -0.25 1.0\n")
    (init / "init_report.json").write_text(json.dumps({"decisions": [], "values": {"scene_origin": origin.tolist()}}))
    results.load_init(bpy.context, init)
    np.testing.assert_allclose(sb.dense_points(), [[0.5, -0.25, 1.0]], atol=1e-6)


def test_import_and_results_need_no_torch_pil_or_pycolmap(scene64, tmp_path):
    """Scene import (LEVIR and COLMAP), path, compositor and initialisation outputs in a Python
    whose imports of torch, Pillow, pycolmap, scipy, ... fail, as in Blender's."""
    from dibrgs_core.geometry.height_map import HeightMap

    init = tmp_path / "init"
    init.mkdir()
    pts = np.random.default_rng(1).normal(size=(50, 3))
    ply = ["ply", "format ascii 1.0", f"element vertex {len(pts)}", "property float x", "property float y",
           "property float z", "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    ply += [f"{x:.6f} {y:.6f} {z:.6f} {10 * k % 255} 120 30" for k, (x, y, z) in enumerate(pts)]
    (init / "points.ply").write_text("\n".join(ply) + "\n")
    HeightMap(up_frame=np.eye(3), origin=np.zeros(3), cell=1.0, x0=-2.0, y0=-2.0,
              bounds=np.arange(16, dtype=float).reshape(4, 4)).save(init / "height_map.npz")
    colmap = Path(os.environ.get("DIBRGS_SHARED", REPO.parent / "shared")) / "data" / "brighton_north"
    out = tmp_path / "out.json"
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(_NO_TORCH_DRIVER), ",".join(BLOCKED), str(REPO),
                        str(scene64), str(colmap) if colmap.is_dir() else "", str(init), str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and out.exists(), r.stdout[-3000:] + r.stderr[-3000:]
    res = json.loads(out.read_text())
    assert res["attempts"] == [] and res["loaded"] == [], res
    assert res["levir_views"] == 21 and res["pseudo"] == 8 and res["wired"] == "heldout_003"
    assert res["points"] == 50 and res["height_map"]
    if colmap.is_dir():
        assert res["colmap_views"] == 9


# ---------------------------------------------------------------------------
# compositor: the result reaches the render, colour-managed, idempotent
# ---------------------------------------------------------------------------
def _tree_state(scene) -> tuple:
    api = _mod("_core").compositor.compositor_api(bpy.app.version)
    tree = scene.compositing_node_group if api.node_group else scene.node_tree
    nodes = sorted((n.name, n.bl_idname, getattr(n, "is_active_output", None)) for n in tree.nodes)
    links = sorted((lk.from_node.name, lk.from_socket.identifier, lk.to_node.name, lk.to_socket.identifier)
                   for lk in tree.links)
    sockets = len(tree.interface.items_tree) if api.node_group else 0
    return nodes, links, sockets


def _render(scene, path: Path) -> np.ndarray:
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 1
    s = scene.render.image_settings
    s.file_format, s.color_mode, s.color_depth = "PNG", "RGB", "8"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return _pixels(path)


def _load_results(scene64, scene) -> list[str]:
    results = _mod("results")
    names = results.load_renders(scene, scene64 / "Images", ["002", "003", "004"], "heldout")
    results.show_all(scene, names[1])
    return names


def test_compositor_render_equals_the_result_png(scene64, fresh, tmp_path):
    comp = _mod("compositor")
    bpy.ops.dibrgs.import_scene(directory=str(scene64))
    assert fresh.view_settings.view_transform == "AgX"  # Blender's default, which would shift the tones
    names = _load_results(scene64, fresh)
    assert comp.wired_image(fresh) == "heldout_003"
    assert fresh.view_settings.view_transform == "Standard"
    got = _render(fresh, tmp_path / "render.png")
    want = _pixels(scene64 / "Images" / "003.png")
    assert np.abs(got - want).max() <= 1  # within 1/255 (the render's dither)
    # Idempotent: showing, selecting the same result again adds or changes nothing.
    state = _tree_state(fresh)
    _load_results(scene64, fresh)
    comp.select(fresh, "heldout_003")
    assert _tree_state(fresh) == state
    # The panel's view switch rewires the output (and only that).
    fresh.dibrgs.result_view = names[2]
    assert comp.wired_image(fresh) == names[2]
    nodes, links, sockets = _tree_state(fresh)
    assert nodes == state[0] and len(links) == len(state[1]) and sockets == state[2]
    assert np.abs(_render(fresh, tmp_path / "render4.png") - _pixels(scene64 / "Images" / "004.png")).max() <= 1


def test_compositor_takes_over_the_active_output_of_an_existing_tree(scene64, fresh, tmp_path):
    """A scene that already composites (Render Layers -> output): the result reaches the render."""
    comp = _mod("compositor")
    bpy.ops.dibrgs.import_scene(directory=str(scene64))
    if bpy.app.version >= (5, 0, 0):
        tree = bpy.data.node_groups.new("My compositing", "CompositorNodeTree")
        tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        fresh.compositing_node_group = tree
        rl, out = tree.nodes.new("CompositorNodeRLayers"), tree.nodes.new("NodeGroupOutput")
        tree.links.new(rl.outputs["Image"], out.inputs[0])
        spare = tree.nodes.new("NodeGroupOutput")  # a second, inactive output
        assert out.is_active_output and not spare.is_active_output
        outputs = lambda: [n for n in tree.nodes if n.bl_idname == "NodeGroupOutput"]  # noqa: E731
    else:
        fresh.use_nodes = True  # Blender's default tree: Render Layers -> Composite
        tree = fresh.node_tree
        tree.nodes.new("CompositorNodeComposite")  # a second Composite: the render uses the active one
        outputs = lambda: [n for n in tree.nodes if n.bl_idname == "CompositorNodeComposite"]  # noqa: E731
    n_out = len(outputs())
    _load_results(scene64, fresh)
    assert len(outputs()) == n_out  # no output node added
    assert "CompositorNodeRLayers" in {n.bl_idname for n in tree.nodes}  # the user's nodes stay
    assert comp.wired_images(fresh) == ["heldout_003"] * (1 if bpy.app.version >= (5, 0, 0) else n_out)
    if bpy.app.version >= (5, 0, 0):
        assert out.is_active_output and out.inputs[0].links[0].from_node.image.name == "heldout_003"
    state = _tree_state(fresh)
    _load_results(scene64, fresh)
    assert _tree_state(fresh) == state
    got = _render(fresh, tmp_path / "render.png")
    assert np.abs(got - _pixels(scene64 / "Images" / "003.png")).max() <= 1


# ---------------------------------------------------------------------------
# poll() with reasons, and job state that never comes from a file
# ---------------------------------------------------------------------------
def _why(action: str) -> str | None:
    return _mod("operators").why_not(bpy.context, action)


def test_every_operator_polls_with_a_reason(scene64, fresh, tmp_path, monkeypatch):
    ops = _mod("operators")
    for name in ("initialise", "train", "results", "flythrough", "render_active_camera", "reset_path"):
        assert not getattr(bpy.ops.dibrgs, name).poll(), name
        assert _why(name) == "import a scene first"
    assert _why("cancel") == "nothing is running" and not bpy.ops.dibrgs.cancel.poll()
    with pytest.raises(RuntimeError, match="nothing is running"):
        bpy.ops.dibrgs.cancel()
    assert bpy.ops.dibrgs.import_scene.poll()
    bpy.ops.dibrgs.import_scene(directory=str(scene64))
    monkeypatch.setenv("DIBRGS_PYTHON", str(tmp_path / "no-such-python"))
    assert "no-such-python not found" in _why("train") and "Preferences" in _why("train")
    with pytest.raises(RuntimeError, match="no-such-python not found"):
        bpy.ops.dibrgs.initialise(blocking=True)
    monkeypatch.setenv("DIBRGS_PYTHON", sys.executable)
    assert _why("initialise") is None and _why("train") is None and _why("reset_path") is None
    work = Path(fresh.dibrgs.work_dir)
    for action in ("results", "flythrough", "render_active_camera"):
        assert _why(action) == f"no trained model in {work}: train first"
    work.mkdir(parents=True)
    (work / "checkpoint.pt").write_bytes(b"")  # an interrupted run: no model.pt, which render loads
    assert "stopped before the end: train with Resume" in _why("results")
    with pytest.raises(RuntimeError, match="stopped before the end"):
        bpy.ops.dibrgs.results(blocking=True)
    (work / "model.pt").write_bytes(b"")
    assert _why("results") is None and _why("flythrough") is None and _why("render_active_camera") is None
    fresh.camera = None
    assert _why("render_active_camera") == "no camera: make a camera active or set the scene camera"
    # A run folder that cannot be written: an error, and no half-started job locking the panel.
    (tmp_path / "a_file").write_text("not a folder")
    fresh.dibrgs.work_dir = str(tmp_path / "a_file" / "work")
    with pytest.raises(RuntimeError, match="Initialise: cannot start"):
        bpy.ops.dibrgs.initialise(blocking=True)
    assert ops.running_job() is None and bpy.ops.dibrgs.initialise.poll()


def _sleeping_job(ops, tmp_path, label="Training"):
    """A real subprocess job started the way the panel starts one, without waiting for it."""
    jobs = _mod("_core").jobs
    marker = tmp_path / "stopped"
    code = ("import signal, sys, time\n"
            f"signal.signal(signal.SIGINT, lambda *a: (open({str(marker)!r}, 'w').write('SIGINT'), sys.exit(130)))\n"
            "print('handler' + ' set', flush=True)\n"
            "time.sleep(120)")
    log = tmp_path / "sleep.log"
    runner = jobs.JobRunner([jobs.Step(label, [sys.executable, "-c", code], log)])
    job = ops.Job(label, runner, finish=lambda ctx: "done", scene_name=bpy.context.scene.name)
    ops._active = job
    runner.start()
    t0 = time.monotonic()
    while "handler set" not in log.read_text() and time.monotonic() - t0 < 30:  # its SIGINT handler is set
        runner.poll()
        time.sleep(0.05)
    return job, marker


def test_a_saved_file_never_brings_a_job_back(scene64, fresh, tmp_path, monkeypatch):
    ops = _mod("operators")
    monkeypatch.setenv("DIBRGS_PYTHON", sys.executable)
    bpy.ops.dibrgs.import_scene(directory=str(scene64))
    job, marker = _sleeping_job(ops, tmp_path)
    try:
        assert ops.running_job() is job
        assert _why("train") == "Training is running: wait for it or cancel it"
        assert bpy.ops.dibrgs.cancel.poll() and not bpy.ops.dibrgs.train.poll()
        assert not bpy.ops.dibrgs.import_scene.poll()  # the scene it runs on stays
        fresh.dibrgs["job_running"] = True  # what earlier versions saved with the file
        blend = tmp_path / "during_training.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(blend))
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        # Opening a file stops the job (its results belong to the file it was started from) ...
        assert job.detached and ops.running_job() is None
        assert job.runner.wait(timeout_s=60) == "cancelled" and marker.read_text() == "SIGINT"
        # ... and the file brings no job back: Train is available, Cancel is not.
        scene = bpy.context.scene
        assert "job_running" not in scene.dibrgs
        assert bpy.ops.dibrgs.train.poll() and not bpy.ops.dibrgs.cancel.poll()
        assert _why("cancel") == "nothing is running"
    finally:
        if not job.runner.finished:
            job.runner.cancel(grace_s=0.0)
            job.runner.wait()
        ops._active = None


def test_set_up_check_reports_a_python_that_cannot_train(scene64, fresh, tmp_path, monkeypatch):
    """Set up / Check in a Python without torch (Blender's own, or one that blocks it)."""
    block = tmp_path / "block"
    block.mkdir()
    (block / "sitecustomize.py").write_text(
        "import sys\nclass B:\n    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'torch':\n            raise ModuleNotFoundError('No module named torch')\n"
        "sys.meta_path.insert(0, B())\n")
    monkeypatch.setenv("PYTHONPATH", str(block))
    monkeypatch.setenv("DIBRGS_PYTHON", sys.executable)
    setup = _mod("setup")
    try:
        with pytest.raises(RuntimeError, match="not ready: torch"):
            bpy.ops.dibrgs.setup_check(blocking=True)
        run = setup.latest(sys.executable)
        items = {i.name: i for i in run.report.items}
        assert not items["torch"].ok and items["torch"].fix == f"{sys.executable} -m pip install torch==2.13.0"
        assert items["numpy"].ok and items["rasterizer"].detail == "needs torch"
        problem = setup.python_problem(bpy.context)
        assert problem.startswith("the training Python lacks torch, ") and "rasterizer" in problem
        assert problem.endswith("press Set up / Check again (Edit > Preferences > Add-ons > DIBR-GS)")
        bpy.ops.dibrgs.import_scene(directory=str(scene64))
        assert _why("initialise") == _why("train") == problem  # the panel says why training is off
    finally:
        setup._runs.pop(sys.executable, None)  # this interpreter is fine outside this test


def test_a_background_job_loads_its_results_into_the_scene_it_started_from(scene64, fresh, tmp_path):
    """What the application timer does interactively (background mode runs no timers: tick by hand)."""
    ops = _mod("operators")
    jobs = _mod("_core").jobs
    bpy.ops.dibrgs.import_scene(directory=str(scene64))
    started = fresh.name
    runner = jobs.JobRunner([jobs.Step("Render camera", [sys.executable, "-c", "print('rendered')"],
                                       tmp_path / "r.log")])
    job = ops.Job("Render camera", runner, finish=lambda ctx: f"loaded into {ctx.scene.name}", scene_name=started)
    ops._active = job
    runner.start()
    other = bpy.data.scenes.new("Another scene")
    with bpy.context.temp_override(scene=other):  # the user looks at another scene meanwhile
        t0 = time.monotonic()
        while ops._tick() is not None and time.monotonic() - t0 < 60:
            assert ops.running_job() is job
            time.sleep(0.05)
    assert ops.running_job() is None and ops._active is None
    assert bpy.data.scenes[started].dibrgs.message == f"loaded into {started}"
    assert other.dibrgs.message == ""
