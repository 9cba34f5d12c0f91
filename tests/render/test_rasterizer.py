"""Rasterizer correctness: both paths vs a float64 brute force, projection vs
gsplat's pure-torch implementation, gradients vs finite differences."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from paths import shared_file
from dibrgs_core.render import composite, project_gaussians, rasterize
from rasterizer_oracle import brute_composite

BACKENDS = ["reference", "fast"]


def random_scene(seed: int, n: int, dtype=torch.float32):
    """Gaussians in front of an identity camera, some elongated, some overlapping the border."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([1.2, 0.9, 0.6], dtype=torch.float64)
    means[:, 2] += 4.0
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.35 + 0.01
    scales[: n // 4, 0] *= 4.0  # elongated ones
    opac = torch.rand(n, generator=g, dtype=torch.float64)
    cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, scales, opac, cols)]


def camera(width: int, height: int, f: float = 30.0, cx: float | None = None, cy: float | None = None, dtype=torch.float32):
    K = torch.tensor(
        [[f, 0, width / 2 if cx is None else cx], [0, f * 1.1, height / 2 if cy is None else cy], [0, 0, 1]], dtype=dtype
    )
    return torch.eye(4, dtype=dtype), K


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed,n,width,height", [(0, 60, 40, 29), (1, 150, 50, 37), (2, 30, 17, 33)])
def test_paths_match_bruteforce(backend, seed, n, width, height):
    means, quats, scales, opac, cols = random_scene(seed, n)
    vm, K = camera(width, height)
    proj = project_gaussians(means, quats, scales, vm, K, width, height)
    assert int(proj.visible.sum()) > n // 2
    feats = torch.cat([cols, proj.depths[:, None], torch.ones(n, 1)], 1)
    out = composite(proj.means2d, proj.conics, opac, feats, proj.depths, proj.radii, width, height, backend=backend)
    ref = brute_composite(proj.means2d.detach(), proj.conics, opac, feats.detach(), proj.depths, proj.radii, width, height)
    assert ref[..., -1].max() > 0.9  # the scene covers pixels fully
    np.testing.assert_allclose(out.detach().numpy(), ref, atol=1e-5, rtol=0)

    # The public API composes the same pieces: background, alpha, normalised depth.
    bg = torch.tensor([0.2, 0.5, 0.9])
    img, alpha, depth, meta = rasterize(means, quats, scales, opac, cols, vm, K, width, height, background=bg, backend=backend)
    a_ref = ref[..., 4:5]
    np.testing.assert_allclose(alpha.numpy(), a_ref, atol=1e-5)
    np.testing.assert_allclose(img.numpy(), ref[..., :3] + (1 - a_ref) * bg.numpy(), atol=1e-5)
    hit = a_ref[..., 0] > 0
    np.testing.assert_allclose(depth.numpy()[hit, 0], ref[hit, 3] / a_ref[hit, 0], rtol=1e-4)
    assert (depth.numpy()[~hit] == 0).all()
    assert torch.equal(meta["visible"], meta["radii"] > 0)


def test_paths_agree_on_many_channels():
    means, quats, scales, opac, _ = random_scene(3, 80)
    feats = torch.rand(80, 7, generator=torch.Generator().manual_seed(0))
    vm, K = camera(48, 40)
    outs = [rasterize(means, quats, scales, opac, feats, vm, K, 48, 40, backend=b) for b in BACKENDS]
    for a, b in zip(outs[0][:3], outs[1][:3]):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0)


