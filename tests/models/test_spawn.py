"""Neural Gaussians spawned from anchor decoder outputs: the C++ pass against the torch formulation."""
from __future__ import annotations

import pytest
import torch

from dibrgs_core.models.spawn import activate_scaling, spawn, spawn_reference, take_rows, true_indices
from dibrgs_core.render import set_backend
from model_synth import camera_tensors, small_camera, small_model

torch.set_num_threads(1)


def _inputs(M: int, k: int, dtype: torch.dtype, seed: int = 0, special: bool = True) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    nop = torch.tanh(torch.randn(M * k, generator=g, dtype=dtype))
    color = torch.rand(M, 3 * k, generator=g, dtype=dtype)
    cov = torch.randn(M, 7 * k, generator=g, dtype=dtype)
    anchor = torch.randn(M, 3, generator=g, dtype=dtype) * 100.0
    log_scal = torch.log(torch.rand(M, 6, generator=g, dtype=dtype) + 0.1)
    offset = torch.randn(M, k, 3, generator=g, dtype=dtype)
    if special and M > 3:
        nop[3 * k + 2] = 0.5
        cov.view(M, k, 7)[3, 2, 3:] = 0.0  # a kept row with a zero quaternion: the identity, no gradient
        nop[: k] = -0.5                    # an anchor with no Gaussian
        log_scal[2, 1], log_scal[2, 4] = 25.0, -40.0  # beyond the clamp: a constant scaling, no gradient
    return [t.requires_grad_() for t in (nop, color, cov, anchor, log_scal, offset)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fast_matches_reference_values_and_gradients(dtype):
    M, k = 64, 10
    fast_in = _inputs(M, k, dtype)
    ref_in = [t.detach().clone().requires_grad_() for t in fast_in]
    a = spawn(*fast_in, backend="fast")
    b = spawn_reference(*ref_in[:4], activate_scaling(ref_in[4]), ref_in[5])
    assert torch.equal(a.selected, b.selected)
    assert 0 < int(a.selected.sum()) < M * k
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    for x, y in zip(a[:5], b[:5]):
        assert x.shape == y.shape and x.dtype == dtype
        torch.testing.assert_close(x, y, rtol=tol, atol=tol)
    row = int(torch.nonzero(b.selected).squeeze(1).tolist().index(3 * k + 2))
    assert a.quats[row].tolist() == [1.0, 0.0, 0.0, 0.0]
    w = [torch.randn_like(t) for t in b[:5]]
    sum((wi * t).sum() for wi, t in zip(w, a[:5])).backward()
    sum((wi * t).sum() for wi, t in zip(w, b[:5])).backward()
    for x, y in zip(fast_in, ref_in):
        torch.testing.assert_close(x.grad, y.grad, rtol=10 * tol, atol=10 * tol)
    assert float(fast_in[2].grad.view(M, k, 7)[3, 2, 3:].abs().sum()) == 0.0
    assert float(fast_in[4].grad[2, 1]) == 0.0 and float(fast_in[4].grad[2, 4]) == 0.0
    # Outside the clamp the gradient is 0 even when what arrives is infinite (as torch's clamp gives).
    x = [t.detach().clone().requires_grad_() for t in fast_in]
    c = spawn(*x, backend="fast")
    c.means.backward(torch.full_like(c.means, float("inf")))
    assert float(x[4].grad[2, 1]) == 0.0
    assert torch.isfinite(a.means).all() and torch.isfinite(a.scales).all()


@pytest.mark.parametrize("used", range(5))
def test_one_output_alone_gives_the_reference_gradients(used):
    """A loss on one of means, quats, scales, opacities, colours alone: the others' gradients
    reach the C++ backward as None (not materialised), and it reads them as zeros."""
    M, k = 16, 4
    fast_in = _inputs(M, k, torch.float64, seed=2)
    ref_in = [t.detach().clone().requires_grad_() for t in fast_in]
    a = spawn(*fast_in, backend="fast")
    b = spawn_reference(*ref_in[:4], activate_scaling(ref_in[4]), ref_in[5])
    w = torch.randn_like(b[used])
    (w * a[used]).sum().backward()
    (w * b[used]).sum().backward()
    got = [x.grad for x in fast_in]
    assert sum(float(g.abs().sum()) for g in got if g is not None) > 0
    for x, y in zip(fast_in, ref_in):
        gx = torch.zeros_like(x) if x.grad is None else x.grad
        gy = torch.zeros_like(y) if y.grad is None else y.grad
        torch.testing.assert_close(gx, gy, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("backend", ["fast", "reference"])
def test_opacities_as_the_heads_rows(backend):
    # The decoder's opacity head gives (M, k): spawning takes it as it is (no reshape node) and
    # gives the same Gaussians and gradients as from the flat opacities.
    M, k = 16, 5
    x = _inputs(M, k, torch.float64, seed=7)
    y = [t.detach().clone().requires_grad_() for t in x]
    a = spawn(x[0].view(M, k), *x[1:], backend=backend)
    b = spawn(*y, backend=backend)
    assert torch.equal(a.selected, b.selected) and a.selected.shape == (M * k,)
    for p, q in zip(a[:5], b[:5]):
        assert torch.equal(p, q)
    w = [torch.randn_like(t) for t in a[:5]]
    sum((wi * t).sum() for wi, t in zip(w, a[:5])).backward()
    sum((wi * t).sum() for wi, t in zip(w, b[:5])).backward()
    for p, q in zip(x, y):
        torch.testing.assert_close(p.grad, q.grad, rtol=1e-12, atol=1e-12)


def test_colour_gradient_read_with_its_row_stride():
    # The renderer composites the colours beside each Gaussian's depth and a one, so the colours'
    # gradient arrives as three columns of a wider one: read in place, it must give what a
    # contiguous copy gives.
    x = _inputs(32, 6, torch.float32, seed=5)
    y = [t.detach().clone().requires_grad_() for t in x]
    a, b = spawn(*x, backend="fast"), spawn(*y, backend="fast")
    w = torch.randn(a.colors.shape[0], 5, generator=torch.Generator().manual_seed(1))
    wide = torch.cat([a.colors, a.means[:, 2:], torch.ones_like(a.opacities)[:, None]], 1)
    g = torch.autograd.grad((w * wide).sum(), a.colors, retain_graph=True)[0]
    assert g.stride() == (5, 1)  # what spawn_backward is given for the colours
    (w * wide).sum().backward()
    ((w[:, :3] * b.colors).sum() + (w[:, 3:4] * b.means[:, 2:]).sum()).backward()
    for p, q in zip(x, y):
        assert p.grad is not None and torch.equal(p.grad, q.grad)


def test_fast_gradients_against_finite_differences():
    torch.autograd.gradcheck(lambda *t: tuple(spawn(*t, backend="fast")[:5]), _inputs(5, 4, torch.float64, seed=3, special=False))


def test_no_visible_anchor_and_no_kept_row():
    for M in (0, 4):
        x = _inputs(M, 3, torch.float32)
        with torch.no_grad():
            x[0].fill_(-1.0)
        out = spawn(*x, backend="fast")
        assert out.means.shape == (0, 3) and out.quats.shape == (0, 4) and out.opacities.shape == (0,)
        (out.means.sum() + out.colors.sum()).backward()
        assert all(t.grad is None or float(t.grad.abs().sum()) == 0.0 for t in x)


def test_model_decodes_the_same_on_both_backends():
    """The model's decode through the C++ pass and through torch: same Gaussians, same parameter gradients."""
    m = small_model(300)
    with torch.no_grad():
        m.mlp_opacity[2].bias.fill_(0.1)
    c = camera_tensors(small_camera())
    grads = {}
    for backend in ("fast", "reference"):
        set_backend(backend)
        try:
            m.zero_grad()
            d = m.decode(c.K, c.w2c, c.center, 32, 32)
            (d.means.square().sum() + d.quats.sum() + d.scales.sum() + d.opacities.sum() + d.colors.sum()).backward()
            grads[backend] = (d, {n: p.grad.clone() for n, p in m.named_parameters() if p.grad is not None})
        finally:
            set_backend(None)
    (df, gf), (dr, gr) = grads["fast"], grads["reference"]
    assert df.means.shape[0] == dr.means.shape[0] > 0
    for name in ("means", "quats", "scales", "opacities", "colors"):
        torch.testing.assert_close(getattr(df, name), getattr(dr, name), rtol=1e-6, atol=1e-5)
    assert gf.keys() == gr.keys() and {"anchor", "offset", "scaling", "anchor_feat"} <= gf.keys()
    for n in gf:
        torch.testing.assert_close(gf[n], gr[n], rtol=1e-4, atol=1e-5)


@pytest.mark.stability
def test_extreme_magnitudes_agree_and_stay_finite():
    """Anchor scalings at the clamp's ends (exp(20), exp(-30)), scale logits of +-1e30, quaternions
    whose squares overflow float32 or underflow it: both paths give the same finite Gaussians and
    gradients; a long quaternion keeps its direction."""
    M, k = 4, 3
    nop = torch.full((M * k,), 0.5)
    color = torch.rand(M, 3 * k, generator=torch.Generator().manual_seed(1))
    cov = torch.randn(M, 7 * k, generator=torch.Generator().manual_seed(2))
    c = cov.view(M, k, 7)
    c[0, 0, :3] = torch.tensor([1e30, -1e30, 0.0])
    c[0, 1, 3:] = torch.tensor([1e20, 1e20, 0.0, 0.0])
    c[0, 2, 3:] = torch.tensor([3e38, 0.0, 0.0, -3e38])
    c[1, 0, 3:] = torch.tensor([1e-20, 1e-20, 0.0, 0.0])  # shorter than 1e-12: the identity
    anchor = torch.randn(M, 3, generator=torch.Generator().manual_seed(3)) * 1e6
    log_scal = torch.tensor([[20.0, 20.0, 20.0, -30.0, -30.0, -30.0]] * M)
    offset = torch.randn(M, k, 3, generator=torch.Generator().manual_seed(4))
    fast_in = [t.requires_grad_() for t in (nop, color, cov, anchor, log_scal, offset)]
    ref_in = [t.detach().clone().requires_grad_() for t in fast_in]
    a = spawn(*fast_in, backend="fast")
    b = spawn_reference(*ref_in[:4], activate_scaling(ref_in[4]), ref_in[5])
    h = 2 ** -0.5
    for out in (a, b):
        assert all(bool(torch.isfinite(t).all()) for t in out[:5])
        torch.testing.assert_close(out.quats[1], torch.tensor([h, h, 0.0, 0.0]))
        torch.testing.assert_close(out.quats[2], torch.tensor([h, 0.0, 0.0, -h]))
        assert out.quats[3].tolist() == [1.0, 0.0, 0.0, 0.0]
    for x, y in zip(a[:5], b[:5]):
        torch.testing.assert_close(x, y, rtol=1e-6, atol=0.0)
    sum(t.sum() for t in a[:5]).backward()
    sum(t.sum() for t in b[:5]).backward()
    for x, y in zip(fast_in, ref_in):
        assert bool(torch.isfinite(x.grad).all())
        torch.testing.assert_close(x.grad, y.grad, rtol=1e-5, atol=1e-30)


def test_anchor_visibility_is_the_same_on_both_backends():
    """Frustum culling through the C++ pass and through torch: the same anchors, among them
    anchors behind the camera, beyond each image edge but reaching in through their offsets
    or scales, at the near plane, non-finite, and with extreme log scalings."""
    m = small_model(400)
    c = camera_tensors(small_camera())
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        # Spread the anchors well past the image and behind the camera, some Gaussians large.
        centre = m.anchor.mean(0)
        m.anchor.copy_(centre + (m.anchor - centre) * 6.0)
        m.offset.copy_(torch.randn(m.offset.shape, generator=g) * 3.0)
        m.scaling.add_(torch.randn(m.scaling.shape, generator=g) * 2.0)
        m.scaling[:5] = torch.tensor([40.0, -50.0, 0.0, 25.0, -45.0, 1.0])
        m.anchor[5] = float("nan")
        m.anchor[6, 0] = float("inf")
    out = {}
    for backend in ("fast", "reference"):
        set_backend(backend)
        try:
            out[backend] = m.visible_anchors(c.K, c.w2c, 32, 32)
        finally:
            set_backend(None)
    f, r = out["fast"], out["reference"]
    assert f.dtype == torch.bool and f.shape == (400,)
    assert 20 < int(r.sum()) < 380  # both kinds present
    assert not f[5] and not f[6]
    assert torch.equal(f, r)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kind", ["increasing", "repeats", "unordered", "empty", "all"])
def test_take_rows_values_and_gradients(dtype, kind):
    """take_rows equals index_select forward and backward on the C++ path, for the strictly
    increasing indices it is fast for (unselected rows get exact zeros) and for the others."""
    g = torch.Generator().manual_seed(9)
    N = 3000  # more than one parallel chunk
    src = torch.randn(N, 4, 3, generator=g, dtype=dtype)
    idx = {"increasing": torch.sort(torch.randperm(N, generator=g)[:1700]).values,
           "repeats": torch.tensor([5, 5, 2999, 0, 5], dtype=torch.int64),
           "unordered": torch.randperm(N, generator=g)[:900],
           "empty": torch.zeros(0, dtype=torch.int64),
           "all": torch.arange(N)}[kind]
    up = torch.randn((len(idx), 4, 3), generator=g, dtype=dtype)
    grads = []
    for backend in ("fast", "reference"):
        t = src.clone().requires_grad_()
        other = torch.randn(N, 2, generator=g, dtype=dtype, requires_grad=True)  # unused: no gradient
        out, out2 = take_rows([t, other], idx, backend=backend)
        assert torch.equal(out, src.index_select(0, idx)) and torch.equal(out2, other.detach().index_select(0, idx))
        (out * up).sum().backward()
        assert other.grad is None
        grads.append(t.grad)
    assert torch.equal(grads[0], grads[1])
    if kind == "increasing":
        unselected = torch.ones(N, dtype=torch.bool)
        unselected[idx] = False
        assert bool((grads[0][unselected] == 0).all()) and bool((grads[0][idx] == up).all())
    with pytest.raises(RuntimeError, match="out of range"):
        take_rows([src], torch.tensor([N]), backend="fast")


@pytest.mark.parametrize("kind", ["random", "none", "all", "empty", "strided"])
def test_true_indices_equal_torch_nonzero(kind):
    """The C++ positions of a mask's true entries equal torch.nonzero's, int64 and increasing,
    on both backends (a strided view of a mask included)."""
    g = torch.Generator().manual_seed(7)
    base = torch.rand(2 * 3001, generator=g) > 0.4
    mask = {"random": base[:3001], "none": torch.zeros(50, dtype=torch.bool),
            "all": torch.ones(77, dtype=torch.bool), "empty": torch.zeros(0, dtype=torch.bool),
            "strided": base[::2]}[kind]
    want = torch.nonzero(mask).squeeze(1)
    for backend in ("fast", "reference"):
        got = true_indices(mask, backend=backend)
        assert got.dtype == torch.int64 and torch.equal(got, want)


def test_spawn_does_not_depend_on_threads():
    """Runs of anchors pulled by the threads (the calling thread's half was the slower one): the
    spawned Gaussians and every input gradient equal the one-thread result bit for bit on 2 and 3
    threads (3,000 anchors, about half of their rows kept)."""
    from threads import torch_threads

    runs = {}
    for nt in (1, 2, 3):
        with torch_threads(nt):
            x = _inputs(3000, 10, torch.float32, seed=4)
            out = spawn(*x, backend="fast")
            w = torch.Generator().manual_seed(9)
            sum((torch.randn(t.shape, generator=w) * t).sum() for t in out[:5]).backward()
            runs[nt] = [*out[:5], out.selected, *(t.grad for t in x)]
    for nt in (2, 3):
        for i, (a, b) in enumerate(zip(runs[1], runs[nt])):
            assert torch.equal(a, b), (nt, i)
