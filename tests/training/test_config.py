"""Training configuration: the paper's schedule, fractions of training, presets and their round trip."""
from __future__ import annotations

import re

import pytest

from dibrgs_core.training.config import TrainConfig, expon_lr, preset
from model_synth import small_model


def test_paper_schedule_matches_the_paper_and_scales_with_length():
    """The paper preset gives the paper's iteration numbers; shorter runs keep the fractions."""
    from dibrgs_core.strategy.anchor import AnchorStrategy

    cfg = preset("paper")
    assert cfg.iterations == 30000
    assert (cfg.it(cfg.pseudo.start), cfg.it(cfg.pseudo.until), cfg.it(cfg.pseudo.every)) == (3000, 20000, 50)
    assert cfg.it(cfg.lr.projection_freeze) == 20000
    m = small_model(20)
    s = AnchorStrategy(m, cfg.growth, cfg.iterations)
    assert (s.start, s.until, s.every, s.stat_start) == (1500, 15000, 100, 500)
    s2 = AnchorStrategy(m, cfg.growth, 3000)
    assert (s2.start, s2.until, s2.every) == (150, 1500, 10)
    # Round trip through JSON-like dicts (checkpoints, config.json).
    c2 = TrainConfig.from_dict(preset("cpu").to_dict())
    assert c2 == preset("cpu")
    with pytest.raises(ValueError):
        TrainConfig.from_dict({"nope": 1})
    with pytest.raises(ValueError):
        preset("gpu")


@pytest.mark.parametrize("key,value,says", [
    ("iterations", "many", "'iterations': 'many' is not a whole number"),
    ("iterations", True, "'iterations': True is not a whole number"),
    ("resolution_scale", "x", "'resolution_scale': 'x' is not a number or null"),
    ("method", "nerf", "'method': 'nerf' is not one of dibrgs, 3dgs"),
    ("lr.offset", [0.01], "'lr.offset': [0.01] is not a list of 2 numbers"),
    ("pseudo.mode", "maybe", "'pseudo.mode': 'maybe' is not one of auto, on, off"),
    ("model", 3, "'model': 3 is not a table of ModelConfig's fields"),
    ("dense_init", "yes", "'dense_init': 'yes' is not true or false"),
])
def test_a_value_of_the_wrong_type_is_named(key, value, says):
    """A damaged or hand-edited config (a checkpoint's, a model file's): the key and what it should
    be, not a failure far away in training; whole numbers where a float goes and JSON's lists are
    read as the fields hold them."""
    d = preset("cpu").to_dict()
    top, _, sub = key.partition(".")
    (d[top] if sub else d)[sub or top] = value
    with pytest.raises(ValueError, match="config key " + re.escape(says)):
        TrainConfig.from_dict(d)
    d = preset("cpu").to_dict()
    d["lambda_volume"], d["lr"]["offset"], d["max_long_side"] = 1, [1, 0.5], None
    cfg = TrainConfig.from_dict(d)
    assert cfg.lambda_volume == 1.0 and isinstance(cfg.lambda_volume, float)
    assert cfg.lr.offset == (1.0, 0.5) and cfg.max_long_side is None


def test_expon_lr_endpoints_and_monotone():
    assert expon_lr(0, 100, 0.01, 0.0001) == pytest.approx(0.01)
    assert expon_lr(100, 100, 0.01, 0.0001) == pytest.approx(0.0001)
    assert expon_lr(50, 100, 0.01, 0.0001) == pytest.approx(0.001)
    assert expon_lr(10, 100, 0.0, 0.0) == 0.0
