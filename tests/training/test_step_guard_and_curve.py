"""The trainer's cheap guards and curve points: non-finite gradients never reach the parameters
(injected NaN), curve points evaluate a fixed subset of held-out views (all at the end) outside
the training clock."""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from threads import torch_threads

from dibrgs_core.training import curve as curve_module
from dibrgs_core.training.config import preset
from dibrgs_core.training.curve import curve_views, evaluate_heldout
from dibrgs_core.render import set_backend
from dibrgs_core.training.guard import all_finite, make_finite
from dibrgs_core.training.trainer import Trainer

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def init_cache(synth, tmp_path_factory) -> Path:
    """``init/`` (geometry and SfM points) made once; every run below starts from a copy."""
    work = tmp_path_factory.mktemp("runs") / "base"
    for method in ("dibrgs", "3dgs"):
        Trainer(synth, work, _cfg(1, method)).setup()
    return work / "init"


def _work(init_cache: Path, work: Path) -> Path:
    shutil.copytree(init_cache, work / "init")
    return work


def _cfg(iterations: int, method: str = "dibrgs"):
    cfg = preset("test")
    cfg.iterations = iterations
    cfg.method = method
    cfg.curve_every_s = 1e9  # points at the start and the end only
    cfg.model.max_init_anchors = 300
    cfg.pseudo.mode = "off"
    return cfg


@pytest.mark.parametrize("backend", ["fast", "reference"])
def test_all_finite(backend):
    """Both paths (one C++ pass over all tensors; a torch sum a tensor) give the exact answer."""
    set_backend(backend)
    try:
        big = torch.full((10,), 3e38)  # finite, but its sum overflows: the exact test decides
        assert all_finite([]) and all_finite([None, torch.ones(3)]) and all_finite([big, torch.zeros(0, 3)])
        assert all_finite([torch.full((3,), 1e308, dtype=torch.float64), torch.full((40000,), -3.4e38)])
        for dtype in (torch.float32, torch.float64):
            for bad in (math.nan, math.inf, -math.inf):
                for pos in (0, 517, 39999):  # first, middle, last element of the last chunk
                    t = torch.ones(40000, dtype=dtype)
                    t[pos] = bad
                    assert not all_finite([torch.ones(4), None, t, torch.ones(7, dtype=torch.float64)])
        t = torch.ones(5, 3)
        t[0, 0], t[1, 1] = math.inf, -math.inf  # +inf and -inf in one tensor
        assert not all_finite([t])
        u = torch.ones(6, 8)
        u[5, 0] = math.nan
        assert not all_finite([u.t()])  # not contiguous
        assert not all_finite([u[:, :1]]) and all_finite([u[:5]])
        # Other dtypes beside float32 ones (the extension declines them; torch's test decides).
        h = torch.ones(9, dtype=torch.float16)
        assert all_finite([torch.ones(3), h, torch.arange(4)])
        h[4] = math.inf
        assert not all_finite([torch.ones(3), h])
    finally:
        set_backend(None)


def test_make_finite_mends_only_the_tensors_that_need_it():
    """After a step whose arithmetic overflowed: NaN becomes 0 and infinities +-1e6 in place, the
    finite tensors are left as they were (the same values and version), and it says so."""
    good = torch.randn(40000)
    bad = torch.ones(2, 3)
    bad[0, 1], bad[1, 0], bad[1, 2] = math.nan, math.inf, -math.inf
    keep, version = good.clone(), good._version
    assert make_finite([good, bad])
    assert torch.equal(bad, torch.tensor([[1.0, 0.0, 1.0], [1e6, 1.0, -1e6]]))
    assert torch.equal(good, keep) and good._version == version
    assert not make_finite([good, bad]) and torch.equal(good, keep)


