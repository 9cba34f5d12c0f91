"""3DGS spherical harmonics: the basis-matrix evaluation equals the per-coefficient formula
(graphdeco-inria's ``eval_sh``, degrees 0-3) in values and in gradients, and its autograd graph
has no per-coefficient select nodes."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dibrgs_core.models.base import CameraTensors
from dibrgs_core.models.gs3d import Gaussians3D, eval_sh, eval_sh_split
from model_synth import small_camera

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def per_coefficient(deg: int, sh: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """The reference: one term a coefficient, as in 3DGS's utils/sh_utils.py."""
    res = C0 * sh[:, 0]
    if deg < 1:
        return res
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    res = res - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3]
    if deg < 2:
        return res
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    res = (res + C2[0] * xy * sh[:, 4] + C2[1] * yz * sh[:, 5] + C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
           + C2[3] * xz * sh[:, 7] + C2[4] * (xx - yy) * sh[:, 8])
    if deg < 3:
        return res
    return (res + C3[0] * y * (3 * xx - yy) * sh[:, 9] + C3[1] * xy * z * sh[:, 10]
            + C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
            + C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + C3[5] * z * (xx - yy) * sh[:, 14]
            + C3[6] * x * (xx - 3 * yy) * sh[:, 15])


def _graph_names(t: torch.Tensor) -> list[str]:
    seen, todo, names = set(), [t.grad_fn], []
    while todo:
        f = todo.pop()
        if f is None or f in seen:
            continue
        seen.add(f)
        names.append(type(f).__name__)
        todo += [g for g, _ in f.next_functions]
    return names


@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_values_and_gradients_equal_the_per_coefficient_formula(deg):
    torch.manual_seed(deg)
    n = 500
    sh = torch.randn(n, 16, 3, dtype=torch.float64, requires_grad=True)
    d0 = torch.randn(n, 3, dtype=torch.float64, requires_grad=True)
    d = torch.nn.functional.normalize(d0, dim=1)
    g = torch.randn(n, 3, dtype=torch.float64)
    want = per_coefficient(deg, sh, d)
    got = eval_sh(deg, sh, d)
    assert torch.allclose(got, want, atol=1e-12)
    gw = torch.autograd.grad((want * g).sum(), (sh, d0), retain_graph=True, allow_unused=True)
    gg = torch.autograd.grad((got * g).sum(), (sh, d0), allow_unused=True)
    for a, b in zip(gw, gg):
        assert (a is None and b is None) if deg == 0 and a is None else torch.allclose(a, b, atol=1e-12)
    nc = (deg + 1) ** 2
    assert torch.count_nonzero(gg[0][:, nc:]) == 0  # inactive coefficients get no gradient
    # float32, as trained
    s32, d32 = sh.detach().float(), d.detach().float()
    assert torch.allclose(eval_sh(deg, s32, d32), per_coefficient(deg, s32, d32), atol=1e-5)


def test_no_per_coefficient_select_nodes():
    torch.manual_seed(0)
    dc = torch.randn(100, 1, 3, requires_grad=True)
    rest = torch.randn(100, 15, 3, requires_grad=True)
    d = torch.nn.functional.normalize(torch.randn(100, 3), dim=1).requires_grad_()
    new = _graph_names(eval_sh_split(3, dc, rest, d))
    old = _graph_names(per_coefficient(3, torch.cat([dc, rest], 1), d))
    assert sum("Select" in n for n in old) == 16          # what the reference allocates in backward
    assert sum("Select" in n for n in new) == 0
    assert sum("Bmm" in n for n in new) == 1              # one basis-times-coefficients product


def test_model_colours_use_the_split_coefficients():
    rng = np.random.default_rng(0)
    m = Gaussians3D(rng.uniform(-10, 10, (200, 3)) * [1, 1, 0.1], rng.uniform(0, 1, (200, 3)), 3)
    with torch.no_grad():
        m.sh_rest.normal_(0.0, 0.3)
    cam = CameraTensors.of(small_camera())
    for deg in range(4):
        m.active_sh_degree = deg
        rgb = m.gaussians(cam).colors
        d = torch.nn.functional.normalize(m.means - cam.center, dim=1)
        want = (per_coefficient(deg, torch.cat([m.sh_dc, m.sh_rest], 1), d) + 0.5).clamp_min(0.0)
        assert torch.allclose(rgb, want, atol=1e-5)
    rgb.sum().backward()
    assert m.sh_rest.grad is not None and torch.count_nonzero(m.sh_rest.grad) > 0
