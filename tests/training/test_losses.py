"""Tests for dibrgs_core.training.losses against scikit-image and at numeric extremes."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from dibrgs_core import render
from dibrgs_core.training.losses import mean_volume, photometric_loss, psnr, ssim, ssim_map
from threads import torch_threads

torch.set_num_threads(2)


def _sk_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=-1)


@pytest.fixture(params=["fast", "reference"])
def backend(request):
    """Both SSIM paths: the C++ kernel (csrc/ssim.h) and the torch formulation."""
    render.set_backend(request.param)
    yield request.param
    render.set_backend(None)


@pytest.mark.parametrize("shape", [(32, 40, 3), (24, 24, 1)])
def test_ssim_matches_skimage(shape, backend):
    rng = np.random.default_rng(0)
    a = rng.random(shape)
    # b correlated with a so SSIM is far from both 0 and 1
    b = np.clip(0.7 * a + 0.3 * rng.random(shape), 0, 1)
    ref = _sk_ssim(a, b)
    got = float(ssim(torch.tensor(a), torch.tensor(b)))
    assert 0.2 < ref < 0.95
    assert abs(got - ref) < 1e-4
    # float32 as the trainer uses it
    got32 = float(ssim(torch.tensor(a, dtype=torch.float32), torch.tensor(b, dtype=torch.float32)))
    assert abs(got32 - ref) < 1e-4


def test_ssim_identical_is_one_and_grad_finite(backend):
    rng = np.random.default_rng(1)
    a = torch.tensor(rng.random((20, 20, 3)), dtype=torch.float32, requires_grad=True)
    s = ssim(a, a.detach())
    assert abs(s.item() - 1.0) < 1e-5
    s.backward()
    assert torch.isfinite(a.grad).all()


@pytest.mark.parametrize("shape,window", [((23, 31, 3), 11), ((7, 5), 11), ((1, 1, 3), 11), ((3, 40, 2), 5),
                                          ((12, 9, 1), 3)])
def test_ssim_kernel_equals_the_torch_formulation(shape, window):
    """The C++ SSIM map and its gradient against the torch formulation in float64 (equal to
    rounding), and in float32 (as training uses it) as close to the float64 values as the torch
    formulation is (a 1x1 image is ill-conditioned in float32 for both), on images smaller and
    larger than the window (the borders replicate); the kernel's backward passes gradcheck."""
    gen = torch.Generator().manual_seed(sum(shape))
    p64 = torch.rand(shape, generator=gen, dtype=torch.float64)
    t64 = torch.rand(shape, generator=gen, dtype=torch.float64)
    up = torch.randn(shape, generator=gen, dtype=torch.float64)

    def run(backend, dt):
        render.set_backend(backend)
        try:
            p = p64.to(dt).requires_grad_()
            m = ssim_map(p, t64.to(dt), window)
            return m.detach().double(), torch.autograd.grad(m, p, up.to(dt))[0].double()
        finally:
            render.set_backend(None)

    truth = run("reference", torch.float64)
    scale = max(1.0, float(truth[1].abs().max()))
    fast64, fast32, ref32 = run("fast", torch.float64), run("fast", torch.float32), run("reference", torch.float32)
    assert fast64[0].shape == shape
    assert float((fast64[0] - truth[0]).abs().max()) < 1e-11
    assert float((fast64[1] - truth[1]).abs().max()) < 1e-11 * scale
    for i, tol in ((0, 1e-5), (1, 1e-5 * scale)):
        err, ref_err = float((fast32[i] - truth[i]).abs().max()), float((ref32[i] - truth[i]).abs().max())
        assert err < max(tol, 2.0 * ref_err)
    p = p64.clone().requires_grad_()
    render.set_backend("fast")
    try:
        assert torch.autograd.gradcheck(lambda q: ssim_map(q, t64, window), (p,))
    finally:
        render.set_backend(None)