class FaultyTrainer(Trainer):
    """A real run with a fault at its chosen iterations (``poison``); keeps the model's parameters
    as set up, to tell which steps reached them."""

    poison: set[int] = set()

    def setup(self):
        ck = super().setup()
        self.snapshot = {n: p.detach().clone() for n, p in self.method.model.named_parameters()}
        return ck


class PoisonedTrainer(FaultyTrainer):
    """Chosen backward passes get a NaN in one element of a parameter's gradient (a gradient hook on
    the model's parameter, as a failing backward would produce)."""

    def setup(self):
        ck = super().setup()
        self.backward_calls = 0
        target = next(p for p in self.method.parameters() if p.requires_grad)

        def hook(g):
            self.backward_calls += 1
            if self.backward_calls in self.poison:
                g = g.clone()
                g.view(-1)[0] = math.nan
            return g

        target.register_hook(hook)
        return ck


class NanTargetTrainer(FaultyTrainer):
    """Chosen iterations supervise a view with a NaN pixel in its target image (a photo read
    wrong), so the loss itself is not finite."""

    def _next_frame(self, it, pseudo):
        frame = super()._next_frame(it, pseudo)
        if it not in self.poison:
            return frame
        image = frame.image.clone()
        image[0, 0, 0] = math.nan
        return dataclasses.replace(frame, image=image)


def test_all_finite_split_over_two_threads():
    """Above SERIAL_BELOW elements the C++ check runs as two equal runs of elements that cut a tensor
    anywhere (csrc/chunks.h; here 60,005 elements, cut inside the 5-element tensor): a bad value is
    found in either run and on either side of the cut."""
    set_backend("fast")
    try:
        with torch_threads(2):
            assert all_finite([torch.ones(30000), torch.ones(5), torch.ones(30000)])
            for t, pos in ((0, 29999), (1, 1), (1, 2), (2, 0), (2, 29999)):
                ts = [torch.ones(30000), torch.ones(5), torch.ones(30000)]
                ts[t][pos] = math.nan
                assert not all_finite(ts), (t, pos)
    finally:
        set_backend(None)


@pytest.mark.parametrize("method", ["dibrgs", "3dgs"])
@pytest.mark.parametrize("fault,says", [(PoisonedTrainer, "gradients are not finite"),
                                        (NanTargetTrainer, "loss is not finite")], ids=["gradient", "loss"])
def test_non_finite_steps_never_reach_the_parameters(synth, init_cache, tmp_path, caplog, method, fault, says):
    t = fault(synth, _work(init_cache, tmp_path / "all"), _cfg(6, method))
    t.poison = set(range(1, 100))  # every step
    with caplog.at_level("WARNING", logger="dibrgs"):
        res = t.run()
    assert res.skipped_steps == 6 and caplog.text.count(f"{says}; step skipped") == 6
    # (3DGS's scheduled opacity reset changes opacities without any gradient)
    for n, p in t.method.model.named_parameters():
        if not (method == "3dgs" and n == "opacity"):
            assert torch.equal(p, t.snapshot[n]), f"{n} changed although every step was non-finite"
    t2 = fault(synth, _work(init_cache, tmp_path / "one"), _cfg(6, method))
    t2.poison = {3}
    res2 = t2.run()
    assert res2.skipped_steps == 1
    assert all(torch.isfinite(p).all() for p in t2.method.parameters())
    assert any(not torch.equal(p, t2.snapshot[n]) for n, p in t2.method.model.named_parameters())


