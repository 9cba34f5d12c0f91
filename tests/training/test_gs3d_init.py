"""The 3DGS baseline's starting Gaussians: the training views' SfM points (as 3DGS starts) when
SfM finds enough of them, else those plus random points in the viewed volume; the SfM points'
cache in ``WORK/init`` is keyed by the views, made again when it belongs to other views or is
unreadable."""
from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest
import torch
from paths import shared_file

from dibrgs_core.models.gs3d import rgb_to_sh
from dibrgs_core.training.config import preset
from dibrgs_core.training.trainer import Trainer

# The real flight: SfM finds hundreds of points in its three training photos (its split.json);
# the generated test scenes' 24-64 px photos give SIFT too little to match.
REAL = shared_file("data/brighton_north")


def _cfg(min_sfm_points: int | None = None):
    cfg = preset("test")
    cfg.method = "3dgs"
    cfg.pseudo.mode = "off"
    if min_sfm_points is not None:
        cfg.gs3d.min_sfm_points = min_sfm_points
    cfg.gs3d.random_points = 500
    return cfg


def _decision(tr: Trainer, step: str):
    return next(d for d in reversed(tr.report.decisions) if d.step == step)


@pytest.fixture(scope="module")
def sfm_init(tmp_path_factory):
    """``init/`` of a 3DGS run on the real flight: its SfM points triangulated once."""
    work = tmp_path_factory.mktemp("gs3d") / "base"
    Trainer(REAL, work, _cfg()).setup()
    return work / "init"


def _work(sfm_init, path):
    shutil.copytree(sfm_init, path / "init")
    return path


def _cache(work):
    with np.load(work / "init" / "sfm_points.npz") as d:
        return d["points"], d["colors"], str(d["key"])


def test_3dgs_starts_from_the_sfm_points_when_there_are_enough(sfm_init, tmp_path):
    tr = Trainer(REAL, _work(sfm_init, tmp_path / "w"), _cfg())
    tr.setup()
    pts, cols, _ = _cache(tmp_path / "w")
    assert len(pts) >= tr.cfg.gs3d.min_sfm_points and cols.dtype == np.uint8
    d = _decision(tr, "sfm_init")
    assert d.applied and f"starts from {len(pts)} SfM points" in d.reason
    model = tr.method.model
    assert torch.equal(model.means.detach(), torch.as_tensor(pts, dtype=torch.float32))
    # colours as 3DGS takes them: the points' 8-bit colours over 255, as degree-0 SH
    want = rgb_to_sh(torch.as_tensor(cols / 255.0, dtype=torch.float32))
    torch.testing.assert_close(model.sh_dc.detach()[:, 0], want)

    # Too few for the threshold: the same points and random ones in the viewed volume.
    tr2 = Trainer(REAL, _work(sfm_init, tmp_path / "w2"), _cfg(min_sfm_points=len(pts) + 1))
    tr2.setup()
    d2 = _decision(tr2, "sfm_init")
    assert not d2.applied and f"only {len(pts)} points" in d2.reason and "500 random points" in d2.reason
    means = tr2.method.model.means.detach()
    assert means.shape[0] == len(pts) + 500
    torch.testing.assert_close(means[: len(pts)], torch.as_tensor(pts, dtype=torch.float32))


@pytest.mark.parametrize("damage", ["other_views", "garbage"])
def test_the_sfm_points_cache_is_made_again_when_it_is_not_this_runs(sfm_init, tmp_path, caplog, damage):
    work = _work(sfm_init, tmp_path / "w")
    pts, cols, key = _cache(work)
    cache = work / "init" / "sfm_points.npz"
    if damage == "other_views":  # another split's points under another key
        np.savez(cache, points=pts[:3] + 100.0, colors=cols[:3], key=np.array("0" * len(key)))
        says = "was made from other views or options; triangulating again"
    else:
        cache.write_bytes(b"not a numpy file")
        says = "unreadable"
    with caplog.at_level(logging.INFO, logger="dibrgs"):
        tr = Trainer(REAL, work, _cfg())
        tr.setup()
    assert says in caplog.text and str(cache) in caplog.text
    again, again_cols, again_key = _cache(work)
    assert again_key == key
    np.testing.assert_array_equal(again, pts)
    np.testing.assert_array_equal(again_cols, cols)
    assert torch.equal(tr.method.model.means.detach(), torch.as_tensor(pts, dtype=torch.float32))
