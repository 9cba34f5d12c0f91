"""The add-on's logic without Blender: dibrgs_core.bridge (path sampling, progress, compositor
choice, commands and the subprocess runner, `dibrgs check`, the numpy-only scene reader, reports),
the height-map mesh and the manifest."""
from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from dibrgs_core.bridge import checks, colmap_model, compositor, describe, imagesize, jobs, path, progress, reports
from dibrgs_core.bridge.geometry import height_map_mesh
from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.camera.serialize import camera_from_dict
from dibrgs_core.camera.orbit import fit_orbit
from dibrgs_core.common.errors import InputError
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


def test_resample_polylines_spreads_samples_over_splines_by_length():
    a = np.array([[0, 0, 0], [3, 0, 0]], float)
    b = np.array([[0, 5, 0], [0, 5, 1]], float)
    s = path.resample_polylines([a, b], 8, closed=False)
    # length 3 + 1: samples at (k + 1/2) * 0.5 -> six on the first line, two on the second
    np.testing.assert_allclose(s[:6, 0], [0.25, 0.75, 1.25, 1.75, 2.25, 2.75])
    np.testing.assert_allclose(s[6:], [[0, 5, 0.25], [0, 5, 0.75]])
    assert np.allclose(path.resample_polylines([a], 4, [False]), path.resample_polyline(a, 4, False))
    with pytest.raises(ValueError):
        path.resample_polylines([a, b], 3, [False])


def _nadir(x: float, y: float, yaw_deg: float = 0.0, name: str = "") -> Camera:
    """A camera 100 units up looking straight down, image up turned ``yaw_deg`` from +x."""
    eye = np.array([x, y, 100.0])
    yaw = math.radians(yaw_deg)
    return Camera(K=_like().K, w2c=look_at(eye, eye - [0, 0, 100.0], [math.cos(yaw), math.sin(yaw), 0.0]),
                  width=64, height=60, name=name)


def _strip_cams(rows: int, cols: int, yaw_deg: float = 0.0) -> list[Camera]:
    """Nadir cameras on a grid (rows = strips 30 apart, cameras 20 apart along them), camera c of a
    strip turned c x ``yaw_deg``."""
    return [_nadir(20.0 * c, 30.0 * r, yaw_deg * c, f"v{r}{c}") for r in range(rows) for c in range(cols)]


def test_path_plan_with_the_cloud_adds_each_cameras_heading():
    """One photo a strip (three strips, image up along the strips): with the dense cloud the path
    also runs along each camera's heading, half the image's ground extent either side, as the
    trainer samples it; cameras there take that photo's pose. Without the cloud: the line only."""
    cams = _strip_cams(3, 1)  # at (0, 0), (0, 30), (0, 60), 100 up; image up along +x
    xs, ys = np.meshgrid(np.linspace(-40, 40, 9), np.linspace(-20, 80, 11))
    ground = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)  # 100 below the cameras
    bare = path.plan_path(cams, views=cams)
    assert bare.kind == "strips" and len(bare.polylines) == 1
    plan = path.plan_path(cams, views=cams, points=ground)
    assert plan.kind == "strips" and "heading" in plan.reason
    lines = [p for p in plan.polylines if np.ptp(p[:, 1]) > 1.0]
    heads = [p for p in plan.polylines if np.ptp(p[:, 1]) <= 1e-9]
    assert len(lines) == 1 and len(heads) == 3
    reach = 0.5 * 60 / 55.0 * 100.0  # half the image height / fy x the depth
    for c, h in zip(cams, sorted(heads, key=lambda p: p[0, 1])):
        np.testing.assert_allclose(sorted(h[:, 0]), [-reach, reach], atol=1e-9)
        np.testing.assert_allclose(h[:, 1:], np.tile(c.center[1:], (2, 1)), atol=1e-9)
        on = path.path_cameras([h], 5, None, plan.up, cams[0], False, follow=cams)
        for q in on:
            np.testing.assert_allclose(q.R, c.R, atol=1e-9)
    # millimetres or kilometres: the same path, scaled
    for s in (1e-3, 1e4):
        scaled = [Camera(K=c.K, w2c=np.block([[c.R, s * c.t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]),
                         width=c.width, height=c.height) for c in cams]
        other = path.plan_path(scaled, views=scaled, points=s * ground)
        assert len(other.polylines) == len(plan.polylines)
        for a, b in zip(other.polylines, plan.polylines):
            np.testing.assert_allclose(a, s * b, rtol=1e-9, atol=1e-9 * s)
    # a cloud behind every camera gives no depth: the line only
    assert len(path.plan_path(cams, views=cams, points=ground + [0, 0, 200.0]).polylines) == 1


def test_path_plan_follows_strips_and_falls_back_to_the_orbit():
    grid = _strip_cams(2, 3)
    plan = path.plan_path(grid, views=grid)
    assert plan.kind == "strips" and plan.orbit is None
    lines = [p for p in plan.polylines if len(p) > 2]
    assert len(lines) == 2  # each strip, continued half a spacing past its end cameras
    for line in lines:
        np.testing.assert_allclose(sorted(line[:, 0]), [-10, 0, 20, 40, 50], atol=1e-9)
        assert np.ptp(line[:, 1]) < 1e-9 and np.allclose(line[:, 2], 100.0)
    cross = [p for p in plan.polylines if len(p) == 2]
    assert cross and all(abs(p[1, 1] - p[0, 1]) == pytest.approx(30.0) for p in cross)  # strip to strip
    cams = path.path_cameras(plan.polylines, 10, None, plan.up, grid[0], False, follow=grid)
    for c in cams:  # nadir, like the photos
        np.testing.assert_allclose(c.view_dir, [0, 0, -1], atol=1e-9)
    with pytest.raises(ValueError):
        path.path_cameras(plan.polylines, 3, None, plan.up, grid[0], False)
    # the same flight in millimetres or kilometres: the same path, scaled
    for s in (1e-3, 1e4):
        scaled = [Camera(K=c.K, w2c=np.block([[c.R, s * c.t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]),
                         width=c.width, height=c.height) for c in grid]
        other = path.plan_path(scaled, views=scaled)
        assert other.kind == "strips" and len(other.polylines) == len(plan.polylines)
        for a, b in zip(other.polylines, plan.polylines):
            np.testing.assert_allclose(a, s * b, rtol=1e-9, atol=1e-9 * s)
        far = path.path_cameras(other.polylines, 10, None, other.up, scaled[0], False, follow=scaled)
        for c, d in zip(far, cams):
            np.testing.assert_allclose(c.R, d.R, atol=1e-9)
            np.testing.assert_allclose(c.center, s * d.center, rtol=1e-9, atol=1e-9 * s)
    # one camera (or all at one place): no crash, the path is that place and looks as the camera does
    for one in ([grid[0]], [grid[0], grid[0]]):
        lone = path.plan_path(one, views=one)
        assert lone.orbit is None and np.allclose(lone.polylines[0], grid[0].center)
        at = path.path_cameras(lone.polylines, 3, None, lone.up, grid[0], False, follow=one)
        assert all(np.allclose(c.w2c, grid[0].w2c, atol=1e-9) for c in at)
    # cameras on an orbit: a circle fitted to them, looked at from the path
    eyes = [np.array([200 * math.cos(a), 200 * math.sin(a), 150.0]) for a in np.radians([10, 130, 250])]
    ring = [Camera(K=_like().K, w2c=look_at(e, [0, 0, 0], [0, 0, 1]), width=64, height=60) for e in eyes]
    orbit = path.plan_path(ring, views=ring)
    assert orbit.kind == "orbit" and orbit.polylines is None
    np.testing.assert_allclose(orbit.orbit.radius, 200.0, rtol=1e-6)


def test_chain_polylines_makes_one_route_without_long_jumps():
    grid = _strip_cams(2, 3)
    polys = path.plan_path(grid, views=grid).polylines
    route = path.chain_polylines(polys)
    assert route.shape[1] == 3 and len(route) == sum(len(p) for p in polys)
    # every vertex of every spline is on the route, and no step is longer than the longest spline
    # segment or the widest gap between the grid's strips
    for p in polys:
        assert all(np.isclose(np.linalg.norm(route - v, axis=1), 0).any() for v in p)
    steps = np.linalg.norm(np.diff(route, axis=0), axis=1)
    assert steps.max() <= max(np.linalg.norm(np.diff(p, axis=0), axis=1).max() for p in polys) + 30.0 + 1e-9
    np.testing.assert_allclose(route[: len(polys[0])], polys[0])  # starts as the first spline
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0]], float)
    closed = path.chain_polylines([square], True)
    np.testing.assert_allclose(closed[[0, -1]], [[0, 0, 0], [0, 0, 0]])  # opened at its first vertex