def test_curve_points_use_a_fixed_subset_and_all_views_at_the_end(synth, init_cache, tmp_path, monkeypatch):
    assert curve_views(17, 4) == [0, 5, 11, 16] and curve_views(3, 4) == [0, 1, 2]
    assert curve_views(17, None) == list(range(17))
    seen: list[int] = []
    real_scores, real_render = curve_module.heldout_scores, curve_module.render_model

    def recording(model, frames, bg):
        seen.append(len(frames))
        return real_scores(model, frames, bg)

    def render_without_autograd(*a):
        assert not torch.is_grad_enabled()
        out = real_render(*a)
        assert not out[0].requires_grad
        return out

    monkeypatch.setattr(curve_module, "heldout_scores", recording)
    monkeypatch.setattr(curve_module, "render_model", render_without_autograd)
    cfg = _cfg(5)
    cfg.curve_every_s = 0.0  # a point after every iteration
    t = Trainer(synth, _work(init_cache, tmp_path / "c"), cfg)
    t.run()
    n = len(t.test_frames)
    assert n > 4
    assert seen == [4] * 5 + [n]  # iterations 0..4 on the subset, the last (5) on every view
    rows = (tmp_path / "c" / "curve.csv").read_text().strip().splitlines()[1:]
    assert [int(r.split(",")[1]) for r in rows] == [0, 1, 2, 3, 4, 5]
    p_all, _ = evaluate_heldout(t.method.model, t.test_frames, t.bg)
    assert float(rows[-1].split(",")[2]) == pytest.approx(p_all, abs=1e-6)
    rep = json.loads((tmp_path / "c" / "report.json").read_text())["values"]["curve"]
    assert rep["views_per_point"] == 4 and rep["views_final"] == n
    p_sub, _ = evaluate_heldout(t.method.model, t.test_frames, t.bg, 4)
    assert rep["final_psnr_on_point_views"] == pytest.approx(p_sub, abs=1e-6)


def test_curve_time_is_not_training_time(synth, init_cache, tmp_path):
    """A point on every held-out view after every iteration: the training clock between two points
    advances by a step, not by the point's evaluation in between (were it counted, each interval
    would hold one evaluation). Medians, so a one-off slow step does not decide it."""
    import csv

    cfg = _cfg(12)
    cfg.curve_every_s = 0.0
    cfg.curve_max_views = None
    t = Trainer(synth, _work(init_cache, tmp_path / "t"), cfg)
    t0 = time.perf_counter()
    res = t.run()
    wall = time.perf_counter() - t0
    curve_s = t.report.values["curve"]["eval_seconds"]
    rows = list(csv.DictReader((tmp_path / "t" / "curve.csv").open()))
    assert [int(r["iteration"]) for r in rows] == list(range(13))
    per_point = curve_s / len(rows)
    steps = np.diff([float(r["seconds"]) for r in rows])
    assert np.median(steps) < 0.7 * per_point, (np.median(steps), per_point)
    assert res.seconds + curve_s <= wall
    assert np.isfinite(res.seconds) and res.seconds > 0


@pytest.mark.slow
def test_a_split_that_holds_nothing_out_trains_without_a_curve(synth, init_cache, tmp_path):
    """``--train all``: every view trains, no curve point is evaluated (none of NaN), the report
    says why, the model is saved and ``dibrgs eval`` says in one line there is nothing to score."""
    from run_synth import dibrgs

    cfg = _cfg(4)
    cfg.curve_every_s = 0.0  # would be a point after every iteration
    t = Trainer(synth, tmp_path / "all", cfg, train_ids=["all"])
    res = t.run()
    assert res.status == "done" and not t.test_frames and len(t.train_frames) == 21
    d = {x.step: x for x in t.report.decisions}
    assert not d["curve"].applied and "no held-out views" in d["curve"].reason
    assert not (tmp_path / "all" / "curve.csv").exists() and not (tmp_path / "all" / "curve.png").exists()
    assert (tmp_path / "all" / "model.pt").is_file() and "curve" not in t.report.values
    rc, err = dibrgs("eval", tmp_path / "all", "--threads", "1")
    assert rc == 2 and "no held-out views" in err and len(err.strip().splitlines()) == 1
    # A split with held-out views records the curve as applied.
    t = Trainer(synth, _work(init_cache, tmp_path / "some"), _cfg(2))
    t.run()
    d = {x.step: x for x in t.report.decisions}
    assert d["curve"].applied and f"of {len(t.test_frames)} held-out views" in d["curve"].reason
