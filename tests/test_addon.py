"""The Blender add-on with the real bpy module, headless.

The repository is loaded the way Blender loads the extension: as a package
(here named ``dibrgs_ext``) whose ``__init__`` hands off to ``addon/``, so the
add-on resolves ``dibrgs_ext.dibrgs_core`` exactly as it resolves the bundled
copy in Blender (see ``addon/_core.py``). Every subprocess is the real
``dibrgs`` command.
"""
from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from dibrgs_core.cameras import to_blender  # noqa: E402
from dibrgs_core.io_levir import read_cams_file, read_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ext():
    """The repository as an extension package, registered."""
    name = "dibrgs_ext"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "__init__.py",
                                                      submodule_search_locations=[str(REPO)])
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    mod = sys.modules[name]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    mod.register()
    yield mod
    mod.unregister()


@pytest.fixture
def fresh(ext, tmp_path):
    """An empty scene whose run folder is in tmp_path."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.dibrgs.work_dir = str(tmp_path / "work")
    return scene


def _mod(name: str):
    return sys.modules[f"dibrgs_ext.addon.{name}"]


def _view_objects() -> dict[str, bpy.types.Object]:
    return {o["dibrgs_view"]: o for o in bpy.data.objects if "dibrgs_view" in o}


def _datablock_counts() -> dict[str, int]:
    return {k: len(getattr(bpy.data, k)) for k in ("objects", "collections", "cameras", "images", "texts",
                                                   "curves", "node_groups")}


def test_register_unregister_twice(ext):
    for _ in range(2):
        ext.unregister()
        assert not hasattr(bpy.types.Scene, "dibrgs")
        assert not hasattr(bpy.types, "DIBRGS_PT_main")
        ext.register()
        assert hasattr(bpy.types.Scene, "dibrgs")
        assert bpy.types.DIBRGS_PT_main.bl_category == "DIBR-GS"
        assert bpy.types.DIBRGS_PT_main.bl_region_type == "UI"
        assert bpy.ops.dibrgs.train.idname() == "DIBRGS_OT_train"
    # The add-on resolved the extension's own dibrgs_core, not the top-level one.
    assert _mod("_core").CORE_PACKAGE == "dibrgs_ext.dibrgs_core"
    assert _mod("_core").cameras.__name__ == "dibrgs_ext.dibrgs_core.cameras"


def test_import_scene_reproduces_every_camera(tiny_scene, fresh):
    assert bpy.ops.dibrgs.import_scene(directory=str(tiny_scene)) == {"FINISHED"}
    sb = _mod("scene_build")
    ref = read_scene(tiny_scene, load_depth=False)
    objs = _view_objects()
    assert set(objs) == set(ref.views)
    r = fresh.render
    W, H = ref.resolution
    assert (r.resolution_x, r.resolution_y, r.resolution_percentage) == (W, H, 100)
    scale = max(np.abs(c.center).max() for c in ref.cameras)
    for vid, obj in objs.items():
        assert obj.name == vid and obj.type == "CAMERA"
        split = "train" if vid in ref.train else "test" if vid in ref.test else "other"
        assert obj.users_collection[0].name == sb.SPLIT_COLLECTIONS[split]
        cam = sb.camera_from_object(obj, fresh)  # through cameras.from_blender on the bpy data
        want = read_cams_file(tiny_scene / "Cams" / f"{vid}.txt", size=(W, H))
        assert (cam.width, cam.height) == (want.width, want.height)
        np.testing.assert_allclose(cam.K, want.K, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(cam.R, want.R, atol=1e-5)
        # Blender stores matrices in float32: positions are exact to 1e-5 of the scene's extent.
        np.testing.assert_allclose(cam.center, want.center, atol=1e-5 * scale)
        bgs = obj.data.background_images
        if split == "train":
            assert obj.data.show_background_images and len(bgs) == 1
            assert Path(bpy.path.abspath(bgs[0].image.filepath)).resolve() == (tiny_scene / "Images" / f"{vid}.png").resolve()
            assert tuple(bgs[0].image.size) == (W, H)
        else:
            assert len(bgs) == 0
    assert fresh.camera == objs[ref.train[0]]
    props = fresh.dibrgs
    assert props.path_curve is not None and props.path_curve.type == "CURVE"
    assert props.path_target is not None


def test_wrong_folder_reports_an_error_and_creates_nothing(fresh, tmp_path):
    junk = tmp_path / "not_a_scene"
    (junk / "photos").mkdir(parents=True)
    (junk / "photos" / "a.png").write_bytes(b"not an image")
    before = _datablock_counts()
    with pytest.raises(RuntimeError, match="Cannot import .*not_a_scene"):
        bpy.ops.dibrgs.import_scene(directory=str(junk))
    assert "not a scene" in fresh.dibrgs.error
    with pytest.raises(RuntimeError, match="not a folder"):
        bpy.ops.dibrgs.import_scene(directory=str(tmp_path / "missing"))
    assert _datablock_counts() == before


def test_editing_the_curve_moves_the_pseudo_views(tiny_scene, fresh):
    bpy.ops.dibrgs.import_scene(directory=str(tiny_scene))
    sb = _mod("scene_build")
    props = fresh.dibrgs
    n = 16
    before = sb.path_cameras(bpy.context, n, "pseudo")
    # The sampled path starts on the fitted orbit: samples are on the orbit's circle.
    orbit = sb.fit_orbit(sb.scene_description())
    radii = [np.linalg.norm(c.center - orbit.center) for c in before]
    np.testing.assert_allclose(radii, orbit.radius, rtol=1e-3)
    # Lift control point 0 (where sample 0 sits) along the scene up axis.
    up = np.array(props.scene_up)
    bp = props.path_curve.data.splines[0].bezier_points[0]
    lift = 0.3 * orbit.radius
    for attr in ("co", "handle_left", "handle_right"):
        setattr(bp, attr, np.array(getattr(bp, attr)) + lift * up)
    after = sb.path_cameras(bpy.context, n, "pseudo")
    moved = np.array([np.linalg.norm(a.center - b.center) for a, b in zip(after, before)])
    assert moved[0] > 0.5 * lift  # the sample at the edited point follows it up
    assert (after[0].center - before[0].center) @ up > 0.5 * lift
    # The far side of the path is unchanged: its samples only slide along the old circle
    # (arc-length spacing redistributes them), they do not rise.
    far = after[n // 2].center
    assert abs((far - before[n // 2].center) @ up) < 1e-3 * lift
    assert abs(np.linalg.norm(far - orbit.center) - orbit.radius) < 1e-3 * orbit.radius
    # Moving the look-at Empty turns the cameras towards it.
    props.path_target.location = np.array(props.path_target.location) + [0.2 * orbit.radius, 0, 0]
    bpy.context.view_layer.update()
    turned = sb.path_cameras(bpy.context, n, "pseudo")
    tgt = np.array(props.path_target.location)
    uv, z = turned[3].project(tgt[None])
    np.testing.assert_allclose(uv[0], [turned[3].cx, turned[3].cy], atol=1e-6)


def test_initialise_imports_points_height_map_and_decisions(tiny_scene, fresh):
    bpy.ops.dibrgs.import_scene(directory=str(tiny_scene))
    assert bpy.ops.dibrgs.initialise(blocking=True) == {"FINISHED"}
    sb = _mod("scene_build")
    work = Path(fresh.dibrgs.work_dir)
    import trimesh

    ply = trimesh.load(work / "init" / "points.ply")
    pts = bpy.data.objects[sb.POINTS_NAME]
    me = pts.data
    assert len(me.vertices) == len(ply.vertices) > 0 and len(me.polygons) == 0
    co = np.array([v.co[:] for v in me.vertices])
    np.testing.assert_allclose(co, ply.vertices, rtol=1e-6, atol=1e-4)
    col = me.color_attributes[0]
    assert col.domain == "POINT"
    rgb = np.array([c.color[:3] for c in col.data])
    assert rgb.std() > 0.01  # the scene's colours, not a constant
    import json

    rep = json.loads((work / "init" / "init_report.json").read_text())
    panel = [(d.stage, d.step, d.applied, d.reason) for d in fresh.dibrgs.decisions]
    assert panel == [(d["stage"], d["step"], d["applied"], d["reason"]) for d in rep["decisions"]]
    if (work / "init" / "height_map.npz").exists():
        from dibrgs_core.height_map import HeightMap

        hm = HeightMap.load(work / "init" / "height_map.npz")
        grid = bpy.data.objects[sb.HEIGHT_NAME].data
        assert len(grid.vertices) == int(np.isfinite(hm.bounds).sum())
        gv = np.array([v.co[:] for v in grid.vertices])
        np.testing.assert_allclose(hm.bound_at(gv), ((gv - hm.origin) @ hm.up_frame.T)[:, 2], atol=1e-3)
    else:
        assert sb.HEIGHT_NAME not in bpy.data.objects
