"""The benchmark machinery: a tiny suite through a local Ray instance, resume, pages."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dibrgs_core.bench import pages, runner as bm
from paths import REPO


@pytest.mark.slow
def test_tiny_suite_through_local_ray_survives_worker_death(tmp_path, tiny_scene):
    ray = pytest.importorskip("ray", reason="ray is an optional extra: pip install -e '.[ray]'")
    work = tmp_path / "bench"
    # Reuse the session's tiny scene instead of rendering it again.
    scene_dir = work / "scenes" / "city64_levir_s0"
    scene_dir.parent.mkdir(parents=True)
    os.symlink(tiny_scene, scene_dir)

    def flaky_job(spec, work_root, lpips=None, threads=None):
        """run_one, but the first attempt of each run kills its own worker process.

        Defined here so Ray pickles it by value: workers cannot import test modules."""
        marker = Path(work_root) / f"attempted_{spec.key}"
        if not marker.exists():
            marker.write_text("1")
            os._exit(1)  # a dying worker, not an exception
        assert threads == 1  # num_cpus=1: one torch thread a task
        return bm.run_one(spec, work_root, lpips, threads)

    suite = bm.make_suite("tiny", preset="test", iterations=60)
    results = work / "results"
    try:
        bm.run_ray(bm.pending(suite, results), work, results, "local", num_cpus=1, job=flaky_job)
    finally:
        ray.shutdown()
    assert bm.pending(suite, results) == []  # both runs finished despite the killed workers
    assert all((work / f"attempted_{s.key}").exists() for s in suite.runs)
    docs = tmp_path / "docs"
    res = pages.write_pages(results, suite, docs, "python scripts/benchmark.py --suite tiny")
    assert len(res) == 2
    rows = list(csv.DictReader(open(docs / "benchmarks" / "results.csv")))
    assert {r["method"] for r in rows} == {"dibrgs", "no-pseudo"}
    for r in rows:
        assert 5.0 < float(r["psnr"]) < 60.0
        assert float(r["train_seconds"]) > 0
        # curve.csv keeps milliseconds; train_seconds is not rounded.
        assert 0 <= float(r["plateau_seconds"]) <= float(r["train_seconds"]) + 5e-4
    assert (docs / "benchmarks" / "curves.png").stat().st_size > 1000
    md = (docs / "benchmarks.md").read_text()
    assert "Benchmark suite `tiny`" in md and "w/o Pseudo Views" in md
    # Rewriting the pages replaces the suite's section instead of appending a second one.
    pages.write_pages(results, suite, docs, "again")
    assert (docs / "benchmarks.md").read_text().count("Benchmark suite `tiny`") == 1


def _curve(points):
    return [{"seconds": t, "iteration": i, "psnr": p, "ssim": 0.5} for i, (t, p) in enumerate(points)]


def test_plateau_is_where_the_curve_stays_near_its_final_value():
    """Rising then flat: the first point within 0.5 dB of the end. A peak that drifts down counts
    from when it got near the end value and stayed. A dip back below restarts the count. With a
    subset of views on the earlier points, the final model's PSNR on those views is the reference."""
    assert bm.plateau_seconds([]) is None
    assert bm.plateau_seconds(_curve([(0, 8.0), (30, 15.0), (60, 19.7), (90, 20.0), (120, 20.1)])) == 60
    assert bm.plateau_seconds(_curve([(0, 8.0), (30, 21.0), (60, 20.5), (90, 20.0)])) == 30
    assert bm.plateau_seconds(_curve([(0, 8.0), (30, 20.0), (60, 18.0), (90, 20.0), (120, 20.2)])) == 90
    assert bm.plateau_seconds(_curve([(0, 8.0), (30, 20.0)])) == 30
    # Points on 4 views read ~2 dB above the all-view final value: compared with the final model on those views.
    sub = _curve([(0, 8.0), (30, 20.0), (60, 21.9), (90, 18.2)])
    assert bm.plateau_seconds(sub) == 30 and bm.plateau_seconds(sub, final_psnr=22.0) == 60


