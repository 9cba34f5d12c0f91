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

from dibrgs_core.camera.blender import to_blender  # noqa: E402
from dibrgs_core.data.levir import read_cams_file, read_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


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
    assert _mod("_core").pinhole.__name__ == "dibrgs_ext.dibrgs_core.camera.pinhole"


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
        from dibrgs_core.geometry.height_map import HeightMap

        hm = HeightMap.load(work / "init" / "height_map.npz")
        grid = bpy.data.objects[sb.HEIGHT_NAME].data
        assert len(grid.vertices) == int(np.isfinite(hm.bounds).sum())
        gv = np.array([v.co[:] for v in grid.vertices])
        np.testing.assert_allclose(hm.bound_at(gv), ((gv - hm.origin) @ hm.up_frame.T)[:, 2], atol=1e-3)
    else:
        assert sb.HEIGHT_NAME not in bpy.data.objects


# ---------------------------------------------------------------------------
# End to end through the real `dibrgs train/render/eval` subprocesses (--preset test)
# ---------------------------------------------------------------------------
@pytest.mark.slow
def test_train_operator_completes_and_fills_the_compositor(tiny_scene, fresh):
    from dibrgs_core.bridge.compositor import IMAGE_NODE_PREFIX, OUTPUT_NODE, VIEWER_NODE
    from dibrgs_core.camera.serialize import camera_from_dict
    import json

    bpy.ops.dibrgs.import_scene(directory=str(tiny_scene))
    props = fresh.dibrgs
    # The test preset with few iterations: this checks the plumbing, not the quality.
    props.preset, props.iterations, props.pseudo_count = "test", 20, 4
    sb, comp = _mod("scene_build"), _mod("compositor")
    expected_pseudo = sb.path_cameras(bpy.context, 4, "pseudo")
    assert bpy.ops.dibrgs.train(blocking=True) == {"FINISHED"}, props.error
    work = Path(props.work_dir)
    assert (work / "checkpoint.pt").is_file()
    assert props.job_fraction == 1.0 and not props.job_running
    # Training got the path as it was when it started.
    sent = [camera_from_dict(d) for d in json.loads((work / "blender" / "pseudo_path.json").read_text())]
    assert len(sent) == 4
    for a, b in zip(sent, expected_pseudo):
        np.testing.assert_allclose(a.w2c, b.w2c, atol=1e-9)
    # Blender 5.0: the compositor is a node group on the scene with a Group Output.
    tree = fresh.compositing_node_group
    assert tree is not None and tree.bl_idname == "CompositorNodeTree"
    image_nodes = [n for n in tree.nodes if n.name.startswith(IMAGE_NODE_PREFIX)]
    ref = read_scene(tiny_scene, load_depth=False)
    assert len(image_nodes) == len(ref.test) + 4
    for n in image_nodes:
        assert n.bl_idname == "CompositorNodeImage" and n.image is not None
        assert tuple(n.image.size) == ref.resolution and n.image.has_data
        px = np.array(n.image.pixels[:]).reshape(-1, 4)[:, :3]
        assert np.isfinite(px).all() and px.std() > 0  # a rendered image, not a blank
    assert tree.nodes[OUTPUT_NODE].bl_idname == "NodeGroupOutput"
    assert tree.nodes[VIEWER_NODE].bl_idname == "CompositorNodeViewer"
    first = f"heldout_{ref.test[0]}"
    assert comp.wired_image(fresh) == first
    assert tree.nodes[VIEWER_NODE].inputs["Image"].links[0].from_node.image.name == first
    props.result_view = "pseudo_002"  # the panel's view switch rewires output and Viewer
    assert comp.wired_image(fresh) == "pseudo_002"
    assert tree.nodes[VIEWER_NODE].inputs["Image"].links[0].from_node.image.name == "pseudo_002"
    metrics = {m.name: m.value for m in props.metrics}
    assert any("psnr" in k.lower() for k in metrics), metrics
    assert all(np.isfinite(v) for v in metrics.values())

    # Render a camera the user placed, into the compositor too.
    cam_obj = sb.new_camera_object("MyShot", fresh.collection)
    src = bpy.data.objects[ref.test[2]]
    for attr in ("lens", "sensor_width", "sensor_height", "shift_x", "shift_y", "clip_start", "clip_end"):
        setattr(cam_obj.data, attr, getattr(src.data, attr))
    cam_obj.matrix_world = src.matrix_world
    bpy.context.view_layer.objects.active = cam_obj
    assert bpy.ops.dibrgs.render_active_camera(blocking=True) == {"FINISHED"}, props.error
    assert comp.wired_image(fresh) == "active_MyShot"
    mine = np.array(bpy.data.images["active_MyShot"].pixels[:])
    same_view = np.array(bpy.data.images[f"heldout_{ref.test[2]}"].pixels[:])
    np.testing.assert_allclose(mine, same_view, atol=2 / 255)  # same pose -> same render

    # Fly-through: an image sequence and a camera animated frame by frame along the path.
    props.fly_frames = 3
    expected_fly = sb.path_cameras(bpy.context, 3, "fly")
    assert bpy.ops.dibrgs.flythrough(blocking=True) == {"FINISHED"}, props.error
    fly = bpy.data.objects[sb.FLY_NAME]
    assert (fresh.frame_start, fresh.frame_end) == (1, 3)
    for f, cam in enumerate(expected_fly, start=1):
        fresh.frame_set(f)
        want = to_blender(cam).matrix_world
        np.testing.assert_allclose(np.array(fly.matrix_world), want, atol=1e-4 * max(1.0, np.abs(want).max()))
        assert (work / "blender" / "renders" / "flythrough" / f"fly_{f:04d}.png").is_file()
    seq = bpy.data.images["flythrough"]
    assert seq.source == "SEQUENCE" and fly.data.background_images[0].image == seq


