"""The pixel budget: the ``cpu`` preset trains large photos at a long side of 512 px unless a
resolution scale is given, the ``paper`` preset at full resolution; the run records and logs the
factor it used, and evaluation renders at it."""
from __future__ import annotations

import json

import pytest
import torch

from dibrgs_core.training.config import TrainConfig, preset, resolve_resolution
from dibrgs_core.training.trainer import Trainer

from train_synth import make_synth_scene

torch.set_num_threads(1)


def test_cpu_preset_shrinks_large_photos_to_its_budget_and_never_enlarges():
    cpu = preset("cpu")
    s, budget, why = resolve_resolution(cpu, [(953, 536), (953, 536)])
    assert s == pytest.approx(512 / 953) and budget and "512" in why and "--resolution-scale" in why
    s, budget, _ = resolve_resolution(cpu, [(4000, 3000)])
    assert round(4000 * s) == 512 and budget
    assert resolve_resolution(cpu, [(256, 256)])[:2] == (1.0, False)
    # Portrait photos: the long side is the height.
    s, _, _ = resolve_resolution(cpu, [(600, 1024)])
    assert round(1024 * s) == 512


def test_an_explicit_scale_wins_and_the_paper_keeps_full_resolution():
    cpu = preset("cpu")
    cpu.resolution_scale = 1.0
    assert resolve_resolution(cpu, [(4000, 3000)])[:2] == (1.0, False)
    assert resolve_resolution(preset("paper"), [(4000, 3000)])[:2] == (1.0, False)
    assert preset("paper").max_long_side is None and preset("cpu").max_long_side == 512
    # Through the command line: --resolution-scale overrides the budget.
    from dibrgs_core.cli import build_parser
    from dibrgs_core.commands.train import config_from_args

    p = build_parser()
    assert config_from_args(p.parse_args(["train", "S", "--out", "W"])).resolution_scale is None
    cfg = config_from_args(p.parse_args(["train", "S", "--out", "W", "--resolution-scale", "1"]))
    assert resolve_resolution(cfg, [(4000, 3000)])[:2] == (1.0, False)
    # The configuration round-trips with and without a resolved scale.
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg


def test_run_trains_and_evaluates_at_the_budget_and_says_so(tmp_path, caplog):
    import logging

    from dibrgs_core.evaluation.evaluate import load_trained, run_scale

    scene = make_synth_scene(tmp_path / "s", resolution=32)
    cfg = preset("test")
    cfg.iterations = 3
    cfg.curve_every_s = 1e9
    cfg.max_long_side = 16
    cfg.pseudo.mode = "off"
    work = tmp_path / "w"
    tr = Trainer(scene, work, cfg)
    with caplog.at_level(logging.INFO, logger="dibrgs"):
        tr.run()
    assert {(f.image.shape[0], f.image.shape[1]) for f in tr.train_frames + tr.test_frames} == {(16, 16)}
    assert {(f.cam.cam.width, f.cam.cam.height) for f in tr.train_frames} == {(16, 16)}
    rep = json.loads((work / "report.json").read_text())
    d = {x["step"]: x for x in rep["decisions"]}["pixel_budget"]
    assert d["applied"] is True and "32 px -> 16 px" in d["reason"]
    assert any("pixel_budget" in r.getMessage() and "16 px" in r.getMessage() for r in caplog.records)
    tr = load_trained(work)
    assert tr.cfg.resolution_scale is None and run_scale(work, tr, None) == pytest.approx(0.5)
