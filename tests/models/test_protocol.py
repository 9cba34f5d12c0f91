"""Both models meet one protocol: Gaussians for a camera, sizes, a state that rebuilds them,
a view-independent export; render_model renders either; the strategies share one interface."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dibrgs_core.models.base import render_model
from dibrgs_core.models.factory import MODELS, model_from_state
from dibrgs_core.models.gs3d import Gaussians3D
from dibrgs_core.strategy.anchor import AnchorStrategy
from dibrgs_core.strategy.base import Strategy
from dibrgs_core.strategy.densify import DensifyStrategy
from dibrgs_core.training.config import preset
from dibrgs_core.training.methods import gs3d_optimizer
from model_synth import camera_tensors, small_camera, small_model, stepped_optimizer


def _models():
    rng = np.random.default_rng(0)
    g3 = Gaussians3D(rng.uniform(-10, 10, (300, 3)) * [1, 1, 0.1], rng.uniform(0, 1, (300, 3)), 3)
    g3.active_sh_degree = 2
    sc = small_model(200, use_ibr=True)
    feats = torch.randn(sc.num_anchors, 32)
    sc.set_ibr(feats)
    with torch.no_grad():
        sc.mlp_opacity[2].bias.fill_(0.2)
    return [(g3, None), (sc, feats)]


@pytest.mark.parametrize("which", [0, 1], ids=["3dgs", "dibrgs"])
def test_state_round_trip_renders_the_same_image(which):
    model, feats = _models()[which]
    cam = camera_tensors(small_camera())
    bg = torch.tensor([0.1, 0.2, 0.3])
    with torch.no_grad():
        img, alpha, depth, info = render_model(model, cam, bg)
    assert info is not None and info["width"] == 32 and info["gaussians"].means.shape[0] > 0
    assert model.kind in MODELS and MODELS[model.kind] is type(model)
    back = model_from_state(model.kind, model.state(), preset("test").model)
    if feats is not None:
        back.set_ibr(feats)
    with torch.no_grad():
        img2 = render_model(back, cam, bg)[0]
    assert torch.equal(img, img2)
    assert back.sizes() == model.sizes() and model.sizes()["gaussians"] > 0
    exported = model.export_gaussians([small_camera()])
    assert exported["means"].shape[0] > 0 and torch.isfinite(exported["means"]).all()


def test_unknown_kind_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown model kind 'nerf'"):
        model_from_state("nerf", {}, preset("test").model)


def test_a_model_that_shows_a_camera_nothing_renders_the_background():
    model, _ = _models()[1]
    with torch.no_grad():
        model.anchor += 1e4  # every anchor far outside the frustum
    bg = torch.tensor([0.1, 0.2, 0.3])
    img, alpha, depth, info = render_model(model, camera_tensors(small_camera()), bg)
    assert info is None and torch.equal(img, bg.expand(32, 32, 3)) and float(alpha.abs().max()) == 0.0


def test_strategies_share_the_hooks_and_skip_statistics_without_info():
    sc = small_model(50)
    a = AnchorStrategy(sc, preset("test").growth, 300)
    g3 = _models()[0][0]
    d = DensifyStrategy(g3, preset("test").gs3d, 300, extent=10.0)
    assert isinstance(a, Strategy) and isinstance(d, Strategy)
    opt = stepped_optimizer(sc)
    it = a.stat_start + 1
    assert a.step_post_backward(sc, opt, it, None) == {} and float(a.anchor_denom.sum()) == 0.0
    cam = camera_tensors(small_camera())
    img, _, _, info = render_model(sc, cam, torch.zeros(3))
    a.step_pre_backward(sc, opt, it, info)
    img.sum().backward()
    a.step_post_backward(sc, opt, it, info)
    assert float(a.anchor_denom.sum()) > 0 and float(a.offset_denom.sum()) > 0
    opt3 = gs3d_optimizer(g3, preset("test").gs3d, 10.0)
    img, _, _, info = render_model(g3, cam, torch.zeros(3))
    d.step_pre_backward(g3, opt3, 1, info)
    img.sum().backward()
    d.step_post_backward(g3, opt3, 1, info)
    assert float(d.denom.sum()) > 0
