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