def _angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R1 @ R2.T) - 1) / 2, -1, 1)))


def test_cameras_following_the_photos_turn_smoothly_along_a_route():
    """A fly-through along the drawn path of a free flight (five photos, headings up to 120
    degrees apart) and of a mapping grid flown back and forth (alternate strips 180 degrees
    apart): no sudden turns between frames; at a photo's place, its rotation."""
    rng = np.random.default_rng(0)

    free = [_nadir(*rng.uniform(-50, 50, 2), rng.uniform(-60, 60)) for _ in range(5)]
    serpentine = [_nadir(20.0 * c, 30.0 * r, 180.0 * r) for r in range(2) for c in range(4)]
    for cams in (free, serpentine):
        plan = path.plan_path(cams, views=cams)
        route = path.chain_polylines(plan.polylines)
        fly = path.path_cameras(route, 400, None, plan.up, cams[0], False, follow=cams)
        steps = [_angle_deg(a.R, b.R) for a, b in zip(fly, fly[1:])]
        assert max(steps) < 15.0, max(steps)
        for c in cams:
            np.testing.assert_allclose(path.follow_rotation(c.center, cams, plan.up), c.R, atol=1e-9)


def test_follow_rotation_slerps_between_the_two_nearest_cameras():
    cams = _strip_cams(1, 2, yaw_deg=40.0)  # the second camera turned 40 degrees about the vertical
    up = np.array([0.0, 0, 1])
    np.testing.assert_allclose(path.follow_rotation(cams[0].center, cams, up), cams[0].R, atol=1e-12)
    mid = path.follow_rotation(0.5 * (cams[0].center + cams[1].center) + [0, 0, 7.0], cams, up)
    right = mid[0]  # image x in world coordinates: turned half way, 20 degrees
    assert math.degrees(math.atan2(right[1], right[0])) - math.degrees(math.atan2(cams[0].R[0, 1], cams[0].R[0, 0])) \
        == pytest.approx(20.0, abs=1e-6)


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


