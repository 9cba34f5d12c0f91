"""Rasterizer at the extremes: finite outputs and gradients everywhere, known values where
there is one, and determinism. Every case runs on both paths."""
from __future__ import annotations

import math

import pytest
import torch

from dibrgs_core.render import rasterize

pytestmark = pytest.mark.stability

BACKENDS = ["reference", "fast"]
W, H = 40, 30


def cam(width=W, height=H, f=30.0, cx=None, cy=None):
    K = torch.tensor([[f, 0, width / 2 if cx is None else cx], [0, f, height / 2 if cy is None else cy], [0, 0, 1.0]])
    return torch.eye(4), K


def gaussians(means, scales, quats=None, opac=None, cols=None):
    n = len(means)
    means = torch.as_tensor(means, dtype=torch.float32).reshape(n, 3)
    scales = torch.as_tensor(scales, dtype=torch.float32).expand(n, 3).clone()
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1) if quats is None else torch.as_tensor(quats, dtype=torch.float32)
    opac = torch.full((n,), 0.8) if opac is None else torch.as_tensor(opac, dtype=torch.float32)
    cols = torch.linspace(0.1, 0.9, 3).repeat(n, 1) if cols is None else cols
    return [means, quats, scales, opac, cols]


def render(params, backend, width=W, height=H, K=None, viewmat=None, bg=None, **kw):
    """Render with gradients; assert every output and gradient is finite; return outputs and grads."""
    vm, K0 = cam(width, height)
    K = K0 if K is None else K
    vm = vm if viewmat is None else viewmat
    ps = [p.clone().requires_grad_() for p in params]
    img, alpha, depth, meta = rasterize(*ps, vm, K, width, height, background=bg, backend=backend, **kw)
    for t in (img, alpha, depth):
        assert torch.isfinite(t).all()
    assert (alpha >= 0).all() and (alpha <= 1 + 1e-6).all()
    loss = img.sum() + alpha.sum() + 1e-3 * depth.sum()
    if meta["means2d"].requires_grad:
        meta["means2d"].retain_grad()
    if loss.requires_grad:
        loss.backward()
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in ps]
    for g in grads:
        assert torch.isfinite(g).all()
    if meta["means2d"].grad is not None:
        assert torch.isfinite(meta["means2d"].grad).all()
    return img.detach(), alpha.detach(), depth.detach(), meta, grads