def test_pixel_centre_convention():
    """A Gaussian on the optical axis with cx = W/2 renders symmetrically; one projecting
    to (u, v) with an off-centre principal point peaks at pixel (floor(u), floor(v))."""
    for backend in BACKENDS:
        means = torch.tensor([[0.0, 0.0, 5.0]])
        quats = torch.tensor([[1.0, 0, 0, 0]])
        scales = torch.full((1, 3), 0.2)
        op = torch.tensor([0.8])
        col = torch.ones(1, 1)
        vm, K = camera(32, 32, f=40.0)
        _, alpha, _, _ = rasterize(means, quats, scales, op, col, vm, K, 32, 32, backend=backend)
        torch.testing.assert_close(alpha, alpha.flip(0), atol=1e-6, rtol=0)
        torch.testing.assert_close(alpha, alpha.flip(1), atol=1e-6, rtol=0)

        W, H = 45, 23
        vm, K = camera(W, H, f=40.0, cx=30.3, cy=5.8)
        X = torch.tensor([[-0.37, 0.52, 5.0]])
        u = float(K[0, 0] * X[0, 0] / X[0, 2] + K[0, 2])
        v = float(K[1, 1] * X[0, 1] / X[0, 2] + K[1, 2])
        _, alpha, _, meta = rasterize(X, quats, torch.full((1, 3), 0.05), op, col, vm, K, W, H, backend=backend)
        assert alpha.shape == (H, W, 1)
        iy, ix = np.unravel_index(int(alpha[..., 0].argmax()), (H, W))
        assert (ix, iy) == (int(np.floor(u)), int(np.floor(v)))
        torch.testing.assert_close(meta["means2d"][0], torch.tensor([u, v]), atol=1e-4, rtol=0)


def test_projection_matches_gsplat():
    """means2d, depths and conics equal gsplat 1.5.3's pure-torch projection on the
    garden scene's cameras (float64); radii follow 3DGS's isotropic 3-sigma rule."""
    impl = pytest.importorskip("gsplat.cuda._torch_impl")
    data = np.load(shared_file("data/test_garden.npz"))
    g = torch.Generator().manual_seed(0)
    means = torch.tensor(data["means3d"], dtype=torch.float64)[::7]
    n = len(means)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=torch.float64) - 4.0)
    W, H = int(data["width"]), int(data["height"])
    from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    for vm, K in zip(data["viewmats"], data["Ks"]):
        vm = torch.tensor(vm, dtype=torch.float64)
        K = torch.tensor(K, dtype=torch.float64)
        radii_g, m2_g, depth_g, conic_g, _ = impl._fully_fused_projection(means, covars, vm[None], K[None], W, H)
        radii_g, m2_g, depth_g, conic_g = radii_g[0], m2_g[0], depth_g[0], conic_g[0]
        ours = project_gaussians(means, quats, scales, vm, K, W, H)
        both = ours.visible & (radii_g > 0).all(-1)
        assert int(both.sum()) > 0.3 * n
        # Visibility differs only through the radius rule near the image border.
        assert int((ours.visible != (radii_g > 0).all(-1)).sum()) < 0.02 * n
        torch.testing.assert_close(ours.depths, depth_g, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(ours.means2d[both], m2_g[both], rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(ours.conics[both], conic_g[both], rtol=1e-7, atol=1e-9)
        # 3-sigma radius of the 2D covariance (inverse of gsplat's conic).
        a, b, c = conic_g[both].unbind(-1)
        det = a * c - b * b
        ca, cc = c / det, a / det
        mid = 0.5 * (ca + cc)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - 1.0 / det, min=0.1))
        assert torch.equal(ours.radii[both], torch.ceil(3 * torch.sqrt(lam)).to(torch.int32))