def test_failing_training_is_reported_with_its_log(tiny_scene, fresh, tmp_path):
    broken = tmp_path / "broken_scene"
    shutil.copytree(tiny_scene, broken)
    bpy.ops.dibrgs.import_scene(directory=str(broken))
    (broken / "Images" / "001.png").unlink()  # `dibrgs train` now rejects the folder
    fresh.dibrgs.preset = "test"
    with pytest.raises(RuntimeError, match=r"Training failed \(exit code \d+\); log: "):
        bpy.ops.dibrgs.train(blocking=True)
    err = fresh.dibrgs.error
    log = Path(err.split("log: ", 1)[1].splitlines()[0])
    assert log.is_file() and "001" in log.read_text()
    assert "001" in err  # the subprocess's own message is shown too
    assert not fresh.dibrgs.job_running


@pytest.mark.slow
def test_batch_mode_writes_the_blend_and_the_renders(tiny_scene, fresh, tmp_path):
    out = tmp_path / "batch"
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "run.py"), "--scene", str(tiny_scene), "--out",
                        str(out), "--preset", "test", "--iterations", "20", "--pseudo-views", "3"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    blend = out / "dibrgs.blend"
    assert blend.is_file() and (out / "checkpoint.pt").is_file()
    ref = read_scene(tiny_scene, load_depth=False)
    for vid in ref.test:
        assert (out / "blender" / "renders" / "heldout" / f"{vid}.png").is_file()
    assert len(list((out / "blender" / "renders" / "pseudo").glob("pseudo_*.png"))) == 3
    # The saved file has everything set up.
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    sb = _mod("scene_build")
    scene = bpy.context.scene
    assert set(_view_objects()) == set(ref.views)
    assert sb.POINTS_NAME in bpy.data.objects and sb.PATH_NAME in bpy.data.objects
    tree = scene.compositing_node_group
    assert tree is not None and sum(n.bl_idname == "CompositorNodeImage" for n in tree.nodes) == len(ref.test) + 3
    assert len(scene.dibrgs.metrics) > 0


def test_batch_mode_rejects_bad_arguments(tmp_path):
    run = [sys.executable, str(REPO / "scripts" / "run.py")]
    for args in ([], ["--scene", str(tmp_path / "missing"), "--out", str(tmp_path / "o")],
                 ["--scene", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "fast"]):
        r = subprocess.run(run + args, capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and "usage:" in r.stderr, (args, r.stderr)
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_cancel_stops_real_training_and_keeps_a_checkpoint(tiny_scene, tmp_path):
    """What the panel's Cancel does (JobRunner.cancel), on the real `dibrgs train` subprocess."""
    from dibrgs_core.bridge import jobs

    work = tmp_path / "work"
    cmd = jobs.train_command(sys.executable, tiny_scene, work, jobs.TrainOptions(preset="test", iterations=100000))
    r = jobs.JobRunner([jobs.Step("Training", cmd, tmp_path / "train.log", progress=True)]).start()
    import time

    t0 = time.monotonic()
    while r.progress.iteration == 0 and not r.finished and time.monotonic() - t0 < 300:
        r.poll()
        time.sleep(0.2)
    assert r.progress.iteration > 0 and r.progress.total == 100000, (tmp_path / "train.log").read_text()[-2000:]
    r.cancel(grace_s=120)
    assert r.wait(interval_s=0.2, timeout_s=300) == "cancelled"
    assert (work / "checkpoint.pt").is_file()  # stopped cleanly, not killed
    assert r.progress.iteration < 100000