def test_stage_lines_show_long_set_up_steps():
    p = progress.Progress()
    assert p.text() == "starting"  # nothing reported yet (torch is still loading)
    p.update(progress.parse_progress_line('{"stage": "compiling the rasterizer (first run, about 2 minutes)"}'))
    assert p.text() == "compiling the rasterizer (first run, about 2 minutes)" and p.fraction == 0.0
    # A stage's "done" is a count of its items, not the end of the run.
    p.update({"stage": "building 96 pseudo views", "done": 3, "total": 96})
    assert not p.done and p.text() == "building 96 pseudo views 3/96"
    assert p.fraction == pytest.approx(3 / 96)
    p.update({"stage": "building 96 pseudo views", "done": "x", "total": float("nan")})
    assert p.text() == "building 96 pseudo views" and p.fraction == 0.0
    p.update({"iteration": 10, "total": 40, "eta_s": 30})  # training has started: the stage is over
    assert p.stage is None and p.text() == "it 10/40  ETA 0:30" and p.fraction == 0.25
    p.update({"done": True})
    assert p.done and p.text() == "done"


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
def test_a_split_chosen_in_blender_reaches_init_and_train(tmp_path):
    """(training, held-out) views from the add-on become --train / --test (--test none: nothing held
    out), which the command line reads back as the same split; no split: the scene's own."""
    from dibrgs_core.cli import build_parser
    from dibrgs_core.data.split import make_split

    ids = ["DJI_0018", "DJI_0019", "DJI_0020", "DJI_0027"]
    for split in ((["DJI_0019", "DJI_0020"], ["DJI_0018"]), (["DJI_0019", "DJI_0020"], []),
                  (["DJI_0019", "DJI_0020"], ["none"])):
        ids = ids + ["none"] if "none" in split[1] else ids  # a view named "none" wins over the keyword
        for cmd in (jobs.train_command("py", tmp_path, tmp_path / "w", jobs.TrainOptions(split=split)),
                    jobs.init_command("py", tmp_path, tmp_path / "w", split=split)):
            args = build_parser().parse_args(cmd[3:])
            assert make_split(tmp_path, ids, args.train, args.test)[:2] == split
    assert "--train" not in jobs.train_command("py", tmp_path, tmp_path, jobs.TrainOptions())
    assert "--test" not in jobs.init_command("py", tmp_path, tmp_path)
    for bad in ((["a,b"], []), ([" a"], []), ([], ["a"]), (["a", "None"], [])):
        with pytest.raises(ValueError):
            jobs.split_flags(bad)


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
    assert "--pseudo-views" not in s  # a path keeps its own cameras
    sampled = jobs.train_command("py", tmp_path, tmp_path, jobs.TrainOptions(pseudo_views=7))
    assert "--pseudo-views 7" in " ".join(sampled) and "--pseudo-path" not in sampled
    # ... and the command line takes it: the preset's count replaced
    from dibrgs_core.cli import build_parser
    from dibrgs_core.commands.train import config_from_args

    args = build_parser().parse_args(sampled[sampled.index("train"):])
    assert config_from_args(args).pseudo.n_views == 7
    assert config_from_args(args).resolution_scale is None  # the preset's pixel budget
    scaled = jobs.train_command("py", tmp_path, tmp_path, jobs.TrainOptions(resolution_scale=0.75))
    assert config_from_args(build_parser().parse_args(scaled[scaled.index("train"):])).resolution_scale == 0.75
    for bad in (0.0, 5.0, float("nan")):
        with pytest.raises(ValueError):
            jobs.TrainOptions(resolution_scale=bad)
    assert "--lpips /w/lpips" in " ".join(jobs.eval_command("py", tmp_path, opts.weights))
    with pytest.raises(ValueError):
        jobs.TrainOptions(preset="fast")
    with pytest.raises(ValueError):
        jobs.TrainOptions(iterations=0)
    with pytest.raises(ValueError):
        jobs.TrainOptions(pseudo_views=0)
    env = jobs.subprocess_env({"PYTHONPATH": "/elsewhere"})
    assert env["PYTHONPATH"].split(":")[0] == str(REPO) and "/elsewhere" in env["PYTHONPATH"]
    # The panel's "Pseudo views" 0 means the preset's own count; a number the user sets wins.
    from dibrgs_core.training.config import preset

    assert jobs.pseudo_view_count("cpu") == preset("cpu").pseudo.n_views == 96
    assert jobs.pseudo_view_count("test") == preset("test").pseudo.n_views
    assert jobs.pseudo_view_count("cpu", 7) == 7
    # the results step renders at most RESULT_PATH_VIEWS of them along the path
    assert jobs.result_path_views("cpu") == jobs.RESULT_PATH_VIEWS == 16
    assert jobs.result_path_views("cpu", 7) == 7 and jobs.result_path_views("test") == preset("test").pseudo.n_views


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
    assert r._proc.stdout.closed and r._log.closed  # nothing of the job stays open after it


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
    # The child installs its SIGINT handler as training does (guard.stop_on_signals): a process
    # started with SIGINT ignored (a background job of a shell without job control) would
    # otherwise inherit that, and Python would not raise KeyboardInterrupt.
    slow = _script(tmp_path, "slow.py", """
        import json, signal, sys, time
        signal.signal(signal.SIGINT, signal.default_int_handler)
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


def test_runner_kills_a_step_that_ignores_the_stop_and_cancels_at_its_timeout(tmp_path):
    """Cancel asks with SIGINT; a step that does not stop within the grace period (hung, or
    ignoring the signal) is killed, so Blender's Cancel always ends the job. ``wait`` with a
    timeout cancels the job when the time is up."""
    import time

    deaf = _script(tmp_path, "deaf.py", """
        import signal, time
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        print("ready", flush=True)
        time.sleep(120)
    """)
    r = jobs.JobRunner([jobs.Step("Training", deaf, tmp_path / "d.log")], on_line=lambda _: None)
    r.start()
    t0 = time.monotonic()
    while "ready" not in (tmp_path / "d.log").read_text() and time.monotonic() - t0 < 30:
        r.poll()
        time.sleep(0.02)
    r.cancel(grace_s=0.5)
    assert r.wait(interval_s=0.02) == "cancelled"
    assert time.monotonic() - t0 < 30 and r.returncode == -signal.SIGKILL
    sleepy = _script(tmp_path, "sleepy.py", """
        import signal, sys, time
        signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            time.sleep(120)
        except KeyboardInterrupt:
            sys.exit(130)
    """)
    r2 = jobs.JobRunner([jobs.Step("Training", sleepy, tmp_path / "s.log")])
    t0 = time.monotonic()
    assert r2.wait(interval_s=0.02, timeout_s=0.5) == "cancelled"
    assert time.monotonic() - t0 < 5 and r2.returncode == 130  # stopped by SIGINT, not killed


# ---------------------------------------------------------------------------
# `dibrgs check` (Set up / Check in Blender)
# ---------------------------------------------------------------------------
def test_check_dependencies_are_the_projects():
    import tomllib

    from dibrgs_core.commands.check import DEPENDENCIES

    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    assert sorted(d.requirement for d in DEPENDENCIES) == sorted(deps)
    assert [d.module for d in DEPENDENCIES][0] == "torch"


def test_check_report_folds_the_lines():
    r = checks.CheckReport()
    assert not r.feed("some log line") and r.ok is None and r.fraction == 0.0
    assert r.feed('{"check": "torch", "ok": true, "required": true, "detail": "2.13.0", "index": 1, "total": 4}')
    assert r.text() == "checked torch (1/4)" and r.fraction == 0.25
    r.feed('{"check": "PIL", "ok": false, "required": true, "detail": "ModuleNotFoundError", '
           '"fix": "py -m pip install pillow", "index": 2, "total": 4}')
    r.feed('{"check": "transformers", "ok": false, "required": false, "index": 3, "total": 4}')
    r.feed('{"stage": "compiling the rasterizer (first run, about 2 minutes)"}')
    assert r.text().startswith("compiling the rasterizer")
    r.feed('{"result": {"ok": false, "missing": ["PIL", "transformers"], "fix": "py -m pip install pillow"}}')
    assert r.ok is False and r.fraction == 1.0 and r.problems() == ["PIL"]
    assert r.text() == "not ready: PIL"


@pytest.mark.slow
def test_check_names_what_is_missing_and_the_fix(tmp_path):
    """The real `dibrgs check` in a Python where pycolmap cannot be imported."""
    block = tmp_path / "block"
    block.mkdir()
    (block / "sitecustomize.py").write_text(textwrap.dedent("""
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] == "pycolmap":
                    raise ModuleNotFoundError(f"No module named {name!r} (blocked by the test)")
        sys.meta_path.insert(0, Block())
    """))
    env = jobs.subprocess_env()
    env["PYTHONPATH"] = os.pathsep.join([env["PYTHONPATH"], str(block)])
    r = subprocess.run(jobs.check_command(sys.executable) + ["--no-build"], env=env, capture_output=True,
                       text=True, timeout=300)
    report = checks.CheckReport()
    for line in r.stdout.splitlines():
        report.feed(line)
    assert r.returncode == 1, r.stdout + r.stderr
    items = {i.name: i for i in report.items}
    assert not items["pycolmap"].ok and "blocked by the test" in items["pycolmap"].detail
    assert items["pycolmap"].fix == f"{sys.executable} -m pip install pycolmap"
    assert report.result["fix"] == items["pycolmap"].fix and report.problems() == ["pycolmap"]
    assert all(i.ok for n, i in items.items() if n != "pycolmap"), [i for i in report.items if not i.ok]
    assert items["torch"].ok and items["dibrgs_core"].detail == str(REPO / "dibrgs_core")


def test_model_problem_names_what_the_run_folder_lacks(tmp_path):
    assert "train first" in jobs.model_problem(tmp_path)
    (tmp_path / jobs.CHECKPOINT_FILE).write_bytes(b"")
    assert "stopped before the end" in jobs.model_problem(tmp_path)  # an interrupted run
    (tmp_path / jobs.MODEL_FILE).write_bytes(b"")
    assert jobs.model_problem(tmp_path) is None
    from dibrgs_core.training import checkpoint, run_folder

    assert (jobs.MODEL_FILE, jobs.CHECKPOINT_FILE, jobs.CONFIG_FILE) == (checkpoint.MODEL, checkpoint.CHECKPOINT,
                                                                         run_folder.CONFIG)


def test_run_pseudo_path_reads_what_the_run_started_with(tmp_path):
    assert jobs.run_pseudo_path(tmp_path) is None  # no run
    (tmp_path / jobs.CONFIG_FILE).write_text("{broken")
    assert jobs.run_pseudo_path(tmp_path) is None
    from dibrgs_core.training.config import preset

    cfg = preset("test")
    (tmp_path / jobs.CONFIG_FILE).write_text(json.dumps({"config": cfg.to_dict()}))
    assert jobs.run_pseudo_path(tmp_path) is None
    cfg.pseudo_path = "/somewhere/pseudo_path.json"
    (tmp_path / jobs.CONFIG_FILE).write_text(json.dumps({"config": cfg.to_dict()}))
    assert jobs.run_pseudo_path(tmp_path) == "/somewhere/pseudo_path.json"


# ---------------------------------------------------------------------------
# scenes read in Blender's Python: numpy and the standard library only
# ---------------------------------------------------------------------------
def test_image_size_from_headers(tmp_path):
    from PIL import Image
    import tifffile

    rgb = (np.random.default_rng(0).random((37, 53, 3)) * 255).astype(np.uint8)
    files = {"a.png": (53, 37), "b.jpg": (53, 37), "c.tif": (53, 37), "d16.png": (53, 37),
             "e_big.tif": (19, 23), "f_prog.jpg": (53, 37)}
    Image.fromarray(rgb).save(tmp_path / "a.png")
    Image.fromarray(rgb).save(tmp_path / "b.jpg", quality=90)
    Image.fromarray(rgb).save(tmp_path / "f_prog.jpg", progressive=True)
    Image.fromarray(rgb).save(tmp_path / "c.tif")
    Image.fromarray((rgb[..., 0].astype(np.uint16) * 257)).save(tmp_path / "d16.png")
    tifffile.imwrite(tmp_path / "e_big.tif", np.zeros((23, 19), np.float32), bigtiff=True)
    for name, size in files.items():
        assert imagesize.image_size(tmp_path / name) == size, name
        if not name.startswith("e_"):
            with Image.open(tmp_path / name) as im:
                assert im.size == size
    (tmp_path / "bad.png").write_bytes(b"not an image at all")

    with pytest.raises(InputError, match="bad.png: unreadable image header"):
        imagesize.image_size(tmp_path / "bad.png")


def test_exif_orientation_from_headers_as_the_library_reads_it(tmp_path):
    """JPEG (APP1), PNG (eXIf) and TIFF (tag 274) orientations, valid, invalid and malformed, as the
    library's Pillow / tifffile readers take them; the size as a viewer shows the photo."""
    from PIL import Image
    import tifffile

    from dibrgs_core.data import images

    rgb = (np.random.default_rng(0).random((37, 53, 3)) * 255).astype(np.uint8)
    files = []
    for o in (1, 2, 3, 4, 5, 6, 7, 8, 9, 0):
        im = Image.fromarray(rgb)
        exif = im.getexif()
        exif[0x0112] = o
        for ext in ("jpg", "png"):
            im.save(tmp_path / f"o{o}.{ext}", exif=exif)
            files.append(tmp_path / f"o{o}.{ext}")
        tifffile.imwrite(tmp_path / f"o{o}.tif", rgb, extratags=[(274, 3, 1, o, True)])
        files.append(tmp_path / f"o{o}.tif")
    im = Image.fromarray(rgb)  # an EXIF block that is not TIFF data: as stored
    im.save(tmp_path / "bad_exif.jpg", exif=b"Exif\x00\x00garbage")
    files.append(tmp_path / "bad_exif.jpg")
    for f in files:
        want = {o: images.image_size(f, orient=o) for o in (True, False)}
        assert want[False] == (53, 37), f.name
        assert {o: imagesize.image_size(f, orient=o) for o in (True, False)} == want, f.name
        o = imagesize.image_header(f)[2]
        assert o == (int(f.stem[1]) if f.stem[1] in "12345678" else 1), f.name
        if f.suffix != ".tif":
            with Image.open(f) as im:
                im.load()
                assert o == images.exif_orientation(im), f.name
    # Blender's pixel order (rows bottom to top, RGBA) turned upright as Pillow turns the photo
    stored = np.asarray(Image.open(tmp_path / "o6.jpg").convert("RGBA"), np.float32) / 255
    with Image.open(tmp_path / "o6.jpg") as im:
        from PIL import ImageOps
        upright = np.asarray(ImageOps.exif_transpose(im).convert("RGBA"), np.float32) / 255
    px, w, h = imagesize.upright_pixels(stored[::-1].ravel(), 53, 37, 6)
    assert (w, h) == (37, 53)
    np.testing.assert_array_equal(px.reshape(h, w, 4)[::-1], upright)