def test_fast_binning_skips_tiles_an_ellipse_misses():
    """Thin diagonal Gaussians: the C++ binning drops the rectangle tiles their alpha >= 1/255
    ellipse does not reach, and the image still equals the brute force (float64, so that
    float32 rounding of these steep profiles does not hide a missing contribution)."""
    from dibrgs_core.render import fast
    from dibrgs_core.render.reference import tile_rects

    fast.available(required=True)
    W, H = 96, 80
    n = 5
    f64 = torch.float64
    means = torch.tensor([[0.0, 0.0, 4.0], [0.3, -0.2, 5.0], [-0.4, 0.3, 4.5], [0.2, 0.4, 3.0], [-0.5, -0.4, 6.0]], dtype=f64)
    ang = torch.tensor([0.7854, -0.6, 0.9, 2.3, -2.2], dtype=f64) / 2  # rotation about the optical axis
    quats = torch.stack([torch.cos(ang), torch.zeros_like(ang), torch.zeros_like(ang), torch.sin(ang)], -1)
    scales = torch.tensor([[1.5, 0.02, 0.02]], dtype=f64).repeat(n, 1)
    opac = torch.full((n,), 0.9, dtype=f64)
    feats = torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=f64)
    vm, K = camera(W, H, f=40.0, dtype=f64)
    proj = project_gaussians(means, quats, scales, vm, K, W, H)
    rect = tile_rects(proj.means2d, proj.conics, opac, proj.radii, W, H)
    in_rects = int(((rect[:, 1] - rect[:, 0]).clamp(min=0) * (rect[:, 3] - rect[:, 2]).clamp(min=0)).sum())
    offsets, _, _ = fast.extension().bin_tiles(
        proj.means2d.detach(), proj.conics.detach(), opac, proj.depths.detach(), proj.radii, W, H
    )
    assert int(offsets[-1]) < 0.8 * in_rects
    for backend in BACKENDS:
        out = composite(proj.means2d, proj.conics, opac, feats, proj.depths, proj.radii, W, H, backend=backend)
        ref = brute_composite(proj.means2d.detach(), proj.conics, opac, feats, proj.depths, proj.radii, W, H)
        assert ref.max() > 0.5
        np.testing.assert_allclose(out.detach().numpy(), ref, atol=1e-9, rtol=0)


@pytest.mark.parametrize("n", [400, 397])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fast_projection_matches_torch(dtype, n):
    """The C++ projection (float64 inside) gives the torch projection's outputs, radii
    and input gradients, including culled, clamped, degenerate and extreme Gaussians; with
    397 Gaussians the special ones come last, where the kernel goes one Gaussian at a time
    after its whole vectors."""
    from dibrgs_core.render import fast

    fast.available(required=True)
    means, quats, scales, _, _ = random_scene(6, 400, dtype=torch.float64)
    means[:40, :2] *= 6.0  # far outside the view: Jacobian clamp
    means[40:50, 2] = torch.linspace(-1.0, 0.2, 10, dtype=torch.float64)  # behind / near the near plane
    quats[50:55] = 0.0  # zero quaternion -> identity
    quats[55:60] = 1e-40
    scales[60:70] *= 1e4
    scales[70:80] *= 1e-8
    scales[80:90, 0] = 0.0  # flat discs
    means[90:95, 2] = 1e4
    W, H = 61, 47
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64))[0]
    vm[:3, :3] *= torch.sign(torch.det(vm[:3, :3]))
    vm[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    means = means @ vm[:3, :3]  # same camera-space points as with the identity camera, minus t
    if n != 400:
        means, quats, scales = (torch.roll(t[:n], n - 95, 0) for t in (means, quats, scales))
    K = torch.tensor([[40.0, 0, 33.3], [0, 44.0, 21.1], [0, 0, 1]], dtype=torch.float64)
    g = torch.Generator().manual_seed(7)
    w_m2, w_con, w_dep = (torch.randn(n, k, generator=g, dtype=torch.float64) for k in (2, 3, 1))
    outs = []
    for proj_fn in (project_gaussians, fast.project_fast):
        ps = [t.to(dtype).clone().requires_grad_() for t in (means, quats, scales)]
        pr = proj_fn(*ps, vm.to(dtype), K.to(dtype), W, H, near=0.1, far=1e6)
        loss = (pr.means2d * w_m2.to(dtype)).sum() + (pr.conics * w_con.to(dtype) * pr.visible[:, None]).sum()
        (loss + (pr.depths * w_dep[:, 0].to(dtype)).sum()).backward()
        outs.append((pr, [p.grad for p in ps]))
    (pa, ga), (pb, gb) = outs
    assert 100 < int(pa.visible.sum()) < n
    assert torch.equal(pa.radii, pb.radii) and torch.equal(pa.visible, pb.visible)
    tol = dict(rtol=1e-10, atol=1e-12) if dtype == torch.float64 else dict(rtol=2e-6, atol=1e-6)
    v = pa.visible
    torch.testing.assert_close(pb.means2d[v], pa.means2d[v], **tol)
    torch.testing.assert_close(pb.conics[v], pa.conics[v], **tol)
    torch.testing.assert_close(pb.depths, pa.depths, **tol)
    gtol = dict(rtol=1e-8, atol=1e-10) if dtype == torch.float64 else dict(rtol=1e-4, atol=1e-4)
    for x, y in zip(gb, ga):
        assert torch.isfinite(x).all()
        torch.testing.assert_close(x, y, **gtol)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_match_finite_differences(backend):
    """Analytic gradients of every input equal float64 central differences."""
    means, quats, scales, opac, cols = random_scene(4, 6, dtype=torch.float64)
    opac = opac * 0.6 + 0.2  # away from the 0.99 clamp
    W, H = 21, 18
    vm, K = camera(W, H, f=12.0, dtype=torch.float64)
    bg = torch.tensor([0.3, 0.1, 0.7], dtype=torch.float64)
    wgt = torch.rand(H, W, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def f(m, q, s, o, c):
        img, alpha, depth, _ = rasterize(m, q, s, o, c, vm, K, W, H, background=bg, backend=backend)
        return (torch.cat([img, alpha, 0.1 * depth], -1) * wgt).sum()

    inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opac, cols)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_a_learnable_background_gets_its_gradient_even_at_black():
    """A background that requires grad is blended (and gets d/dbg = sum of T * upstream) even
    where it is zero; a fixed black one renders as no background at all."""
    means, quats, scales, opac, cols = random_scene(6, 40)
    W, H = 30, 22
    vm, K = camera(W, H)
    wgt = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(3))
    bg = torch.zeros(3, requires_grad=True)
    img, alpha, _, _ = rasterize(means, quats, scales, opac, cols, vm, K, W, H, background=bg)
    (img * wgt).sum().backward()
    expect = ((1.0 - alpha.detach()) * wgt).sum((0, 1))
    assert float(expect.min()) > 0
    torch.testing.assert_close(bg.grad, expect, rtol=1e-5, atol=1e-5)
    plain, _, _, _ = rasterize(means, quats, scales, opac, cols, vm, K, W, H)
    black, _, _, _ = rasterize(means, quats, scales, opac, cols, vm, K, W, H, background=torch.zeros(3))
    assert torch.equal(plain, black)


