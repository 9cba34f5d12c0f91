"""Small neural-Gaussian models, cameras and optimisers for unit tests of models and strategies."""
from __future__ import annotations

import numpy as np
import torch

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.models.base import CameraTensors
from dibrgs_core.models.scaffold import NeuralGaussians, build_model
from dibrgs_core.training.config import TrainConfig


def small_camera(eye=(0.0, -30.0, 40.0), size=32) -> Camera:
    f = size * 1.2
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return Camera(K=K, w2c=look_at(np.array(eye), np.zeros(3), np.array([0, 0, 1.0])), width=size, height=size)


def camera_tensors(cam: Camera) -> CameraTensors:
    return CameraTensors.of(cam)


def small_model(n=200, seed=0, use_ibr=False) -> NeuralGaussians:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-10, 10, (n, 3)) * np.array([1, 1, 0.1])
    cfg = TrainConfig().model
    model, _ = build_model(pts, np.array([[0, -30, 40.0]]), cfg, use_ibr=use_ibr, scale=1.0)
    return model


# -- optimisers ------------------------------------------------------------------
def stepped_optimizer(m: NeuralGaussians) -> torch.optim.Adam:
    groups = [{"params": [m.offset], "lr": 0.01, "name": "offset"},
              {"params": [m.anchor_feat], "lr": 0.01, "name": "anchor_feat"},
              {"params": [m.scaling], "lr": 0.01, "name": "scaling"}]
    m.anchor.requires_grad_(False)
    opt = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    for p in (m.offset, m.anchor_feat, m.scaling):
        p.grad = torch.ones_like(p)
    opt.step()
    return opt


def check_optimizer_state(m: NeuralGaussians, opt: torch.optim.Adam):
    for g in opt.param_groups:
        p = g["params"][0]
        assert p is getattr(m, g["name"])
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape


def ring_views(W: int = 64, H: int = 48, V: int = 2) -> tuple[torch.Tensor, list[Camera]]:
    """``V`` cameras on a ring looking at the origin, and random (V,3,H,W) images (seed 0)."""
    K = np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]])
    cams = []
    for i in range(V):
        a = 2 * np.pi * i / V
        eye = np.array([4 * np.cos(a), 4 * np.sin(a), 3.0])
        cams.append(Camera(K=K, w2c=look_at(eye, [0, 0, 0], [0, 0, 1]), width=W, height=H, name=f"{i:03d}"))
    torch.manual_seed(0)
    return torch.rand(V, 3, H, W), cams
