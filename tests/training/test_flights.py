"""A generated mapping flight end to end: the scene generator's grid flight (nine nadir photos on
three strips, split.json on the middle photo of each) through `dibrgs train` and
`scripts/eval_real_flight.py`, as a user's drone flight would go."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]

pytest.importorskip("bpy")


@pytest.mark.slow
def test_a_grid_flight_trains_along_its_strips(tmp_path):
    from dibrgs_core.synth.writer import make_scene

    scene = make_scene("village", 48, 0, tmp_path / "grid", samples=4, flight="grid")
    work = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "dibrgs_core", "train", str(scene), "--out", str(work), "--preset",
                        "test", "--iterations", "120"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((work / "report.json").read_text())
    values, decisions = report["values"], {d["step"]: d for d in report["decisions"]}
    assert values["scene"]["train"] == ["001", "004", "007"]
    # One photo from each strip: the training cameras lie on one line across the strips.
    assert decisions["pseudo_trajectory"]["applied"]
    assert decisions["pseudo_trajectory"]["reason"].startswith("strips: ")
    pv = values["pseudo_views"]
    assert pv["kept"] > 0 and pv["mean_warped"] > 0.5, pv
    out = tmp_path / "e.json"
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_real_flight.py"), str(scene), str(work),
                        "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    (run,) = json.loads(out.read_text())["runs"]
    # About a third of each held-out photo lies past the strips' ends; what a photo saw is rendered
    # far better than what none did.
    assert 0.4 < run["seen_fraction"] < 0.8
    assert np.isfinite(run["seen"]) and run["seen"] > run["groups"]["unseen"] + 3.0