def test_backends_give_same_gradients_and_means2d_grad():
    means, quats, scales, opac, cols = random_scene(5, 120)
    vm, K = camera(64, 48)
    wgt = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(2))
    grads = []
    for backend in BACKENDS:
        inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opac, cols)]
        img, alpha, depth, meta = rasterize(*inputs, vm, K, 64, 48, backend=backend)
        assert not meta["means2d"].retains_grad  # kept only when asked: a copy every step
        meta["means2d"].retain_grad()
        ((img * wgt).sum() + depth.sum() + alpha.sum()).backward()
        m2g = meta["means2d"].grad
        assert m2g is not None and m2g.abs().sum() > 0
        assert (m2g[~meta["visible"]] == 0).all()
        grads.append([t.grad for t in inputs] + [m2g])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, atol=2e-4, rtol=1e-4)


@pytest.mark.parametrize("use", ["image", "alpha", "depth"])
def test_outputs_used_alone_give_the_reference_gradients(use):
    """The C++ path writes colour, depth and alpha as three contiguous tensors (none a strided
    slice); a loss on one of them alone (the others' gradients absent, read as zeros) gives the
    reference path's gradients."""
    means, quats, scales, opac, cols = random_scene(7, 90, dtype=torch.float64)
    W, H = 37, 29
    vm, K = camera(W, H, dtype=torch.float64)
    wgt = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    grads = []
    for backend in BACKENDS:
        inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opac, cols)]
        img, alpha, depth, _ = rasterize(*inputs, vm, K, W, H, backend=backend)
        if backend == "fast":
            assert img.is_contiguous() and alpha.is_contiguous()
        out = {"image": img, "alpha": alpha, "depth": depth}[use]
        (out * wgt[..., : out.shape[-1]]).sum().backward()
        grads.append([t.grad for t in inputs])
    assert sum(float(g.abs().sum()) for g in grads[1]) > 0
    for a, b in zip(*grads):
        assert a is not None and b is not None
        torch.testing.assert_close(b, a, atol=1e-9, rtol=1e-7)