@pytest.mark.parametrize("shape", [(23, 31, 3), (12, 9), (7, 5, 3), (40, 33, 1)])
@pytest.mark.parametrize("masked", [False, True])
def test_fused_loss_equals_the_torch_formulation(shape, masked):
    """The loss in one C++ node (render/ssim.py photometric_fast: L1 + D-SSIM, plain or masked)
    against the torch formulation: values and gradients equal to rounding in float64, within
    float32 rounding in float32; its backward passes gradcheck; the fast backend's loss is that
    one node. (An empty mask returns before either path: test_mask_restricts_loss_...)"""
    gen = torch.Generator().manual_seed(sum(shape) + masked)
    p64 = torch.rand(shape, generator=gen, dtype=torch.float64)
    t64 = torch.rand(shape, generator=gen, dtype=torch.float64)
    t64[:2] = p64[:2]  # equal pixels: |x - y| has gradient 0 there in both
    mask = (torch.rand(shape[:2], generator=gen) > 0.4) if masked else None

    def run(backend, dt):
        render.set_backend(backend)
        try:
            p = p64.to(dt).requires_grad_()
            loss = photometric_loss(p, t64.to(dt), lam=0.3, mask=mask)
            # the fast backend is the one node
            assert (type(loss.grad_fn).__name__ == "_PhotometricBackward") == (backend == "fast")
            return loss.detach().double(), torch.autograd.grad(loss, p)[0].double()
        finally:
            render.set_backend(None)

    ref64, fast64 = run("reference", torch.float64), run("fast", torch.float64)
    assert abs(float(fast64[0] - ref64[0])) < 1e-12
    assert float((fast64[1] - ref64[1]).abs().max()) < 1e-12 * float(ref64[1].abs().max())
    fast32 = run("fast", torch.float32)
    assert abs(float(fast32[0] - ref64[0])) < 1e-6
    assert float((fast32[1] - ref64[1]).abs().max()) < 1e-5 * float(ref64[1].abs().max())
    render.set_backend("fast")
    try:
        # away from |x - y| = 0, where L1 has no derivative
        q = (p64 + 0.5 * (p64 > t64).double() - 0.25).requires_grad_()
        assert torch.autograd.gradcheck(lambda x: photometric_loss(x, t64, lam=0.3, mask=mask), (q,))
    finally:
        render.set_backend(None)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_loss_kernels_give_the_same_bits_on_any_thread_count(dtype):
    """The SSIM forward's rows shared from both ends of a band by two threads (a pair a band,
    a last thread alone), the backward's and the sums' runs pulled by the threads: every output of
    the loss's kernels equals the one-thread result bit for bit on 2, 3 and 4 threads, on an image
    tall enough to split (200 rows) and one at the limit (32 rows)."""
    from dibrgs_core.render.fast import extension

    ext = extension()
    for shape in ((200, 37, 3), (32, 19, 1)):
        gen = torch.Generator().manual_seed(shape[0])
        x = torch.rand(shape, generator=gen, dtype=torch.float64).to(dtype)
        y = torch.rand(shape, generator=gen, dtype=torch.float64).to(dtype)
        wl = torch.rand(shape, generator=gen, dtype=torch.float64).to(dtype)
        ws = torch.rand(shape, generator=gen, dtype=torch.float64).to(dtype)
        up = torch.randn(shape, generator=gen, dtype=torch.float64).to(dtype)
        g = torch.tensor([0.05, 0.25, 0.4, 0.25, 0.05], dtype=dtype)

        def run():
            f = ext.ssim_forward(x, y, g)
            loss, a, b, c = ext.photometric_forward(x, y, g, wl, ws, 0.3)
            return [*f, loss, ext.ssim_backward(up, x, y, *f[1:], g),
                    ext.photometric_backward(torch.tensor(0.7, dtype=dtype), x, y, a, b, c, g, wl, ws, 0.3)]

        with torch_threads(1):
            one = run()
        for n in (2, 3, 4):
            with torch_threads(n):
                many = run()
            for i, (u, v) in enumerate(zip(one, many)):
                assert torch.equal(u, v), (shape, n, i)