def test_describe_follows_exif_orientation_as_the_library(tmp_path, monkeypatch):
    """Photos stored turned with an EXIF orientation (a camera held on its side): LEVIR views are
    the upright photos; COLMAP views the stored pixels unless only the upright ones fit the camera
    (COLMAP ignores EXIF). The description says how to turn each file into its view's image."""
    import pycolmap
    from PIL import Image

    from photo_synth import H, W, write_distorted_model, write_turned_levir_scene

    from dibrgs_core.data.images import oriented, read_image
    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    levir = tmp_path / "levir"
    write_turned_levir_scene(levir, [6, 8, 1, 3])
    desc, scene = describe.describe_scene(levir), read_any_scene(levir, load_depth=False)
    _same_description(desc, scene)
    assert [v["orientation"] for v in desc["views"]] == [6, 8, 1, 3]
    for v in desc["views"]:  # the file's pixels turned as the description says are the library's image
        np.testing.assert_array_equal(oriented(read_image(v["image"], orient=False), v["orientation"]),
                                      scene.views[v["name"]].image)
    # COLMAP: v0 stored as the camera sees it (its EXIF tag is ignored), v1 and v2 stored turned
    colmap = tmp_path / "colmap"
    write_distorted_model(colmap, "PINHOLE", [80.0, 80.0, W / 2, H / 2])
    rec = pycolmap.Reconstruction(str(colmap / "sparse" / "0"))
    for i, im in enumerate(sorted(rec.images.values(), key=lambda im: im.name)):
        png = colmap / "images" / im.name
        photo = Image.open(png)
        photo = photo if i == 0 else photo.transpose(Image.Transpose.ROTATE_90)
        exif = photo.getexif()
        exif[0x0112] = 6
        photo.save(png.with_suffix(".jpg"), quality=95, exif=exif)
        png.unlink()
        im.name = im.name.replace(".png", ".jpg")
    rec.write_text(str(colmap / "sparse" / "0"))
    desc, scene = describe.describe_scene(colmap), read_any_scene(colmap, load_depth=False)
    _same_description(desc, scene)
    assert [v["orientation"] for v in desc["views"]] == [1, 6, 6]
    for v in desc["views"]:
        np.testing.assert_array_equal(oriented(read_image(v["image"], orient=False), v["orientation"]),
                                      scene.views[v["name"]].image)


