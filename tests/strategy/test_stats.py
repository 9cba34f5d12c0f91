"""The densification statistic (strategy/stats.py): the C++ pass and the torch path give the sums
of a per-Gaussian brute force, bit for bit, for neural Gaussians (offset slots) and 3DGS (one slot
a Gaussian), with invisible Gaussians skipped and non-finite gradients counted as 0."""
from __future__ import annotations

import math

import pytest
import torch

from dibrgs_core.render import set_backend
from dibrgs_core.strategy.stats import add_grad_norms


def _view(seed: int, n_anchors: int, k: int):
    """A view's inputs: visible anchors, their rasterized offsets, the Gaussians' gradients."""
    g = torch.Generator().manual_seed(seed)
    aidx = torch.sort(torch.randperm(n_anchors, generator=g)[: n_anchors * 2 // 3]).values
    selected = torch.rand(len(aidx) * k, generator=g) > 0.3
    G = int(selected.sum())
    grad = torch.randn(G, 2, generator=g) * torch.exp(torch.randn(G, 1, generator=g) * 4)
    grad[::17, 0] = math.nan
    grad[5::23, 1] = math.inf
    visible = torch.rand(G, generator=g) > 0.2
    return aidx, selected, grad, visible


def _brute(n_slots, grad, visible, sx, sy, aidx=None, selected=None, k=1):
    acc, den = [0.0] * n_slots, [0.0] * n_slots
    slots = ([int(aidx[p // k]) * k + p % k for p in range(len(selected)) if selected[p]] if aidx is not None
             else list(range(len(visible))))
    for i, s in enumerate(slots):
        if not visible[i]:
            continue
        x = torch.tensor(float(grad[i, 0])) * torch.tensor(sx)  # float32 products, as the kernels
        y = torch.tensor(float(grad[i, 1])) * torch.tensor(sy)
        v = torch.stack([x, y]).norm()
        v = 0.0 if not torch.isfinite(v) else float(v)
        acc[s] = float(torch.tensor(acc[s]) + torch.tensor(v))
        den[s] += 1.0
    return torch.tensor(acc), torch.tensor(den)


@pytest.mark.parametrize("backend", ["fast", "reference"])
@pytest.mark.parametrize("kind", ["anchors", "gaussians"])
def test_grad_norm_sums_match_a_brute_force(backend, kind):
    k, n_anchors = 10, 60
    aidx, selected, grad, visible = _view(3, n_anchors, k)
    W, H = 64, 48
    n = n_anchors * k if kind == "anchors" else len(visible)
    acc = torch.rand(n) * 0.1  # running sums from earlier views
    den = torch.randint(0, 5, (n,)).float()
    want_acc, want_den = _brute(n, grad, visible, W / 2.0, H / 2.0,
                                *((aidx, selected, k) if kind == "anchors" else ()))
    want_acc += acc
    want_den += den
    set_backend(backend)
    try:
        if kind == "anchors":
            add_grad_norms(acc, den, grad, visible, W, H, aidx, selected, k)
        else:
            add_grad_norms(acc, den, grad, visible, W, H)
    finally:
        set_backend(None)
    assert torch.isfinite(acc).all()
    assert torch.equal(den, want_den)
    torch.testing.assert_close(acc, want_acc, rtol=1e-6, atol=0.0)


def test_both_paths_give_the_same_bits():
    k = 10
    aidx, selected, grad, visible = _view(7, 300, k)
    out = []
    for backend in ("fast", "reference"):
        acc, den = torch.zeros(300 * k), torch.zeros(300 * k)
        set_backend(backend)
        try:
            add_grad_norms(acc, den, grad, visible, 256, 256, aidx, selected, k)
        finally:
            set_backend(None)
        out.append((acc, den))
    assert float(out[0][1].sum()) > 0
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])


def test_mismatched_counts_are_an_error():
    aidx, selected, grad, visible = _view(1, 40, 10)
    acc, den = torch.zeros(400), torch.zeros(400)
    set_backend("fast")
    try:
        with pytest.raises(RuntimeError, match="selected offsets"):
            add_grad_norms(acc, den, grad[:-1], visible[:-1], 32, 32, aidx, selected, 10)
        with pytest.raises(RuntimeError, match="outside acc"):
            add_grad_norms(acc[:-10], den[:-10], grad, visible, 32, 32, aidx + 40 - int(aidx.max()) - 1, selected, 10)
    finally:
        set_backend(None)
    assert not acc.any() and not den.any()  # nothing added before the errors