def test_ssim_gradient_reaches_a_target_that_needs_one():
    """With a target that needs a gradient the torch formulation runs (the kernel has none for it)."""
    a = torch.rand(10, 12, 3, dtype=torch.float64, requires_grad=True)
    b = torch.rand(10, 12, 3, dtype=torch.float64, requires_grad=True)
    ssim(a, b).backward()
    assert a.grad.abs().sum() > 0 and b.grad.abs().sum() > 0


@pytest.mark.stability
def test_extremes_black_constant_images_finite(backend):
    """SSIM/L1 loss on all-black and constant images: finite loss and gradients."""
    black = torch.zeros(16, 16, 3, requires_grad=True)
    white = torch.ones(16, 16, 3)
    for gt in (torch.zeros(16, 16, 3), white):
        loss = photometric_loss(black, gt)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(black.grad).all()
        black.grad = None
    assert float(psnr(black.detach(), torch.zeros(16, 16, 3))) == pytest.approx(100.0)
    assert float(psnr(black.detach(), white)) == pytest.approx(0.0, abs=1e-6)


def test_photometric_loss_value():
    rng = np.random.default_rng(2)
    a = torch.tensor(rng.random((16, 16, 3)), dtype=torch.float64)
    b = torch.tensor(rng.random((16, 16, 3)), dtype=torch.float64)
    want = 0.8 * (a - b).abs().mean() + 0.2 * (1 - ssim(a, b))
    assert float(photometric_loss(a, b)) == pytest.approx(float(want), rel=1e-9)
    # a full mask gives the same L1 term; SSIM term then averages over all pixels
    full = photometric_loss(a, b, mask=torch.ones(16, 16, dtype=torch.bool))
    assert torch.isfinite(full) and float(full) > 0


@pytest.mark.stability
def test_mask_restricts_loss_and_empty_mask_is_zero():
    """Pseudo-view loss with no valid pixel: exactly zero loss and zero gradients, no NaN."""
    gt = torch.zeros(24, 24, 3)
    pred = torch.zeros(24, 24, 3)
    pred[:, 12:] = 1.0  # wrong only on the right half
    pred.requires_grad_(True)
    left = torch.zeros(24, 24, dtype=torch.bool)
    left[:, :6] = True  # far enough from the error that SSIM windows barely reach it
    l_left = photometric_loss(pred, gt, mask=left)
    l_right = photometric_loss(pred, gt, mask=~left)
    assert l_left.item() < 0.01 < l_right.item()
    empty = photometric_loss(pred, gt, mask=torch.zeros(24, 24, dtype=torch.bool))
    assert empty.item() == 0.0
    empty.backward()
    assert torch.isfinite(pred.grad).all() and float(pred.grad.abs().sum()) == 0.0


def test_pixels_of_weight_zero_take_no_part_in_the_loss(backend):
    """Whatever is rendered where the weight is 0 (a photo's fill, a rejected pseudo-view pixel) gets no
    gradient and changes neither term, SSIM's windows that reach it included; an SSIM score with the
    mask is the same, and PSNR is over the weighted pixels."""
    rng = np.random.default_rng(0)
    gt = torch.from_numpy(rng.random((24, 24, 3), dtype=np.float32))
    pred = (gt + 0.1 * torch.from_numpy(rng.standard_normal((24, 24, 3)).astype(np.float32))).clamp(0, 1)
    keep = torch.ones(24, 24)
    keep[:8, :8] = 0.0
    keep[12:, :] = 0.5  # a pseudo view's padding: weighted, not left out
    other = pred.clone()
    other[:8, :8] = torch.from_numpy(rng.random((8, 8, 3), dtype=np.float32))
    p = pred.clone().requires_grad_(True)
    loss = photometric_loss(p, gt, mask=keep)
    loss.backward()
    assert float(p.grad[:8, :8].abs().max()) == 0.0 and float(p.grad[8:12].abs().max()) > 0
    assert photometric_loss(other, gt, mask=keep).item() == pytest.approx(loss.item(), abs=1e-6)
    assert ssim(other, gt, mask=keep).item() == pytest.approx(ssim(pred, gt, mask=keep).item(), abs=1e-6)
    assert psnr(other, gt, mask=keep > 0).item() == pytest.approx(psnr(pred, gt, mask=keep > 0).item(), abs=1e-5)
    assert ssim(other, gt).item() != pytest.approx(ssim(pred, gt).item(), abs=1e-4)  # without it, it does count