def centre(alpha):
    return float(alpha[H // 2, W // 2, 0])


@pytest.mark.parametrize("backend", BACKENDS)
def test_tiny_and_huge_scales(backend):
    """A 1e-8 Gaussian is the 0.3 px^2 dilation kernel: centred on a pixel centre it gives alpha = opacity there. (mean at pixel (20, 15)'s centre: x/z = 0.5/30, y/z = 0.5/30)"""
    z = 5.0
    p = gaussians([[0.5 / 30 * z, 0.5 / 30 * z, z]], 1e-8, opac=[0.7])
    _, alpha, depth, meta, _ = render(p, backend)
    assert meta["radii"][0] == math.ceil(3 * math.sqrt(0.3 + math.sqrt(0.1)))  # 3DGS eigenvalue floor
    assert abs(centre(alpha) - 0.7) < 1e-5
    assert abs(float(depth[H // 2, W // 2, 0]) - z) < 1e-4
    # A 1e4 Gaussian covers the image almost uniformly with alpha = opacity.
    _, alpha, depth, _, _ = render(gaussians([[0.0, 0.0, 50.0]], 1e4, opac=[0.6]), backend)
    assert float((alpha - 0.6).abs().max()) < 1e-4
    assert float((depth - 50.0).abs().max()) < 1e-3


@pytest.mark.parametrize("backend", BACKENDS)
def test_near_plane(backend):
    """Gaussians exactly on, just in front of and behind the near plane: those on or behind are culled with zero gradients; the one just in front renders with the expected alpha and depth."""
    near = 0.5
    on = gaussians([[0.0, 0.0, near]], 0.1)
    behind = gaussians([[0.0, 0.0, near - 1e-4], [0.0, 0.0, -2.0]], 0.1)
    front = gaussians([[0.0, 0.0, near * 1.0001]], 0.1)
    for p in (on, behind):
        img, alpha, _, meta, grads = render(p, backend, near=near)
        assert not meta["visible"].any() and float(alpha.abs().max()) == 0.0
        assert all(float(g.abs().max()) == 0.0 for g in grads)
    # Just in front: larger than its depth, still an ordinary splat (sigma = 6 px) with
    # alpha ~ opacity at the principal point, which sits on a pixel corner.
    _, alpha, depth, meta, grads = render(front, backend, near=near)
    assert meta["visible"].all()
    assert abs(float(alpha[H // 2, W // 2, 0]) - 0.8 * math.exp(-0.25 / 36.3)) < 2e-3
    assert abs(float(depth[H // 2, W // 2, 0]) - near) < 1e-4
    assert float(grads[0].abs().sum()) > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_far_away_aerial_depths(backend):
    """Depth 1e4 with a ground-sized Gaussian, seen by a long-focal camera."""
    z = 1e4
    K = torch.tensor([[5000.0, 0, W / 2], [0, 5000.0, H / 2], [0, 0, 1]])
    _, alpha, depth, _, grads = render(gaussians([[0.0, 0.0, z]], 20.0, opac=[0.9]), backend, K=K)
    assert centre(alpha) > 0.85
    assert float((depth - z).abs().max()) / z < 1e-6
    assert float(grads[0].abs().sum()) > 0
    # A second one 50 m behind pulls the expected depth back by its share of the weight.
    p = gaussians([[0.0, 0.0, z], [30.0, -20.0, z + 50.0]], 20.0, opac=[0.9, 0.9])
    _, alpha, depth, _, _ = render(p, backend, K=K)
    d = depth[..., 0]
    assert float(d.min()) >= z - 1e-2 and float(d.max()) <= z + 50 + 1e-2 and float(d.max()) > z + 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_grazing_angle(backend):
    """A flat disc (normal along x) seen edge-on: its projected covariance is rank one before the dilation, so across the line the profile is the 0.3 px^2 kernel alone."""
    for thin in (1e-7, 0.0):
        p = gaussians([[0.0, 0.0, 4.0]], torch.tensor([[thin, 1.0, 1.0]]))
        _, alpha, _, meta, _ = render(p, backend)
        assert meta["visible"].all()
        # The line is at u = 20.0, between pixel columns 19 and 20 (centres 0.5 px away).
        # Rows: the disc's vertical spread (sigma = 7.5 px) seen from 0.5 px off its centre.
        expect = 0.8 * math.exp(-0.5 * 0.25 / 0.3) * math.exp(-0.5 * 0.25 / (7.5**2 + 0.3))
        assert abs(float(alpha[H // 2, 19, 0]) - expect) < 1e-4
        assert abs(float(alpha[H // 2, 20, 0]) - expect) < 1e-4
        assert float(alpha[:, :17].abs().max()) == 0.0 and float(alpha[:, 23:].abs().max()) == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_and_denormal_quaternions_are_identity(backend):
    """Zero and denormal quaternions: read as the identity rotation, same image as the identity quaternion, finite gradients."""
    base = gaussians([[0.1, -0.2, 4.0]], torch.tensor([[0.3, 0.05, 0.1]]))
    ref_img = render(base, backend)[0]
    for q in ([0.0, 0.0, 0.0, 0.0], [1e-40, 0.0, 0.0, 0.0], [1e-41, 1e-42, 0.0, 0.0]):
        p = list(base)
        p[1] = torch.tensor([q])
        img, _, _, _, grads = render(p, backend)
        assert torch.equal(img, ref_img)


@pytest.mark.parametrize("backend", BACKENDS)
def test_opacity_zero_and_one(backend):
    """Opacity 0 renders exactly the background with zero alpha and depth; opacity 1 is clamped to alpha 0.99; gradients finite."""
    bg = torch.tensor([0.25, 0.5, 0.75])
    p = gaussians([[0.5 / 30 * 4, 0.5 / 30 * 4, 4.0]], 0.2, opac=[0.0])
    img, alpha, depth, _, _ = render(p, backend, bg=bg)
    assert float(alpha.abs().max()) == 0.0 and float(depth.abs().max()) == 0.0
    assert torch.allclose(img, bg.expand_as(img))
    p[3] = torch.tensor([1.0])
    img, alpha, _, _, grads = render(p, backend, bg=bg)
    assert abs(centre(alpha) - 0.99) < 1e-6  # clamped
    assert float(grads[3].abs().sum()) > 0  # pixels away from the centre are below the clamp


@pytest.mark.parametrize("backend", [pytest.param("reference", marks=pytest.mark.slow), "fast"])
def test_million_tiny_gaussians(backend):
    """One million tiny Gaussians (~1300 per pixel): all visible, the image saturates (alpha > 0.99), finite gradients."""
    n = 1_000_000
    g = torch.Generator().manual_seed(0)
    # Spread over the view of a 32x24 camera with f = 30: ~1300 per pixel.
    z = 3.0 + torch.rand(n, generator=g)
    u = torch.rand(n, 2, generator=g) * torch.tensor([32.0, 24.0])
    means = torch.stack([(u[:, 0] - 16) / 30 * z, (u[:, 1] - 12) / 30 * z, z], -1)
    p = gaussians(means, 1e-5, opac=torch.rand(n, generator=g), cols=torch.rand(n, 3, generator=g))
    img, alpha, _, meta, grads = render(p, backend, width=32, height=24)
    assert meta["visible"].all()
    assert float(alpha.min()) > 0.99
    assert float(grads[4].abs().sum()) > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene_and_one_pixel(backend):
    """An empty scene (background only, zero alpha) and a 1x1 image: finite outputs and gradients."""
    bg = torch.tensor([0.1, 0.2, 0.3])
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    img, alpha, depth, meta, _ = render(empty, backend, bg=bg)
    assert img.shape == (H, W, 3) and torch.allclose(img, bg.expand_as(img))
    assert float(alpha.abs().max()) == 0 and meta["radii"].shape == (0,)
    K = torch.tensor([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])
    p = gaussians([[0.0, 0.0, 3.0], [0.2, 0.0, 6.0]], 0.5, opac=[0.5, 0.5])
    img, alpha, depth, _, _ = render(p, backend, width=1, height=1, K=K, bg=bg)
    assert img.shape == (1, 1, 3)
    # Front Gaussian on the pixel centre: alpha 0.5. Back one 2*0.2/6 px off, EWA variance along x:
    cov_xx = (2 / 6) ** 2 * 0.25 + (2 * 0.2 / 36) ** 2 * 0.25 + 0.3
    a2 = 0.5 * math.exp(-0.5 * (2 * 0.2 / 6) ** 2 / cov_xx)
    assert abs(float(alpha) - (0.5 + 0.5 * a2)) < 1e-5


@pytest.mark.parametrize("backend", BACKENDS)
def test_non_square_off_centre_camera(backend):
    """Non-square 53x21 image with an off-centre principal point: screen-space means equal K applied to the camera-frame means."""
    Wn, Hn = 53, 21
    K = torch.tensor([[25.0, 0, 40.2], [0, 31.0, 3.7], [0, 0, 1]])
    g = torch.Generator().manual_seed(3)
    means = torch.randn(50, 3, generator=g) + torch.tensor([0.0, 0.0, 5.0])
    p = gaussians(means, 0.2, opac=torch.rand(50, generator=g))
    img, alpha, _, meta, _ = render(p, backend, width=Wn, height=Hn, K=K)
    assert img.shape == (Hn, Wn, 3)
    m2 = meta["means2d"].detach()
    torch.testing.assert_close(m2[:, 0], 25.0 * means[:, 0] / means[:, 2] + 40.2)
    torch.testing.assert_close(m2[:, 1], 31.0 * means[:, 1] / means[:, 2] + 3.7)


@pytest.mark.parametrize("backend", BACKENDS)
def test_camera_inside_a_gaussian(backend):
    """Centre just in front of the camera, 100 m wide: the camera sits inside it."""
    p = gaussians([[0.0, 0.0, 0.2], [0.0, 0.0, 3.0]], torch.tensor([[100.0, 100.0, 100.0], [0.5, 0.5, 0.5]]), opac=[0.5, 0.9])
    _, alpha, depth, meta, grads = render(p, backend)
    assert meta["visible"].all()
    assert float(alpha.min()) > 0.49  # the enclosing Gaussian covers every pixel
    assert float(grads[2].abs().sum()) > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_deterministic(backend):
    """The same inputs give bit-identical images twice."""
    g = torch.Generator().manual_seed(4)
    n = 1000
    means = torch.randn(n, 3, generator=g) + torch.tensor([0.0, 0.0, 6.0])
    p = gaussians(means, torch.rand(n, 3, generator=g) * 0.3, quats=torch.randn(n, 4, generator=g),
                  opac=torch.rand(n, generator=g), cols=torch.rand(n, 3, generator=g))
    a = render(p, backend, width=70, height=50)
    b = render(p, backend, width=70, height=50)
    for x, y in zip(a[:3], b[:3]):
        assert torch.equal(x, y)
    if backend == "fast":  # fixed-order gradient reduction (torch's index backward is not)
        for x, y in zip(a[4], b[4]):
            assert torch.equal(x, y)
