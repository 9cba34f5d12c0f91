"""Weight-free geometry on a real drone flight (shared/data/brighton_north), checked against its
reference points by scripts/eval_geometry_real.py (a real subprocess; the pipeline never reads them)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from paths import REPO, shared_file


@pytest.mark.slow
def test_brighton_north_geometry_targets(tmp_path):
    """Issue 14's geometry targets on the real flight with its split, at long side 476: the dense
    initialisation covers >= 40 % of the training pixels and its depth at the reference points is
    within 2 % (median). The plane sweep itself must carry a real share (on a sibling block it kept
    0-2 % before), and the height-field completion must stay near the ground truth too."""
    scene = shared_file("data/brighton_north/reference_points.txt").parent
    out = tmp_path / "geom.json"
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_geometry_real.py"), str(scene),
                        "--long-side", "476", "--json", str(out)], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(out.read_text())
    assert res["train"] == ["DJI_0019", "DJI_0028", "DJI_0031"]  # from split.json
    assert res["size"] == [476, 268]
    assert res["coverage"] >= 0.40
    assert res["median_rel_error"] <= 0.02
    assert res["matched_coverage"] >= 0.35
    assert res["median_rel_error_matched"] <= 0.01
    assert res["median_rel_error_completed"] <= 0.03
    assert res["ref_samples"] > 2000
    for v in res["views"]:
        assert v["matched"] > 0.15, v