def _same_description(desc: dict, scene, atol: float = 1e-12) -> None:
    assert desc["train"] == list(scene.train) and desc["test"] == list(scene.test)
    assert desc["layout"] == scene.layout  # the same reader picked
    np.testing.assert_array_equal(desc["origin"], scene.origin)
    assert [v["name"] for v in desc["views"]] == list(scene.views)
    assert len(desc["track"]) == len(scene.track)
    for v in desc["views"]:
        c = scene.views[v["name"]].camera
        got = camera_from_dict(v["camera"])
        assert (got.width, got.height, got.depth_range) == (c.width, c.height, c.depth_range)
        np.testing.assert_array_equal(got.K, c.K)
        np.testing.assert_allclose(got.w2c, c.w2c, rtol=0, atol=atol)
        assert Path(v["image"]).is_file() and Path(v["image"]).stem == v["name"]
    for d, c in zip(desc["track"], scene.track):
        np.testing.assert_array_equal(camera_from_dict(d).w2c, c.w2c)


def test_describe_matches_the_library_on_levir_and_colmap(tiny_scene, tmp_path):
    """The add-on's reader (numpy only) and the library's (Pillow, pycolmap) agree."""
    import pycolmap

    from dibrgs_core.data.load import read_any_scene

    from paths import shared_file

    _same_description(describe.describe_scene(tiny_scene), read_any_scene(tiny_scene, load_depth=False))
    brighton = shared_file("data/brighton_north")
    _same_description(describe.describe_scene(brighton), read_any_scene(brighton, load_depth=False))
    # The same model as COLMAP binary files (written by pycolmap) next to the same images.
    binary = tmp_path / "brighton_bin"
    (binary / "sparse" / "0").mkdir(parents=True)
    (binary / "images").symlink_to(brighton / "images")
    pycolmap.Reconstruction(str(brighton / "sparse" / "0")).write_binary(str(binary / "sparse" / "0"))
    assert colmap_model.model_format(binary / "sparse" / "0") == "bin"
    _same_description(describe.describe_scene(binary), read_any_scene(binary, load_depth=False))
    # Moved 5e6 off its origin (georeferenced): both readers put it in the same frame of its own.
    far = tmp_path / "brighton_far"
    (far / "sparse" / "0").mkdir(parents=True)
    (far / "images").symlink_to(brighton / "images")
    rec = pycolmap.Reconstruction(str(brighton / "sparse" / "0"))
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), np.array([3.0e6, 2.0e6, 5.0e6])))
    rec.write_text(str(far / "sparse" / "0"))
    desc, scene = describe.describe_scene(far), read_any_scene(far, load_depth=False)
    assert np.linalg.norm(scene.origin - [3.0e6, 2.0e6, 5.0e6]) < 10.0
    _same_description(desc, scene, atol=1e-8)