def _equal(a: torch.Tensor, b: torch.Tensor, **_) -> None:
    assert torch.equal(a, b)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("bg", ["black", "grey"])
def test_rgb_mode_gives_the_image_and_gradients_of_the_full_render(backend, bg):
    """``render_mode="RGB"`` (a training step) composites the colours alone: the same image and,
    for a loss on it, the same gradients as the full render, bit for bit on the fast path; no alpha
    or depth. The reference path's compositing is a batched product whose BLAS kernel, and so
    summation order, may change with the channel count (on an AMD Zen 4 it does: 1 ulp), so there
    the two agree to float32 rounding. A background that is blended still gets its alpha composited
    (the image changes with it)."""
    means, quats, scales, opac, cols = random_scene(11, 80)
    W, H = 45, 31
    vm, K = camera(W, H)
    back = torch.zeros(3) if bg == "black" else torch.tensor([0.5, 0.25, 0.75])
    wgt = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(8))
    res = {}
    for mode in ("RGB+ED", "RGB"):
        inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opac, cols)]
        img, alpha, depth, meta = rasterize(*inputs, vm, K, W, H, background=back, backend=backend,
                                            render_mode=mode)
        meta["means2d"].retain_grad()
        (img * wgt).sum().backward()
        res[mode] = (img.detach(), [t.grad for t in inputs] + [meta["means2d"].grad], alpha, depth)
    full, rgb = res["RGB+ED"], res["RGB"]
    assert rgb[2] is None and rgb[3] is None and full[2] is not None and full[3] is not None
    same = torch.testing.assert_close if backend == "reference" else _equal
    same(rgb[0], full[0], rtol=1e-6, atol=1e-7)
    assert float(full[1][0].abs().sum()) > 0
    for a, b in zip(full[1], rgb[1]):
        same(b, a, rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="render_mode"):
        rasterize(means, quats, scales, opac, cols, vm, K, W, H, render_mode="D")


@pytest.mark.stability
def test_expected_depth_node_equals_the_torch_formula():
    """render/depth.py: the C++ node and the torch formula give the same depth and gradients,
    0 and a zero gradient where the alpha is 0 (never NaN); float64 gradcheck where it is positive."""
    from dibrgs_core.render.depth import expected_depth

    g = torch.Generator().manual_seed(5)
    for dt in (torch.float32, torch.float64):
        alpha = torch.rand(40, 50, 1, generator=g, dtype=dt)
        alpha[alpha < 0.3] = 0.0
        alpha[0, 0, 0] = 1e-30  # tiny but positive
        acc = alpha * torch.rand(40, 50, 1, generator=g, dtype=dt) * 1e3
        gd = torch.randn(40, 50, 1, generator=g, dtype=dt)
        outs = []
        for use_fast in (True, False):
            a, w = acc.clone().requires_grad_(), alpha.clone().requires_grad_()
            d = expected_depth(a, w, use_fast)
            assert (d.grad_fn.name() == "_ExpectedDepthBackward") is use_fast
            d.backward(gd)
            outs.append((d.detach(), a.grad, w.grad))
        for x, y in zip(*outs):
            assert torch.isfinite(x).all()
            torch.testing.assert_close(x, y, rtol=1e-6 if dt == torch.float32 else 1e-12, atol=0.0)
        off = alpha == 0
        assert (outs[0][0][off] == 0).all() and (outs[0][1][off] == 0).all() and (outs[0][2][off] == 0).all()
    # An infinite gradient where nothing covers the pixel still gives exactly 0 there, as in torch.
    a, w = torch.ones(2, 1, requires_grad=True), torch.tensor([[0.5], [0.0]], requires_grad=True)
    expected_depth(a, w, True).backward(torch.full((2, 1), math.inf))
    assert a.grad[1, 0] == 0 and w.grad[1, 0] == 0
    a = (torch.rand(6, 1, dtype=torch.float64) * 5).requires_grad_()
    w = (torch.rand(6, 1, dtype=torch.float64) + 0.1).requires_grad_()
    assert torch.autograd.gradcheck(lambda x, y: expected_depth(x, y, True), (a, w))
