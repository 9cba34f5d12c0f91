"""The add-on's logic without Blender: dibrgs_core.bridge (path sampling, progress, compositor
choice, commands and the subprocess runner, reports), the height-map mesh and the manifest."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from dibrgs_core.bridge import compositor, jobs, path, progress, reports
from dibrgs_core.bridge.geometry import height_map_mesh
from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.camera.serialize import camera_from_dict
from dibrgs_core.camera.orbit import fit_orbit
from dibrgs_core.geometry.height_map import HeightMap

REPO = Path(__file__).resolve().parents[2]


def _like() -> Camera:
    return Camera(K=[[50.0, 0, 32.0], [0, 55.0, 30.0], [0, 0, 1]], w2c=np.eye(4), width=64, height=60,
                  name="ref", depth_range=(1.0, 500.0))


# ---------------------------------------------------------------------------
# path sampling
# ---------------------------------------------------------------------------
def test_resample_closed_polyline_is_uniform_by_arc_length():
    # A square with unevenly placed vertices: samples must be evenly spaced along the perimeter.
    sq = np.array([[0, 0, 0], [1, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
    s = path.resample_polyline(sq, 8, closed=True)
    assert s.shape == (8, 3)
    np.testing.assert_allclose(s[0], [0, 0, 0])
    np.testing.assert_allclose(s[1], [2, 0, 0])
    np.testing.assert_allclose(s[4], [4, 4, 0])
    np.testing.assert_allclose(s[7], [0, 2, 0])


def test_resample_open_polyline_keeps_ends_and_survives_repeated_vertices():
    line = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [3, 0, 0]], float)
    s = path.resample_polyline(line, 4, closed=False)
    np.testing.assert_allclose(s[:, 0], [0, 1, 2, 3])
    # Degenerate: all vertices equal -> the point repeated, no NaN.
    d = path.resample_polyline(np.ones((5, 3)), 3, closed=True)
    assert np.isfinite(d).all() and np.allclose(d, 1.0)
    with pytest.raises(ValueError):
        path.resample_polyline(np.array([[0, 0, np.nan]]), 3, closed=True)
    with pytest.raises(ValueError):
        path.resample_polyline(np.zeros((0, 3)), 3, closed=True)


def test_path_cameras_look_at_target_with_reference_intrinsics():
    th = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    circle = np.stack([100 * np.cos(th), 100 * np.sin(th), np.full_like(th, 80.0)], 1)
    target = np.array([5.0, -3.0, 0.0])
    cams = path.path_cameras(circle, 6, target, [0, 0, 1], _like(), closed=True)
    assert [c.name for c in cams] == [f"pseudo_{k:03d}" for k in range(6)]
    for c in cams:
        np.testing.assert_allclose(c.K, _like().K)
        assert (c.width, c.height, c.depth_range) == (64, 60, (1.0, 500.0))
        uv, z = c.project(target[None])
        np.testing.assert_allclose(uv[0], [c.cx, c.cy], atol=1e-9)  # target on the optical axis
        assert z[0] > 0
        # the scene's up axis stays on the image's vertical line (no roll); its sign follows
        # cameras.look_at, which these cameras are built with
        uv_up, _ = c.project((target + [0, 0, 10])[None])
        assert abs(uv_up[0, 0] - c.cx) < 1e-6 and abs(uv_up[0, 1] - c.cy) > 1.0
        np.testing.assert_allclose(c.w2c, look_at(c.center, target, [0, 0, 1]), atol=1e-12)
    # Evenly spaced in angle around the circle (60 degrees apart).
    ang = np.degrees(np.arctan2([c.center[1] for c in cams], [c.center[0] for c in cams]))
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(ang))), np.radians(60), atol=1e-3)


def test_path_camera_on_the_target_stays_finite():
    cams = path.path_cameras(np.zeros((3, 3)), 2, [0, 0, 0], [0, 0, 1], _like(), closed=False)
    assert all(np.isfinite(c.w2c).all() for c in cams)


def test_orbit_control_points_lie_on_the_fitted_orbit(tmp_path):
    eyes = [np.array([200 * math.cos(a), 200 * math.sin(a), 150.0]) for a in np.radians([10, 130, 250])]
    cams = [Camera(K=_like().K, w2c=look_at(e, [0, 0, 0], [0, 0, 1]), width=64, height=60) for e in eyes]
    orbit = fit_orbit(cams)
    pts = path.orbit_control_points(orbit, 8)
    np.testing.assert_allclose(np.linalg.norm(pts - orbit.center, axis=1), orbit.radius, rtol=1e-9)
    np.testing.assert_allclose(pts[0], eyes[0], atol=1e-6)  # angle 0 is the first camera
    out = path.write_camera_list(tmp_path / "cams.json", cams)
    back = [camera_from_dict(d) for d in json.loads(out.read_text())]
    np.testing.assert_allclose(back[1].w2c, cams[1].w2c)


# ---------------------------------------------------------------------------
# progress
# ---------------------------------------------------------------------------
def test_progress_lines_and_eta():
    p = progress.Progress()
    assert progress.parse_progress_line("INFO something {not json}") is None
    assert progress.parse_progress_line("{broken") is None
    assert progress.parse_progress_line("[1, 2]") is None
    p.update(progress.parse_progress_line('{"iteration": 30, "total": 120, "loss": 0.25, "eta_s": 95.4, "elapsed_s": 31}'))
    assert p.fraction == pytest.approx(0.25)
    assert p.text() == "it 30/120  loss 0.25  ETA 1:35"
    # NaN/inf/garbage from a diverging run must not break the display.
    p.update({"iteration": 60, "total": 120, "loss": float("nan"), "eta_s": float("inf")})
    assert p.loss is None and p.eta_s is None and p.text().endswith("ETA --:--")
    p.update({"iteration": "x", "total": -5})
    assert (p.iteration, p.total) == (60, 120)
    p.update({"done": True, "work": "/tmp/w"})
    assert p.done and p.fraction == 1.0 and p.work == "/tmp/w"
    assert progress.format_duration(3725) == "1:02:05"
    assert progress.format_duration(-1) == "--:--"


# ---------------------------------------------------------------------------
# compositor API choice and plan
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("version,group,out_type", [
    ((4, 2, 0), False, "CompositorNodeComposite"),
    ((4, 5, 3), False, "CompositorNodeComposite"),
    ((5, 0, 1), True, "NodeGroupOutput"),
    ((5, 1, 0), True, "NodeGroupOutput"),
])
def test_compositor_api_by_version(version, group, out_type):
    api = compositor.compositor_api(version)
    assert api.node_group is group and api.output_node_type == out_type
    plan = compositor.compositor_plan(["test_002", "test_003", "pseudo_000"], "test_003", api)
    assert set(plan.image_nodes) == {compositor.image_node_name(n) for n in ("test_002", "test_003", "pseudo_000")}
    src = compositor.image_node_name("test_003")
    assert (src, "Image", plan.output[0], api.output_socket) in plan.links
    assert (src, "Image", plan.viewer[0], "Image") in plan.links
    locs = [loc for _, loc in plan.image_nodes.values()]
    assert len(set(locs)) == len(locs)  # no two nodes on top of each other


def test_compositor_plan_rejects_bad_input():
    api = compositor.compositor_api((4, 2, 0))
    with pytest.raises(ValueError):
        compositor.compositor_api((4, 1, 0))
    with pytest.raises(ValueError):
        compositor.compositor_plan([], None, api)
    with pytest.raises(ValueError):
        compositor.compositor_plan(["a"], "b", api)
    assert compositor.compositor_plan(["a", "b"], None, api).links[0][0] == compositor.image_node_name("a")


# ---------------------------------------------------------------------------
# commands and the subprocess runner
# ---------------------------------------------------------------------------
def test_train_command_carries_the_options(tmp_path):
    opts = jobs.TrainOptions(preset="test", method="3dgs", iterations=50, pseudo_path=tmp_path / "p.json",
                             resume=True, weights=jobs.Weights(depth_model="/w/da", lpips="/w/lpips"))
    cmd = jobs.train_command("/usr/bin/python3", tmp_path / "scene", tmp_path / "work", opts)
    assert cmd[:4] == ["/usr/bin/python3", "-m", "dibrgs_core", "train"]
    s = " ".join(cmd)
    for part in ("--preset test", "--method 3dgs", "--iterations 50", f"--pseudo-path {tmp_path / 'p.json'}",
                 "--resume", "--progress-json", "--depth-model /w/da", f"--out {tmp_path / 'work'}"):
        assert part in s
    assert "--lpips" not in s  # LPIPS is for eval
    assert "--lpips /w/lpips" in " ".join(jobs.eval_command("py", tmp_path, opts.weights))
    with pytest.raises(ValueError):
        jobs.TrainOptions(preset="fast")
    with pytest.raises(ValueError):
        jobs.TrainOptions(iterations=0)
    env = jobs.subprocess_env({"PYTHONPATH": "/elsewhere"})
    assert env["PYTHONPATH"].split(":")[0] == str(REPO) and "/elsewhere" in env["PYTHONPATH"]
    # The panel's "Pseudo views" 0 means the preset's own count; a number the user sets wins.
    from dibrgs_core.training.config import preset

    assert jobs.pseudo_view_count("cpu") == preset("cpu").pseudo.n_views == 96
    assert jobs.pseudo_view_count("test") == preset("test").pseudo.n_views
    assert jobs.pseudo_view_count("cpu", 7) == 7


def _script(tmp_path: Path, name: str, body: str) -> list[str]:
    p = tmp_path / name
    p.write_text(textwrap.dedent(body))
    return [sys.executable, str(p)]


def test_runner_reads_progress_and_runs_steps_in_order(tmp_path):
    prog = _script(tmp_path, "prog.py", """
        import json, sys
        print("a log line on stdout")
        for i in (10, 20):
            print(json.dumps({"iteration": i, "total": 20, "loss": 1.0 / i, "eta_s": 20 - i, "elapsed_s": i}))
        print(json.dumps({"done": True, "work": "W"}))
        print("to stderr", file=sys.stderr)
    """)
    second = _script(tmp_path, "second.py", "open(__import__('sys').argv[1], 'w').write('ran')")
    lines = []
    r = jobs.JobRunner([jobs.Step("Training", prog, tmp_path / "logs" / "t.log", progress=True),
                        jobs.Step("After", second + [str(tmp_path / "marker")], tmp_path / "logs" / "a.log")],
                       on_line=lines.append)
    assert r.wait(interval_s=0.02, timeout_s=60) == "done"
    assert (tmp_path / "marker").read_text() == "ran"
    assert lines == ["a log line on stdout"]
    log = (tmp_path / "logs" / "t.log").read_text()
    assert "to stderr" in log and '"iteration": 20' in log and log.startswith("$ ")


def test_runner_failure_names_the_log(tmp_path):
    bad = _script(tmp_path, "bad.py", """
        import sys
        print("dibrgs train: error: /x/Images: missing folder", file=sys.stderr)
        sys.exit(2)
    """)
    never = _script(tmp_path, "never.py", "open('never_ran', 'w')")
    log = tmp_path / "bad.log"
    r = jobs.JobRunner([jobs.Step("Training", bad, log, progress=True), jobs.Step("Next", never, tmp_path / "n.log")],
                       cwd=tmp_path)
    assert r.wait(interval_s=0.02, timeout_s=60) == "failed"
    assert r.returncode == 2
    assert f"log: {log}" in r.error and "missing folder" in r.error
    assert not (tmp_path / "never_ran").exists()
    missing = jobs.JobRunner([jobs.Step("X", [str(tmp_path / "no-such-python")], tmp_path / "x.log")])
    assert missing.wait(timeout_s=10) == "failed" and "cannot start" in missing.error


def test_runner_cancel_sends_sigint_so_the_process_can_save(tmp_path):
    slow = _script(tmp_path, "slow.py", """
        import json, sys, time
        try:
            for i in range(1000):
                print(json.dumps({"iteration": i, "total": 1000}), flush=True)
                time.sleep(0.05)
        except KeyboardInterrupt:
            open(sys.argv[1], "w").write("checkpoint")
            sys.exit(130)
    """)
    r = jobs.JobRunner([jobs.Step("Training", slow + [str(tmp_path / "ckpt")], tmp_path / "s.log", progress=True),
                        jobs.Step("Render", slow + [str(tmp_path / "other")], tmp_path / "r.log")])
    r.start()
    import time
    t0 = time.monotonic()
    while r.progress.iteration < 3 and time.monotonic() - t0 < 30:
        r.poll()
        time.sleep(0.02)
    assert r.progress.iteration >= 3
    r.cancel(grace_s=20)
    assert r.wait(interval_s=0.02, timeout_s=60) == "cancelled"
    assert (tmp_path / "ckpt").read_text() == "checkpoint"  # saved on SIGINT, not killed
    assert not (tmp_path / "other").exists() and len(r.steps) == 1


def test_check_interpreter_reports_a_python_without_torch(tmp_path):
    ok, msg = jobs.check_interpreter(str(tmp_path / "missing-python"))
    assert not ok and "cannot run" in msg
    ok, msg = jobs.check_interpreter(sys.executable)
    assert ok, msg


# ---------------------------------------------------------------------------
# reports, height map mesh
# ---------------------------------------------------------------------------
def test_reports_decisions_and_metrics(tmp_path):
    rep = {"decisions": [{"stage": "init", "step": "height_map", "applied": False, "reason": "flat", "details": {}},
                         {"bad": 1}], "values": {}}
    assert reports.decisions(rep) == [{"stage": "init", "step": "height_map", "applied": False, "reason": "flat"}]
    m = reports.summary_metrics({"psnr": 25.5, "ssim": 0.8, "lpips": float("nan"), "valid": True,
                                 "per_view": [1, 2], "mean": {"psnr": 25.5, "deep": {"x": 1}}})
    assert m == {"psnr": 25.5, "ssim": 0.8, "mean/psnr": 25.5}
    (tmp_path / "bad.json").write_text("{")
    from dibrgs_core.common.errors import InputError
    with pytest.raises(InputError, match="bad.json"):
        reports.read_json(tmp_path / "bad.json")


def test_height_map_mesh_in_world_coordinates():
    up = np.array([0.0, 0.6, 0.8])
    from dibrgs_core.camera.frame import up_frame
    F = up_frame(up)
    bounds = np.array([[1.0, 2.0, np.nan], [3.0, 4.0, 5.0]])
    hm = HeightMap(up_frame=F, origin=np.array([10.0, 0, 0]), cell=2.0, x0=-1.0, y0=0.0, bounds=bounds)
    verts, quads = height_map_mesh(hm)
    assert verts.shape == (5, 3) and quads.tolist() == [[0, 2, 3, 1]]
    loc = (verts - hm.origin) @ F.T  # back to the map's frame
    np.testing.assert_allclose(loc[:, 2], [1, 2, 3, 4, 5])
    np.testing.assert_allclose(loc[0, :2], [0.0, 1.0], atol=1e-12)  # centre of cell (0, 0)
    assert hm.allows(verts - 1e-6 * up).all()  # every vertex is at its cell's bound


# ---------------------------------------------------------------------------
# the extension manifest, checked and built by Blender's own extension tool
# ---------------------------------------------------------------------------
def _blender_ext() -> Path:
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    p = Path(spec.origin).parent / "5.0" / "scripts" / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    if not p.exists():
        pytest.skip(f"Blender's extension tool not found at {p}")
    return p


def test_manifest_is_valid_and_builds_an_extension(tmp_path):
    import tomllib

    m = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    for key in ("schema_version", "id", "version", "name", "tagline", "maintainer", "type",
                "blender_version_min", "license", "permissions"):
        assert key in m, key
    assert m["type"] == "add-on" and m["blender_version_min"] == "4.2.0" and "files" in m["permissions"]
    tool = _blender_ext()
    r = subprocess.run([sys.executable, str(tool), "validate", str(REPO)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    zpath = tmp_path / "dibrgs.zip"
    r = subprocess.run([sys.executable, str(tool), "build", "--source-dir", str(REPO), "--output-filepath",
                        str(zpath)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    names = zipfile.ZipFile(zpath).namelist()
    for needed in ("__init__.py", "blender_manifest.toml", "addon/__init__.py", "addon/_core.py",
                   "dibrgs_core/camera/pinhole.py", "dibrgs_core/bridge/jobs.py"):
        assert needed in names
    assert not any(n.startswith(("tests/", "scripts/", ".git")) or "__pycache__" in n for n in names)