def test_colmap_reader_takes_pinholes(tmp_path):
    import pycolmap

    rec = pycolmap.Reconstruction()
    for cid, (model, params) in enumerate([("SIMPLE_RADIAL", [50.0, 32.0, 30.0, 0.0]),
                                           ("OPENCV", [50.0, 52.0, 32.0, 30.0, 0.1, 0.0, 0.0, 0.0])], start=1):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=64, height=60, params=params,
                                                        camera_id=cid))
        img = pycolmap.Image(name=f"v{cid}.png", camera_id=cid, image_id=cid)
        pose = look_at([10.0 * cid, 5.0, 80.0], [0, 0, 0], [0, 0, 1])
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pose[:3, :4]))
    for write in ("write_text", "write_binary"):
        d = tmp_path / write
        d.mkdir()
        getattr(rec, write)(str(d))
        cams, imgs = colmap_model.read_model(d)
        assert cams[1].pinhole(d) is cams[1]  # no distortion: the camera as it is
        np.testing.assert_allclose(cams[1].K(), [[50, 0, 32], [0, 50, 30], [0, 0, 1]])
        assert cams[2].pinhole(d).model == "PINHOLE"  # distorted: undistorted (next test)
        assert sorted(i.name for i in imgs) == ["v1.png", "v2.png"]
        for im in imgs:
            np.testing.assert_allclose(im.w2c()[:3], rec.images[im.image_id].cam_from_world().matrix(), atol=1e-12)
    (tmp_path / "write_text" / "points3D.txt").unlink()  # not needed: the points are never read
    assert len(colmap_model.read_model(tmp_path / "write_text")[1]) == 2
    (tmp_path / "write_text" / "images.txt").unlink()
    with pytest.raises(InputError, match="images.bin: COLMAP model file missing"):
        colmap_model.read_model(tmp_path / "write_text")


#: (model, distortion) of cameras with lens distortion: mild to strong, down to barrel distortion
#: so strong (-0.4 here) that the border pixels have no inverse and the scale hits its clamp.
_DISTORTIONS = [("SIMPLE_RADIAL", [-0.1]), ("SIMPLE_RADIAL", [0.05]), ("SIMPLE_RADIAL", [-0.4]),
                ("RADIAL", [-0.2, 0.05]), ("OPENCV", [-0.15, 0.03, 0.001, -0.002]), ("OPENCV", [0.1, 0, 0, 0]),
                ("OPENCV", [-0.3, 0.1, 0.01, 0.0]), ("FULL_OPENCV", [-0.1, 0.02, 0.001, 0.001, 0.003, 0.01, 0, 0])]


def _distorted_params(model: str, extra: list[float], W: int, H: int, rng) -> list[float]:
    f = 0.8 * max(W, H)
    cx, cy = W / 2 + rng.normal() * W * 0.01, H / 2 + rng.normal() * H * 0.01
    return ([f, cx, cy] if model in ("SIMPLE_RADIAL", "RADIAL") else [f, f * (1 + 0.01 * rng.normal()), cx, cy]) + extra


def test_distorted_cameras_become_pycolmaps_undistorted_pinholes():
    """Blender's Python has no pycolmap: the numpy undistorted camera is pycolmap's, to the bit, for
    every distorted model, image shape and strength (the library trains with pycolmap's)."""
    import pycolmap

    rng = np.random.default_rng(0)
    for W, H in [(953, 536), (4000, 2250), (1080, 1920), (64, 60), (7, 5)]:
        for model, extra in _DISTORTIONS:
            params = _distorted_params(model, extra, W, H, rng)
            ref = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(),
                                            pycolmap.Camera(model=model, width=W, height=H, params=params))
            got = colmap_model.ColmapCamera(1, model, W, H, np.array(params)).pinhole(Path("model"))
            assert (got.model, got.width, got.height) == ("PINHOLE", ref.width, ref.height), (model, extra, W, H)
            np.testing.assert_array_equal(got.params, ref.params)
            np.testing.assert_array_equal(got.K(), ref.calibration_matrix())
    # The points themselves, inside the image, are where pycolmap unprojects them.
    for model, extra in _DISTORTIONS:
        params = _distorted_params(model, extra, 953, 536, rng)
        cam = colmap_model.ColmapCamera(1, model, 953, 536, np.array(params))
        xy = rng.uniform([100, 50], [853, 486], (200, 2))
        K = cam.K()
        u, v = colmap_model._undistort(model, cam.distortion, (xy[:, 0] - K[0, 2]) / K[0, 0],
                                       (xy[:, 1] - K[1, 2]) / K[1, 1])
        ref = pycolmap.Camera(model=model, width=953, height=536, params=params).cam_from_img(xy)
        np.testing.assert_allclose(np.stack([u, v], 1), np.asarray(ref)[:, :2], rtol=0, atol=1e-9)


def test_describe_matches_the_library_on_distorted_colmap_models(tiny_scene, tmp_path, monkeypatch):
    """A COLMAP project as COLMAP leaves it (SIMPLE_RADIAL is its default model) imports into Blender
    with the cameras training uses (the add-on refused it: "undistort the images first"); fisheye
    models are refused with the library's message."""
    import pycolmap
    from PIL import Image

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    rng = np.random.default_rng(1)
    W, H = 96, 64
    root = tmp_path / "project"
    (root / "images").mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    for cid, (model, extra) in enumerate(_DISTORTIONS[:6], start=1):
        params = _distorted_params(model, extra, W, H, rng)
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=cid))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"v{cid}.png", camera_id=cid, image_id=cid),
                                         pycolmap.Rigid3d(look_at([10.0 * cid, 5.0, 80.0], [0, 0, 0], [0, 0, 1])[:3, :4]))
        Image.fromarray(rng.integers(0, 256, (H, W, 3), dtype=np.uint8)).save(root / "images" / f"v{cid}.png")
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(root / "sparse" / "0"))
    desc, scene = describe.describe_scene(root), read_any_scene(root, load_depth=False)
    _same_description(desc, scene)
    assert len({(v.camera.width, v.camera.height) for v in scene.views.values()}) > 2  # undistorted: sizes differ
    assert all(v["undistorted"] for v in desc["views"])
    assert not any(v["undistorted"] for v in describe.describe_scene(tiny_scene)["views"])
    rec.cameras[2] = pycolmap.Camera(model="OPENCV_FISHEYE", width=W, height=H, camera_id=2,
                                     params=[60.0, 60.0, 48.0, 32.0, 0.1, 0.0, 0.0, 0.0])
    rec.write_binary(str(root / "sparse" / "0"))
    with pytest.raises(InputError) as lib:
        read_any_scene(root, load_depth=False)
    with pytest.raises(InputError) as ours:
        describe.describe_scene(root)
    assert str(ours.value) == str(lib.value) and "OPENCV_FISHEYE is a fisheye model" in str(ours.value)


