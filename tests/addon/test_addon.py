"""The add-on end to end with the training interpreter (bpy 5.0.1 and torch): real `dibrgs` subprocesses.

* The extension is built with Blender's own extension tool, installed with
  ``bpy.ops.extensions.package_install_files`` into a throw-away user folder and enabled;
  the whole workflow is then driven through ``bpy.ops`` in that Blender (one subprocess,
  :func:`_installed_workflow`), including the batch entry that ships inside the extension.
* Batch mode from the checkout (``scripts/run.py``): bad arguments, SIGINT and SIGTERM.
* The initialise operator and a failing training, in this process (the repository loaded
  as an extension package, like ``tests/addon/test_blender_addon.py``).

Tests without torch (import, cameras, compositor, polls) are in ``tests/addon/test_blender_addon.py``.
"""
from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

REPO = Path(__file__).resolve().parents[2]


def _mod(name: str):
    return sys.modules[f"dibrgs_ext.addon.{name}"]


def test_initialise_imports_points_height_map_and_decisions(tiny_scene, fresh):
    bpy.ops.dibrgs.import_scene(directory=str(tiny_scene))
    assert bpy.ops.dibrgs.initialise(blocking=True) == {"FINISHED"}
    sb = _mod("scene_build")
    work = Path(fresh.dibrgs.work_dir)
    import trimesh

    ply = trimesh.load(work / "init" / "points.ply")
    me = bpy.data.objects[sb.POINTS_NAME].data
    assert len(me.vertices) == len(ply.vertices) > 0 and len(me.polygons) == 0
    co = np.array([v.co[:] for v in me.vertices])
    np.testing.assert_allclose(co, ply.vertices, rtol=1e-6, atol=1e-4)
    col = me.color_attributes[0]
    assert col.domain == "POINT"
    assert np.array([c.color[:3] for c in col.data]).std() > 0.01  # the scene's colours, not a constant
    rep = json.loads((work / "init" / "init_report.json").read_text())
    panel = [(d.stage, d.step, d.applied, d.reason) for d in fresh.dibrgs.decisions]
    assert panel == [(d["stage"], d["step"], d["applied"], d["reason"]) for d in rep["decisions"]]
    if (work / "init" / "height_map.npz").exists():
        from dibrgs_core.geometry.height_map import HeightMap

        hm = HeightMap.load(work / "init" / "height_map.npz")
        gv = np.array([v.co[:] for v in bpy.data.objects[sb.HEIGHT_NAME].data.vertices])
        assert len(gv) == int(np.isfinite(hm.bounds).sum())
        np.testing.assert_allclose(hm.bound_at(gv), ((gv - hm.origin) @ hm.up_frame.T)[:, 2], atol=1e-3)
    else:
        assert sb.HEIGHT_NAME not in bpy.data.objects


@pytest.mark.slow
def test_initialise_uses_the_split_of_the_moved_view_cameras(tiny_scene, fresh):
    """A view camera moved into Train views trains (the real `dibrgs init` subprocess gets --train /
    --test); one moved out of the split collections is left out."""
    bpy.ops.dibrgs.import_scene(directory=str(tiny_scene))
    sb = _mod("scene_build")
    objs = {o["dibrgs_view"]: o for o in bpy.data.objects if "dibrgs_view" in o}
    imported = sb.scene_description(imported=True)
    train, held = bpy.data.collections[sb.TRAIN_COLLECTION], bpy.data.collections[sb.TEST_COLLECTION]
    moved_in, moved_out = imported["test"][0], imported["train"][-1]
    held.objects.unlink(objs[moved_in])
    train.objects.link(objs[moved_in])
    train.objects.unlink(objs[moved_out])
    assert bpy.ops.dibrgs.initialise(blocking=True) == {"FINISHED"}
    rep = json.loads((Path(fresh.dibrgs.work_dir) / "init" / "init_report.json").read_text())
    want = sorted([*imported["train"][:-1], moved_in])
    assert rep["values"]["train"] == want != imported["train"]


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
    assert "001" in err and not fresh.dibrgs.error_is_setup  # the subprocess's own message, not a set-up problem
    assert _mod("operators").running_job() is None


