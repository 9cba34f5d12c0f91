"""One quaternion-to-rotation conversion (render.projection.quat_to_rotmat) for the rasterizer's
reference path and 3DGS splitting: zero and denormal quaternions are the identity (the former
3DGS copy normalised them by a clamped norm, so a tiny quaternion gave a non-orthonormal matrix)."""
from __future__ import annotations

import math

import numpy as np
import torch

from dibrgs_core.models.gs3d import Gaussians3D
from dibrgs_core.render.projection import quat_to_rotmat
from dibrgs_core.strategy.densify import DensifyStrategy
from dibrgs_core.training.config import GS3DConfig
from dibrgs_core.training.methods import gs3d_optimizer


def test_unit_and_scaled_quaternions_give_the_same_rotation():
    q = torch.nn.functional.normalize(torch.randn(50, 4, dtype=torch.float64), dim=1)
    R = quat_to_rotmat(q)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(quat_to_rotmat(q * 1e5), R, atol=1e-12)
    # 90 degrees about z (w = cos 45, z = sin 45) maps x to y.
    rz = quat_to_rotmat(torch.tensor([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]], dtype=torch.float64))
    assert torch.allclose(rz[0] @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)


def test_zero_denormal_and_tiny_quaternions():
    q = torch.tensor([[0.0, 0, 0, 0], [1e-40, 0, 0, 0], [0, 1e-13, 0, 1e-13]], dtype=torch.float64,
                     requires_grad=True)
    R = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.equal(R[0], eye) and torch.equal(R[1], eye)  # identity for zero / denormal
    # A tiny but valid quaternion is still a rotation (the clamped-norm copy gave ~I here).
    assert torch.allclose(R[2] @ R[2].T, eye, atol=1e-12)
    assert not torch.allclose(R[2], eye, atol=1e-3)
    R.sum().backward()
    assert torch.isfinite(q.grad).all() and torch.equal(q.grad[:2], torch.zeros(2, 4, dtype=torch.float64))


def test_splitting_a_gaussian_with_a_zero_quaternion_stays_finite():
    g = Gaussians3D(np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], np.full((2, 3), 0.5), 0)
    with torch.no_grad():
        g.quats.zero_()
        g.log_scales.fill_(math.log(2.0))  # large: split, not clone
    cfg = GS3DConfig()
    opt = gs3d_optimizer(g, cfg, extent=1.0)
    st = DensifyStrategy(g, cfg, 30000, extent=1.0)
    st.grad_accum[:] = 1.0
    st.denom[:] = 1.0
    st.densify_and_prune(1000, g, opt)
    assert g.num_gaussians == 4 and torch.isfinite(g.means).all()