def test_describe_matches_the_library_on_transforms_layouts(tiny_scene, tmp_path, monkeypatch):
    """transforms.json (shared and per-frame intrinsics, OPENCV distortion) and Blender's part files:
    the add-on's reader gives the library's cameras, split and EXIF handling."""
    import json

    from photo_synth import levir_as_transforms

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    ngp = tmp_path / "ngp"
    levir_as_transforms(tiny_scene, ngp, per_frame=True)
    _same_description(describe.describe_scene(ngp), read_any_scene(ngp, load_depth=False))
    dist = tmp_path / "ns"
    levir_as_transforms(tiny_scene, dist, extra={"k1": -0.2, "k2": 0.04, "p1": 0.001, "p2": 0.0, "k3": 0.01})
    desc, scene = describe.describe_scene(dist), read_any_scene(dist, load_depth=False)
    _same_description(desc, scene)
    assert camera_from_dict(desc["views"][0]["camera"]).width != 64  # undistorted
    parts = tmp_path / "parts"
    levir_as_transforms(tiny_scene, parts)
    data = json.loads((parts / "transforms.json").read_text())
    (parts / "transforms.json").unlink()
    for part, frames in (("train", data["frames"][1::3]), ("test", data["frames"][2::3])):
        (parts / f"transforms_{part}.json").write_text(json.dumps({**data, "frames": frames}))
    desc, scene = describe.describe_scene(parts), read_any_scene(parts, load_depth=False)
    _same_description(desc, scene)
    assert desc["split_source"] == scene.split_source == "transforms_train.json + transforms_test.json"
    assert len(desc["train"]) == 7 and len(desc["test"]) == 7


def test_describe_matches_the_library_on_metashape_exports(tiny_scene, tmp_path, monkeypatch):
    """A Metashape cameras XML in a georeferenced chunk (far from the origin: both move it near) with
    lens distortion: the add-on's reader gives the library's cameras, origin and split."""
    from photo_synth import levir_as_metashape

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "ms"
    levir_as_metashape(tiny_scene, out, calibration={"k1": -0.15, "p1": 0.002})
    xml = (out / "cameras.xml").read_text()  # the chunk moved to geocentric metres
    far = '<translation locked="true">3900000.0 210000.0 5000000.0</translation>'
    (out / "cameras.xml").write_text(xml.replace('<translation locked="true">0.0 0.0 0.0</translation>', far))
    desc, scene = describe.describe_scene(out), read_any_scene(out, load_depth=False)
    assert np.abs(scene.origin).max() > 1e6
    _same_description(desc, scene, atol=1e-9)
    assert all(v["undistorted"] for v in desc["views"])


def test_describe_matches_the_library_on_opensfm_reconstructions(tiny_scene, tmp_path, monkeypatch):
    """An OpenDroneMap project (opensfm/reconstruction.json, two reconstructions) with a Brown
    camera: the add-on's reader gives the library's cameras and split."""
    from photo_synth import levir_as_opensfm

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "odm"
    levir_as_opensfm(tiny_scene, out, camera={"k1": -0.15, "p2": 0.002})
    desc, scene = describe.describe_scene(out), read_any_scene(out, load_depth=False)
    _same_description(desc, scene)
    assert len(desc["views"]) == 21 and all(v["undistorted"] for v in desc["views"])


def test_describe_matches_the_library_on_meshroom_projects(tiny_scene, tmp_path, monkeypatch):
    """A Meshroom project (MeshroomCache/StructureFromMotion/<id>/cameras.sfm, file version 1.2.4,
    a Brown lens, two views without a pose, photos named by absolute path): the add-on's reader
    gives the library's cameras and split."""
    from photo_synth import levir_as_meshroom, sfm_intrinsic

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "mr"
    intr = sfm_intrinsic((1, 2, 4), 64, 64, 70.0, 69.0, 33.0, 31.5, "brown", (-0.15, 0.02, 0.0, 0.001, -0.002))
    levir_as_meshroom(tiny_scene, out, version=(1, 2, 4), photos=tmp_path / "photos", intrinsic=intr, unposed=2)
    desc, scene = describe.describe_scene(out), read_any_scene(out, load_depth=False)
    _same_description(desc, scene)
    assert len(desc["views"]) == 19 and all(v["undistorted"] for v in desc["views"])


def test_describe_matches_the_library_on_openmvg_output(tiny_scene, tmp_path, monkeypatch):
    """An OpenMVG output folder (reconstruction_sequential/sfm_data.json, a pinhole_brown_t2 lens
    named once for two intrinsics, three views without a pose, photos by root_path): the add-on's
    reader gives the library's cameras and split."""
    from photo_synth import levir_as_openmvg

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "omvg"
    levir_as_openmvg(tiny_scene, out, camera="pinhole_brown_t2", disto=(-0.15, 0.02, 0.0, 0.001, -0.002),
                     photos=tmp_path / "photos", unposed=3)
    desc, scene = describe.describe_scene(out), read_any_scene(out, load_depth=False)
    _same_description(desc, scene)
    assert len(desc["views"]) == 18 and all(v["undistorted"] for v in desc["views"])