@pytest.mark.slow
def test_batch_mode_rejects_bad_arguments(tmp_path):
    run = [sys.executable, str(REPO / "scripts" / "run.py")]
    for args in ([], ["--scene", str(tmp_path / "missing"), "--out", str(tmp_path / "o")],
                 ["--scene", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "fast"],
                 ["--scene", str(tmp_path), "--out", str(tmp_path / "o"), "--resolution-scale", "nan"]):
        r = subprocess.run(run + args, capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and "usage:" in r.stderr, (args, r.stderr)
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_batch_mode_takes_the_split_of_train_and_test(tiny_scene, tmp_path):
    """`--train` / `--test` move the view cameras as a user would (the rules of `dibrgs train`'s
    options); a name the scene lacks is exit 2 naming it, before anything runs."""
    run = [sys.executable, str(REPO / "scripts" / "run.py"), "--scene", str(tiny_scene), "--no-init",
           "--preset", "test", "--iterations", "1"]
    r = subprocess.run(run + ["--out", str(tmp_path / "bad"), "--train", "001,999"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 2 and "split failed" in r.stderr and "'999' not in the scene" in r.stderr, r.stderr
    assert not (tmp_path / "bad" / "config.json").exists()
    r = subprocess.run(run + ["--out", str(tmp_path / "o"), "--train", "001,004,008", "--test", "none",
                              "--resolution-scale", "0.5"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    cfg = json.loads((tmp_path / "o" / "config.json").read_text())
    assert cfg["run"]["train"] == ["001", "004", "008"] and cfg["run"]["test"] == []
    assert cfg["config"]["resolution_scale"] == 0.5  # the panel's field, passed on by the batch


# ---------------------------------------------------------------------------
# The built extension, installed and driven through bpy.ops (one Blender process)
# ---------------------------------------------------------------------------
def _blender_ext() -> Path:
    spec = importlib.util.find_spec("bpy")
    p = Path(spec.origin).parent / "5.0" / "scripts" / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    if not p.exists():
        pytest.skip(f"Blender's extension tool not found at {p}")
    return p


def _pixels(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def _installed_workflow(zip_path: str, scene: str, work: str, batch_out: str) -> None:
    """Runs in a fresh Python with bpy and BLENDER_USER_RESOURCES set (see the fixture)."""
    import bpy
    from PIL import Image

    from dibrgs_core.camera.serialize import camera_from_dict
    from dibrgs_core.camera.blender import to_blender
    from dibrgs_core.data.levir import read_scene

    scene, work = Path(scene), Path(work)
    t0 = time.monotonic()
    timings = {}

    def lap(name):
        timings[name] = round(time.monotonic() - t0, 1)

    assert bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                    enable_on_install=True) == {"FINISHED"}
    pkg = "bl_ext.user_default.dibrgs"
    assert pkg in bpy.context.preferences.addons, list(bpy.context.preferences.addons.keys())
    core = sys.modules[pkg + ".addon._core"]
    assert core.CORE_PACKAGE == pkg + ".dibrgs_core" and Path(core.pinhole.__file__).is_relative_to(
        Path(os.environ["BLENDER_USER_RESOURCES"]))
    mod = lambda name: sys.modules[f"{pkg}.addon.{name}"]  # noqa: E731

    def stop(*_):  # the fixture's time limit sends SIGTERM: stop the `dibrgs` child too (it has its own session)
        mod("operators").stop_all(grace_s=5.0)
        sys.stdout.flush()
        os._exit(1)

    signal.signal(signal.SIGTERM, stop)
    C = bpy.context
    props = C.scene.dibrgs
    lap("install")

    # Set up / Check: every dependency imports, the rasterizer is built; a stale set-up error goes.
    props.error, props.error_is_setup = "Training failed: No module named 'torch'", True
    assert bpy.ops.dibrgs.setup_check(blocking=True) == {"FINISHED"}
    run = mod("setup").latest(sys.executable)
    assert run.report.ok and all(i.ok for i in run.report.items if i.required), run.report.items
    assert {i.name for i in run.report.items} >= {"torch", "PIL", "pycolmap", "scipy", "tifffile", "OpenEXR",
                                                   "trimesh", "skimage", "rasterizer"}
    assert props.error == "" and not props.error_is_setup
    lap("check")

    assert bpy.ops.dibrgs.import_scene(directory=str(scene)) == {"FINISHED"}
    props.work_dir = str(work)
    props.preset, props.iterations, props.pseudo_count = "test", 20, 3  # the preset has 4
    assert bpy.ops.dibrgs.initialise(blocking=True) == {"FINISHED"}, props.error
    assert mod("scene_build").POINTS_NAME in bpy.data.objects
    lap("initialise")
    sb, comp = mod("scene_build"), mod("compositor")
    assert not bpy.ops.dibrgs.results.poll()  # nothing trained yet
    assert not sb.path_edited(C)
    assert bpy.ops.dibrgs.train(blocking=True) == {"FINISHED"}, props.error
    lap("train")
    assert (work / "model.pt").is_file() and bpy.ops.dibrgs.results.poll()
    # The path as drawn only shows the trajectory: training sampled its 3 pseudo views itself.
    report = json.loads((work / "report.json").read_text())
    assert not (work / "blender" / "pseudo_path.json").exists()
    assert {d["step"]: d["applied"] for d in report["decisions"]}["pseudo_trajectory"]
    assert report["values"]["pseudo_views"]["wanted"] == 3
    ref = read_scene(scene, load_depth=False)
    tree = C.scene.compositing_node_group
    image_nodes = [n for n in tree.nodes if n.name.startswith(core.compositor.IMAGE_NODE_PREFIX)]
    assert len(image_nodes) == len(ref.test) + 3
    for n in image_nodes:
        assert [tuple(n.image.size)] == list(ref.sizes()) and n.image.has_data
    first = f"heldout_{ref.test[0]}"
    assert comp.wired_image(C.scene) == first
    assert [n.bl_idname for n in tree.nodes].count("NodeGroupOutput") == 1
    metrics = {m.name: m.value for m in props.metrics}
    assert any("psnr" in k.lower() for k in metrics) and all(np.isfinite(v) for v in metrics.values()), metrics
    # The final render is the result PNG (Standard view transform; AgX would shift its tones).
    C.scene.render.filepath = str(work / "final.png")
    bpy.ops.render.render(write_still=True)
    png = work / "blender" / "renders" / "heldout" / f"{ref.test[0]}.png"
    diff = np.abs(np.asarray(Image.open(work / "final.png").convert("RGB")).astype(int)
                  - np.asarray(Image.open(png).convert("RGB")).astype(int)).max()
    assert diff <= 1, diff
    props.result_view = "pseudo_002"  # the panel's view switch rewires the output
    assert comp.wired_image(C.scene) == "pseudo_002"
    lap("results")

    # A camera the user placed, rendered into the compositor: same pose as a held-out view, same image.
    cam_obj = sb.new_camera_object("MyShot", C.scene.collection)
    src = bpy.data.objects[ref.test[2]]
    for attr in ("lens", "sensor_width", "sensor_height", "shift_x", "shift_y", "clip_start", "clip_end"):
        setattr(cam_obj.data, attr, getattr(src.data, attr))
    cam_obj.matrix_world = src.matrix_world
    C.view_layer.objects.active = cam_obj
    assert bpy.ops.dibrgs.render_active_camera(blocking=True) == {"FINISHED"}, props.error
    assert comp.wired_image(C.scene) == "active_MyShot"
    np.testing.assert_allclose(np.array(bpy.data.images["active_MyShot"].pixels[:]),
                               np.array(bpy.data.images[f"heldout_{ref.test[2]}"].pixels[:]), atol=2 / 255)
    lap("active camera")

    # Fly-through: an image sequence and a camera animated frame by frame along the path.
    props.fly_frames = 3
    expected_fly = sb.path_cameras(C, 3, "fly")
    assert bpy.ops.dibrgs.flythrough(blocking=True) == {"FINISHED"}, props.error
    fly = bpy.data.objects[sb.FLY_NAME]
    assert (C.scene.frame_start, C.scene.frame_end) == (1, 3)
    for f, cam in enumerate(expected_fly, start=1):
        C.scene.frame_set(f)
        want = to_blender(cam).matrix_world
        np.testing.assert_allclose(np.array(fly.matrix_world), want, atol=1e-4 * max(1.0, np.abs(want).max()))
        assert (work / "blender" / "renders" / "flythrough" / f"fly_{f:04d}.png").is_file()
    assert bpy.data.images["flythrough"].source == "SEQUENCE"
    lap("fly-through")

    # Batch mode from the installed extension (what `blender -b -c dibrgs ...` runs), continuing the
    # trained run in a copy of its folder: the scene imported again draws the same path, unedited,
    # so training samples the trajectory as before (3 views) and the run continues.
    batch_out = Path(batch_out)
    shutil.copytree(work, batch_out, ignore=shutil.ignore_patterns("blender", "final.png"))
    rc = mod("batch").cli_command(["--scene", str(scene), "--out", str(batch_out), "--preset", "test",
                                   "--iterations", "24", "--pseudo-views", "3", "--no-init", "--resume"])
    assert rc == 0
    resumed = json.loads((batch_out / "report.json").read_text())["values"]
    assert resumed["resumed_from"] == 20 and resumed["pseudo_views"]["wanted"] == 3
    blend = batch_out / "dibrgs.blend"
    assert blend.is_file() and len(list((batch_out / "blender" / "renders" / "pseudo").glob("pseudo_*.png"))) == 3
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    tree = bpy.context.scene.compositing_node_group
    assert sum(n.bl_idname == "CompositorNodeImage" for n in tree.nodes) == len(ref.test) + 3
    assert len(bpy.context.scene.dibrgs.metrics) > 0 and sb.PATH_NAME in bpy.data.objects
    lap("batch")

    # A path the user edited is theirs: training takes its cameras as they are when it starts.
    C = bpy.context
    props = C.scene.dibrgs
    edited = batch_out.parent / "edited_path_run"
    props.work_dir, props.resume = str(edited), False
    bp = props.path_curve.data.splines[0].bezier_points[0]
    bp.co = np.array(bp.co) + 0.2 * np.array(props.scene_up) * np.linalg.norm(np.array(bp.co))
    assert sb.path_edited(C)
    expected_pseudo = sb.path_cameras(C, 3, "pseudo")
    assert bpy.ops.dibrgs.train(blocking=True) == {"FINISHED"}, props.error
    sent = [camera_from_dict(d) for d in json.loads((edited / "blender" / "pseudo_path.json").read_text())]
    assert len(sent) == 3
    for a, b in zip(sent, expected_pseudo):
        np.testing.assert_allclose(a.w2c, b.w2c, atol=1e-9)
    report = json.loads((edited / "report.json").read_text())
    assert not {d["step"]: d["applied"] for d in report["decisions"]}["pseudo_trajectory"]
    lap("edited path")
    print("TIMINGS " + json.dumps(timings), flush=True)


@pytest.fixture(scope="module")
def installed(tiny_scene, tmp_path_factory) -> dict:
    """Build, install and drive the extension (see :func:`_installed_workflow`); its run folders."""
    tmp = tmp_path_factory.mktemp("installed")
    zpath = tmp / "dibrgs.zip"
    r = subprocess.run([sys.executable, str(_blender_ext()), "build", "--source-dir", str(REPO),
                        "--output-filepath", str(zpath)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "blender_user"),
               PYTHONPATH=os.pathsep.join([str(REPO / "tests" / "addon"), str(REPO / "tests"), str(REPO)]))
    env.pop("DIBRGS_PYTHON", None)
    code = (f"import test_addon as t; t._installed_workflow({str(zpath)!r}, {str(tiny_scene)!r}, "
            f"{str(tmp / 'work')!r}, {str(tmp / 'batch')!r})")
    p = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, cwd=tmp)
    try:
        stdout, stderr = p.communicate(timeout=2400)
    except subprocess.TimeoutExpired:  # SIGTERM: the driver stops its child before it exits
        p.terminate()
        stdout, stderr = p.communicate(timeout=120)
        stderr += "\n(the installed workflow ran out of time: 2400 s)"
    out = {"rc": p.returncode, "log": stdout[-6000:] + stderr[-6000:], "work": tmp / "work", "tmp": tmp}
    timings = [ln for ln in stdout.splitlines() if ln.startswith("TIMINGS ")]
    out["timings"] = json.loads(timings[-1][8:]) if timings else {}
    return out


@pytest.mark.slow
def test_installed_extension_runs_the_whole_workflow(installed):
    """Install, Set up / Check, import, initialise, train, results, final render, active camera,
    fly-through and the extension's own batch entry, all through bpy.ops (see _installed_workflow)."""
    assert installed["rc"] == 0, installed["log"]
    print("workflow timings (s since start):", installed["timings"])


def _procs_with(text: str) -> list[int]:
    """PIDs of live processes whose command line contains ``text``."""
    pids = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if text in (p / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                    pids.append(int(p.name))
            except OSError:
                pass
    return pids


@pytest.mark.slow
@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_batch_stops_cleanly_on_sigint_and_sigterm(installed, tiny_scene, tmp_path):
    """Ctrl+C (SIGINT) or SIGTERM during training: the child stops and writes its checkpoint, one line, exit 130."""
    assert installed["rc"] == 0, installed["log"]
    out = tmp_path / "interrupted"
    shutil.copytree(installed["work"], out, ignore=shutil.ignore_patterns("blender", "final.png"))
    (out / "model.pt").unlink()  # so that we see the interrupted run does not write one
    cmd = [sys.executable, str(REPO / "scripts" / "run.py"), "--scene", str(tiny_scene), "--out", str(out),
           "--preset", "test", "--iterations", "100000", "--pseudo-views", "3", "--no-init", "--resume"]
    for sig in (signal.SIGINT, signal.SIGTERM):
        before = (out / "checkpoint.pt").stat().st_mtime_ns
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        lines = []
        t0 = time.monotonic()
        for line in p.stdout:  # wait until training reports iterations past the checkpoint's
            lines.append(line)
            it = re.search(r"\[DIBR-GS\] Training: it (\d+)/100000", line)
            if (it and int(it.group(1)) > 20) or time.monotonic() - t0 > 300:
                break
        assert it and int(it.group(1)) > 20, "".join(lines)[-3000:]
        p.send_signal(sig)
        stdout, stderr = p.communicate(timeout=300)
        err = [ln for ln in stderr.splitlines() if ln.strip()]
        assert p.returncode == 130, (stderr, stdout[-2000:])
        assert len(err) == 1 and err[0].startswith(f"run.py: interrupted by {sig.name} during train") and \
            "checkpoint is kept: run again with --resume" in err[0], stderr
        assert "Traceback" not in stdout + stderr
        assert (out / "checkpoint.pt").stat().st_mtime_ns > before  # written on the way out, not killed
        assert not (out / "model.pt").exists()
        assert _procs_with(str(out)) == []  # the training child is gone too