def _result(folder: Path, scene: str, method: str, points, on_point_views=None, wall=None) -> None:
    curve = _curve(points)
    row = {"scene": scene, "method": method, "psnr": curve[-1]["psnr"], "train_seconds": curve[-1]["seconds"],
           "plateau_seconds": bm.plateau_seconds(curve, on_point_views)}
    res = {"spec": {"kind": scene[:-3], "resolution": int(scene[-3:]), "method": method}, "row": row,
           "curve": curve, "final_psnr_on_point_views": on_point_views}
    if wall is not None:
        res["wall_seconds"] = wall
    (folder / "results" / "runs").mkdir(parents=True, exist_ok=True)
    (folder / "results" / "runs" / f"{scene}__{method}.json").write_text(json.dumps(res))


def test_compare_benchmarks_script_pairs_runs_and_draws_them(tmp_path):
    """Runs in both folders are paired by scene and method; a run in one only is left out; the
    subset-view curve ends on the final model's PSNR on those views, the all-view point apart."""
    a, b = tmp_path / "before", tmp_path / "after"
    _result(a, "city256", "dibrgs", [(0, 8.0), (30, 17.0), (60, 19.8), (90, 20.0)], wall=200)
    _result(a, "city256", "3dgs", [(0, 8.0), (30, 14.0)])
    _result(b, "city256", "dibrgs", [(0, 8.0), (30, 21.0), (60, 21.4), (90, 20.1)], on_point_views=21.3, wall=120)
    res = json.loads((b / "results" / "runs" / "city256__dibrgs.json").read_text())
    xs, ys, final = pages.curve_points(res)
    assert xs == [30, 60, 90] and ys == [21.0, 21.4, 21.3] and final == (90, 20.1)
    md, png = tmp_path / "cmp.md", tmp_path / "cmp.png"
    script = str(REPO / "scripts" / "compare_benchmarks.py")
    out = subprocess.run([sys.executable, script, str(a), str(b), "--labels", "old", "new", "--md", str(md),
                          "--png", str(png)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    rows = [ln for ln in md.read_text().splitlines() if ln.startswith("| city")]
    assert rows == ["| city256__dibrgs | 20.00 | 20.10 | 90 | 90 | 60 | 30 | 200 | 120 |"]
    assert "PSNR old" in md.read_text() and png.stat().st_size > 1000
    empty = subprocess.run([sys.executable, script, str(a), str(tmp_path / "nothing")], capture_output=True,
                           text=True, timeout=300)
    assert empty.returncode != 0 and "no finished runs in" in empty.stderr and "nothing" in empty.stderr


def test_compare_benchmarks_script_compares_run_folders(finished_run, tmp_path):
    """``dibrgs train`` run folders pair by scene and method, given as folders of run folders or
    as two run folders: PSNR from ``metrics.json`` where ``dibrgs eval`` wrote one, else the
    curve's last point (every held-out view); folders with no run in common are refused in one
    line."""
    import shutil

    from run_synth import dibrgs

    evaluated, plain = tmp_path / "a" / "run", tmp_path / "b" / "run"
    shutil.copytree(finished_run, evaluated)
    shutil.copytree(finished_run, plain)
    rc, err = dibrgs("eval", evaluated, "--threads", "1")
    assert rc == 0, err
    metrics = json.loads((evaluated / "metrics.json").read_text())
    curve = bm.read_curve(plain / "curve.csv")
    assert len(curve) >= 2 and not (plain / "metrics.json").exists()
    plateau = bm.plateau_seconds(curve, bm._final_on_point_views(plain))
    script = str(REPO / "scripts" / "compare_benchmarks.py")
    for i, (x, y) in enumerate([(evaluated.parent, plain.parent), (evaluated, plain)]):
        md, png = tmp_path / f"cmp{i}.md", tmp_path / f"cmp{i}.png"
        out = subprocess.run([sys.executable, script, str(x), str(y), "--md", str(md), "--png", str(png)],
                             capture_output=True, text=True, timeout=300, check=False)
        assert out.returncode == 0, out.stderr
        rows = [ln.split(" | ") for ln in md.read_text().splitlines() if ln.startswith("| s24__")]
        assert len(rows) == 1 and rows[0][0] == "| s24__dibrgs"
        assert rows[0][1] == f"{metrics['psnr']:.2f}" and rows[0][2] == f"{curve[-1]['psnr']:.2f}"
        assert rows[0][5] == rows[0][6] == f"{plateau:.0f}"
        assert png.stat().st_size > 1000
    bench = tmp_path / "bench"
    _result(bench, "city256", "dibrgs", [(0, 8.0), (30, 17.0)])
    apart = subprocess.run([sys.executable, script, str(bench), str(plain.parent)], capture_output=True, text=True,
                           timeout=300, check=False)
    assert apart.returncode != 0 and "have no run in common (city256_levir_s0__dibrgs against s24__dibrgs)" in apart.stderr
    assert len(apart.stderr.strip().splitlines()) == 1
    # A run folder of the benchmark's generated scene (as `dibrgs train` on its scenes/ folder) pairs with it.
    cfg = json.loads((plain / "config.json").read_text())
    cfg["scene"] = str(bench / "scenes" / bm.scene_path(bm.RunSpec("city", 256, "dibrgs"), "").name)
    (plain / "config.json").write_text(json.dumps(cfg))
    md = tmp_path / "mixed.md"
    mixed = subprocess.run([sys.executable, script, str(bench), str(plain.parent), "--md", str(md)],
                           capture_output=True, text=True, timeout=300, check=False)
    assert mixed.returncode == 0, mixed.stderr
    rows = [ln.split(" | ") for ln in md.read_text().splitlines() if ln.startswith("| city")]
    assert [r[0] for r in rows] == ["| city256_levir_s0__dibrgs"] and rows[0][2] == f"{curve[-1]['psnr']:.2f}"


def test_local_jobs_run_side_by_side_and_a_failure_does_not_lose_the_others(tmp_path):
    """run_local with jobs=2: the runs overlap in time, a failing run is reported once the
    others are done, and the finished ones are saved (so a restart only redoes the failure)."""
    import threading
    import time

    suite = bm.make_suite("quick", preset="test", iterations=10)
    results = tmp_path / "results"
    spans: dict[str, tuple[float, float]] = {}
    lock = threading.Lock()

    def job(spec, work_root, lpips=None, threads=None):
        assert threads == max(1, len(os.sched_getaffinity(0)) // 2)  # jobs=2 share the cores
        t0 = time.perf_counter()
        time.sleep(0.3)
        with lock:
            spans[spec.key] = (t0, time.perf_counter())
        if spec.method == "no-pseudo":
            raise RuntimeError("training failed")
        return {"spec": {"kind": spec.kind, "resolution": spec.resolution, "method": spec.method,
                         "seed": spec.seed, "preset": spec.preset, "iterations": spec.iterations,
                         "orbit": spec.orbit},
                "row": {"scene": spec.scene, "method": spec.method, "psnr": 20.0}, "curve": [], "host": "h"}

    with pytest.raises(RuntimeError, match="1 of 3 runs failed"):
        bm.run_local(suite.runs, tmp_path, results, jobs=2, job=job, progress=lambda m: None)
    assert [s.method for s in bm.pending(suite, results)] == ["no-pseudo"]
    (a0, a1), (b0, b1) = spans["city128__3dgs"], spans["city128__dibrgs"]
    assert a0 < b1 and b0 < a1  # the first two ran at the same time


@pytest.mark.slow
def test_scenes_render_from_several_job_threads(tmp_path):
    """Local jobs are threads and bpy crashes when driven from two threads of one process, so
    scenes render in child processes: two threads asking for two scenes both get complete ones."""
    from concurrent.futures import ThreadPoolExecutor

    specs = [bm.RunSpec("village", 12, "dibrgs"), bm.RunSpec("mountain", 12, "dibrgs", orbit="wide")]
    with ThreadPoolExecutor(2) as pool:
        dirs = list(pool.map(lambda s: bm.ensure_scene(s, bm.scene_path(s, tmp_path)), specs))
    for d, s in zip(dirs, specs):
        assert len(list((d / "Images").glob("*.png"))) == 21
        info = __import__("json").loads((d / "scene.json").read_text())
        assert info["kind"] == s.kind and info["orbit_name"] == s.orbit
    assert not list((tmp_path / "scenes").glob("*.tmp*"))