def test_psnr_known_value():
    a = torch.zeros(8, 8, 3)
    b = torch.full((8, 8, 3), 0.1)
    assert float(psnr(a, b)) == pytest.approx(20.0, abs=1e-4)
    m = torch.zeros(8, 8, dtype=torch.bool)
    assert float(psnr(a, b, mask=m)) == 0.0


def test_ssim_after_inference_mode_still_trains():
    """The cached interior weights of the mean SSIM: a first call in inference mode (evaluation)
    must not hand a later training call a tensor that autograd cannot save."""
    g = torch.Generator().manual_seed(11)
    a, b = torch.rand(24, 20, 3, generator=g), torch.rand(24, 20, 3, generator=g)
    with torch.inference_mode():
        s0 = float(ssim(a, b))
    p = a.clone().requires_grad_()
    s1 = ssim(p, b)
    s1.backward()
    assert abs(float(s1.detach()) - s0) < 1e-6 and p.grad is not None and bool(torch.isfinite(p.grad).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 7, 20_000])
def test_mean_volume_equals_torch_prod(backend, dtype, n):
    """The volume regulariser on either path: torch's ``prod(scales / unit).mean()`` and its
    gradient, whichever node computed it (the C++ one on "fast")."""
    g = torch.Generator().manual_seed(n)
    unit = 0.37
    s0 = (torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 1e-3) * unit
    s = s0.clone().requires_grad_(True)
    v = mean_volume(s, unit, weight=3.0)  # the weight inside the node on "fast"
    assert (v.grad_fn.name() == "_MeanVolumeBackward") is (backend == "fast"), v.grad_fn.name()
    v.backward()
    t = s0.clone().requires_grad_(True)
    w = (t / unit).prod(dim=1).mean()
    (3.0 * w).backward()
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    assert v.dtype == dtype and abs(v.item() - 3.0 * w.item()) <= 3.0 * tol * w.item()
    torch.testing.assert_close(s.grad, t.grad, rtol=tol * 10, atol=0.0)


@pytest.mark.stability
@pytest.mark.parametrize("units", [1e-6, 1e-3, 1e3, 1e6])
def test_mean_volume_is_the_same_in_any_units(backend, units):
    """Scales in another scene's units with the unit scaled alike: the same value and the same
    gradient once rescaled (no overflow or underflow at either end)."""
    g = torch.Generator().manual_seed(1)
    s = torch.rand(1000, 3, generator=g) * 0.1 + 1e-3
    a = s.clone().requires_grad_(True)
    b = (s * units).requires_grad_(True)
    va, vb = mean_volume(a, 1.0), mean_volume(b, units)
    va.backward()
    vb.backward()
    assert torch.isfinite(vb) and abs(va.item() - vb.item()) <= 1e-5 * va.item()
    torch.testing.assert_close(b.grad * units, a.grad, rtol=1e-5, atol=0.0)


@pytest.mark.stability
def test_mean_volume_of_no_gaussians_is_zero(backend):
    """No Gaussian in view: the regulariser is 0 with an empty gradient (torch's mean of nothing is NaN)."""
    s = torch.zeros(0, 3, requires_grad=True)
    v = mean_volume(s, 2.0)
    v.backward()
    assert v.item() == 0.0 and s.grad.shape == (0, 3)


def test_mean_volume_gradcheck():
    render.set_backend("fast")
    try:
        s = (torch.rand(6, 3, dtype=torch.float64) + 0.1).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda x: mean_volume(x, 0.7), (s,))
    finally:
        render.set_backend(None)