def test_describe_matches_the_library_on_realitycapture_sidecars(tiny_scene, tmp_path, monkeypatch):
    """Photos with RealityCapture XMP sidecars (a brown3t2 lens): the add-on's reader, which sizes
    the photos from their headers, gives the library's cameras and split."""
    from photo_synth import levir_as_realitycapture

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "rc"
    levir_as_realitycapture(tiny_scene, out, xcr={"DistortionModel": "brown3t2",
                                                  "DistortionCoeficients": "-0.15 0.02 0 0 0.001 0.002"})
    desc, scene = describe.describe_scene(out), read_any_scene(out, load_depth=False)
    _same_description(desc, scene)
    assert len(desc["views"]) == 21 and all(v["undistorted"] for v in desc["views"])


def test_describe_matches_the_library_on_bundler_files(tiny_scene, tmp_path, monkeypatch):
    """A Bundler bundle.out with a radial lens and an unregistered camera: the add-on's reader gives
    the library's cameras and split."""
    from photo_synth import levir_as_bundler

    from dibrgs_core.data.load import read_any_scene

    monkeypatch.setenv("DIBRGS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "bundler"
    levir_as_bundler(tiny_scene, out, k=(-0.1, 0.01), unregistered=1)
    desc, scene = describe.describe_scene(out), read_any_scene(out, load_depth=False)
    _same_description(desc, scene)
    assert len(desc["views"]) == 21 and all(v["undistorted"] for v in desc["views"])


def _refusals(root: Path) -> tuple[str, str]:
    """The library's and the add-on reader's InputError lines for the scene folder ``root``."""
    from dibrgs_core.data.load import read_any_scene

    with pytest.raises(InputError) as lib:
        read_any_scene(root, load_depth=False)
    with pytest.raises(InputError) as ours:
        describe.describe_scene(root)
    return str(lib.value), str(ours.value)


def test_describe_rejects_bad_folders_like_the_library(tiny_scene, tmp_path):
    cases = {}
    cases["empty"] = tmp_path / "empty"
    cases["empty"].mkdir()
    bad_cam = tmp_path / "bad_cam"
    shutil.copytree(tiny_scene, bad_cam, ignore=shutil.ignore_patterns("Depths", "Track"))
    (bad_cam / "Cams" / "003.txt").write_text("extrinsic 1 0 0 0 1 0 0 0 1 intrinsic 1 0 0 1")
    cases["bad_cam"] = bad_cam
    no_cam = tmp_path / "no_cam"
    shutil.copytree(tiny_scene, no_cam, ignore=shutil.ignore_patterns("Depths", "Track"))
    (no_cam / "Cams" / "004.txt").unlink()
    cases["no_cam"] = no_cam
    for name, root in cases.items():
        lib, ours = _refusals(root)
        assert ours == lib, name


def test_describe_rejects_bad_colmap_scenes_like_the_library(tmp_path):
    """A COLMAP scene as users break it (a listed photo missing, a photo of another size than its
    camera, no image folder, an image of a camera the model lacks): the add-on's reader stops with
    the library's line."""
    from PIL import Image

    from paths import shared_file

    brighton = shared_file("data/brighton_north")

    def copy(name: str) -> Path:
        root = tmp_path / name
        shutil.copytree(brighton / "sparse", root / "sparse")
        (root / "images").mkdir()
        for f in (brighton / "images").iterdir():
            (root / "images" / f.name).symlink_to(f)
        return root

    cases = {"photo_missing": copy("photo_missing"), "other_size": copy("other_size"),
             "no_images": copy("no_images"), "camera_missing": copy("camera_missing")}
    (cases["photo_missing"] / "images" / "DJI_0019.png").unlink()
    (cases["other_size"] / "images" / "DJI_0019.png").unlink()
    Image.new("RGB", (64, 48)).save(cases["other_size"] / "images" / "DJI_0019.png")
    shutil.rmtree(cases["no_images"] / "images")
    images_txt = cases["camera_missing"] / "sparse" / "0" / "images.txt"
    lines = images_txt.read_text().splitlines()
    first = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    f = lines[first].split()
    lines[first] = " ".join(f[:8] + ["77"] + f[9:])  # CAMERA_ID of the first image
    images_txt.write_text("\n".join(lines) + "\n")
    lines = {name: _refusals(root) for name, root in cases.items()}
    for name, (lib, ours) in lines.items():
        assert ours == lib, name
    model = cases["camera_missing"] / "sparse" / "0"  # not pycolmap's "Rig with ID 77 does not exist"
    assert lines["camera_missing"][0] == f"{model}: image DJI_0018.png refers to camera 77, which is not in the model"


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


def _tracked_files() -> list[str]:
    r = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"not a git checkout: {r.stderr.strip()}")
    return [f for f in r.stdout.splitlines() if (REPO / f).is_file()]


def test_build_ships_only_the_allow_listed_paths(tmp_path):
    """A working tree with a venv, scenes, runs, caches and build products: the zip holds the add-on only."""
    src = tmp_path / "tree"
    files = _tracked_files()
    for f in files:
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / f, src / f)
    junk = ["venv/lib/python3.11/site-packages/torch/__init__.py", "venv/bin/python", "city64/Images/000.png",
            "city64/Cams/000.txt", "runs/demo/checkpoint.pt", "brighton/sparse/0/cameras.txt", "notes.txt",
            "dibrgs-0.1.0.zip", ".venv/pyvenv.cfg", "addon/__pycache__/panel.cpython-311.pyc",
            "dibrgs_core/__pycache__/cameras.cpython-311.pyc", "dibrgs_core/render/csrc/build/rasterize.o",
            "dibrgs_core/render/csrc/build/ext.so", "dibrgs.egg-info/PKG-INFO", "addon/.DS_Store"]
    for f in junk:
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        (src / f).write_bytes(b"junk")
    zpath = tmp_path / "dibrgs.zip"
    r = subprocess.run([sys.executable, str(_blender_ext()), "build", "--source-dir", str(src), "--output-filepath",
                        str(zpath)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    names = sorted(zipfile.ZipFile(zpath).namelist())
    want = sorted(f for f in files if f in ("__init__.py", "blender_manifest.toml")
                  or (f.startswith(("addon/", "dibrgs_core/")) and "/." not in f))
    assert names == want, (set(names) ^ set(want))
    for needed in ("addon/batch.py", "addon/_core.py", "dibrgs_core/bridge/describe.py",
                   "dibrgs_core/render/csrc/rasterize.cpp"):
        assert needed in names
