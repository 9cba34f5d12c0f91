"""scripts/eval_real_flight.py: held-out PSNR split by how many training photos see a pixel."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dibrgs_core.data.ply import read_ply

REPO = Path(__file__).resolve().parents[2]


def test_scores_a_run_by_visibility_and_draws_its_figures(scene24, finished_run, tmp_path):
    pts, _ = read_ply(finished_run / "init" / "points.ply")
    ref = tmp_path / "reference_points.txt"
    ref.write_text("# x y z\n" + "\n".join(" ".join(f"{v:.6f}" for v in p) for p in pts[:500]) + "\n")
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_real_flight.py"), str(scene24), str(finished_run),
                          "--reference", str(ref), "--json", str(out / "r.json"), "--png", str(out / "views.png"),
                          "--curves", str(out / "curves.png"), "--warp", "--md", str(out / "t.md")],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    r = json.loads((out / "r.json").read_text())
    (run,) = r["runs"]
    assert run["method"] == "dibrgs" and np.isfinite(run["psnr"])
    assert 0.0 < run["seen_fraction"] <= 1.0 and np.isfinite(run["seen"])
    assert abs(sum(run["fractions"][k] for k in ("one", "two_plus")) - run["seen_fraction"]) < 1e-6
    assert (out / "views.png").stat().st_size > 1000 and (out / "curves.png").stat().st_size > 1000
    # The warp baseline: the training photos warped with the run's cloud cover part of the seen
    # pixels, and both it and the run are scored there.
    (wb,) = r["warp"]
    assert wb["work"] == str(finished_run) and 0.0 < wb["covered_seen"] <= 1.0 + 1e-9
    assert np.isfinite(wb["warp"]["seen"]) and np.isfinite(wb["model"]["seen"])
    assert "warped into the held-out cameras" in (out / "t.md").read_text()
    # A missing reference file is one line naming it.
    bad = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_real_flight.py"), str(scene24),
                          str(finished_run), "--reference", str(tmp_path / "none.txt")],
                         capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and "none.txt" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_generated_scene_is_scored_with_its_true_depth(scene24, finished_run, tmp_path):
    """Without reference points a scene's depth maps decide what a training photo sees: the same
    figures as scripts/error_by_visibility.py on the same run; no depth either is one clear line."""
    import shutil

    assert not (scene24 / "reference_points.txt").exists()
    out = tmp_path / "r.json"
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_real_flight.py"), str(scene24),
                          str(finished_run), "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    r = json.loads(out.read_text())
    assert r["visibility"] == "true depth" and r["reference"] is None
    (run,) = r["runs"]
    ev = tmp_path / "v.json"
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "error_by_visibility.py"), str(scene24),
                          str(finished_run), "--json", str(ev)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    (other,) = json.loads(ev.read_text())["runs"]
    assert run["seen"] == pytest.approx(other["seen"], abs=1e-6)
    assert run["psnr"] == pytest.approx(other["whole_image"], abs=1e-6)
    for g in ("one", "two_plus", "unseen"):
        assert run["groups"][g] == pytest.approx(other["psnr"][g], abs=1e-6)
    bare = tmp_path / "bare"
    shutil.copytree(scene24, bare, ignore=shutil.ignore_patterns("Depths"))
    bad = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_real_flight.py"), str(bare),
                          str(finished_run)], capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and "no depth map" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.slow  # 6-8 s (a second run trained in a subprocess); keeps the fast tier under 3 minutes
def test_runs_of_other_splits_are_each_scored_by_their_own_training_photos(scene24, finished_run, tmp_path):
    """Two runs of other splits that hold out some of the same photos: scored together, each gets
    the figures it gets alone (which pixels count as seen is the run's own training photos' matter)."""
    from run_synth import QUICK, dibrgs

    other = tmp_path / "other"
    rc, err = dibrgs("train", scene24, "--out", other, *QUICK, "--iterations", "6", "--train", "003,010,017")
    assert rc == 0, err

    def score(*works, md=None):
        out = tmp_path / f"r{len(works)}.json"
        res = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_real_flight.py"), str(scene24),
                              *map(str, works), "--json", str(out), *(["--md", str(md)] if md else [])],
                             capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr
        return {Path(r["work"]).name: r for r in json.loads(out.read_text())["runs"]}

    together = score(finished_run, other, md=tmp_path / "t.md")
    alone = score(other)["other"]
    assert together["other"]["seen_fraction"] == pytest.approx(alone["seen_fraction"], abs=1e-12)
    for g in ("one", "two_plus", "unseen"):
        assert together["other"]["groups"][g] == pytest.approx(alone["groups"][g], abs=1e-9)
    # The splits see different shares of the held-out pixels: the table gives each run's own.
    assert together["other"]["fractions"] != together[finished_run.name]["fractions"]
    assert "differ in split" in (tmp_path / "t.md").read_text()
    # scripts/error_by_visibility.py on the same runs: each on its own split, as above.
    ev = tmp_path / "v.json"
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "error_by_visibility.py"), str(scene24),
                          str(finished_run), str(other), "--json", str(ev)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    by_vis = {Path(r["work"]).name: r for r in json.loads(ev.read_text())["runs"]}
    for name, r in together.items():
        for g in ("one", "two_plus", "unseen"):
            assert by_vis[name]["psnr"][g] == pytest.approx(r["groups"][g], abs=1e-6)
    assert "splits differ" in res.stdout
