"""The factorised IBR projection: P applied after sampling equals sampling the P-projected maps.

``IBRFeatures.forward`` samples each anchor's raw encoder features once and applies P as one
matmul; these tests hold it to the definition (bilinear border ``grid_sample`` of the fused
maps ``feature_maps()``, averaged over the views that see the anchor, zeros for nobody) in
values and in gradients w.r.t. P, at borders, outside the image and behind cameras, and
check that the per-anchor cache follows anchors being added, pruned and reordered.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dibrgs_core.camera.pinhole import Camera
from dibrgs_core.models.base import CameraTensors
from dibrgs_core.models.ibr.features import IBRFeatures
from dibrgs_core.models.ibr.projection import project_rows
from dibrgs_core.models.ibr.resnet import ResNetFeatures
from dibrgs_core.models.ibr.sampling import upsampled_taps
from dibrgs_core.models.ibr.vit import ViTFeatures
from dibrgs_core.render import set_backend
from dibrgs_core.render.fast import available
from model_synth import ring_views, small_camera, small_model

torch.set_num_threads(2)


def _views(W: int = 70, H: int = 52, V: int = 3):
    """Sizes not divisible by the pyramid's or the ViT's strides."""
    return ring_views(W, H, V)


def _ibr(encoder: str, W: int = 70, H: int = 52, views=None) -> tuple[IBRFeatures, list[Camera]]:
    """IBR features of ``views`` ((images, cameras); default :func:`_views`) with P moved off its init."""
    images, cams = views if views is not None else _views(W, H)
    kw = {}
    if encoder == "dino":
        torch.manual_seed(0)
        kw = {"resnet": ResNetFeatures((1, 1, 1, 1), width=4),
              "vit": ViTFeatures(patch=8, dim=64, depth=2, heads=4, img_size=32)}
    ibr = IBRFeatures(encoder, images, cams, c_r=8, **kw)
    torch.manual_seed(3)
    with torch.no_grad():  # biases away from 0 so that "seen by nobody" is tested
        for p in ibr.projection_parameters():
            p.add_(0.3 * torch.randn_like(p))
    return ibr, cams


def _old_forward(ibr: IBRFeatures, cams: list[Camera], X: torch.Tensor) -> torch.Tensor:
    """The definition: sample the fused maps at each view's projection, average where seen."""
    maps = ibr.feature_maps()
    total = torch.zeros(X.shape[0], ibr.c_r)
    cnt = torch.zeros(X.shape[0], 1)
    for i, c in enumerate(cams):
        uv, z = c.project(X.double().numpy())
        ok = torch.tensor((z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width)
                          & (uv[:, 1] >= 0) & (uv[:, 1] < c.height))
        g = torch.tensor(np.stack([2 * uv[:, 0] / c.width - 1, 2 * uv[:, 1] / c.height - 1], -1),
                         dtype=torch.float32)
        g = torch.where(ok[:, None], g, torch.zeros_like(g))
        s = F.grid_sample(maps[i][None], g[None, None], mode="bilinear", padding_mode="border",
                          align_corners=False)[0, :, 0].T
        total = total + s * ok[:, None]
        cnt = cnt + ok[:, None]
    return total / cnt.clamp(min=1)


def _anchors(cams: list[Camera], n: int = 400) -> torch.Tensor:
    """Random anchors plus hard cases: image corners and edges (just inside, just outside),
    a point behind camera 0, points seen by nobody."""
    torch.manual_seed(1)
    X = [torch.randn(n, 3) * 1.5]
    cam = cams[0]
    Kinv, c2w = np.linalg.inv(cam.K), cam.c2w
    eps = 1e-3
    W, H = cam.width, cam.height
    for u, v in [(0, 0), (eps, eps), (W - eps, H - eps), (W / 2, 0), (W / 2, H - eps), (0, H / 2),
                 (W - eps, H / 2), (-eps, H / 2), (W + eps, H / 2), (W / 2, -eps), (W / 2, H + 0.5)]:
        ray = Kinv @ np.array([u, v, 1.0])
        X.append(torch.tensor(c2w[:3, :3] @ (ray * 2.5) + cam.center, dtype=torch.float32)[None])
    X.append(torch.tensor(2 * cam.center, dtype=torch.float32)[None])  # behind camera 0 (and others)
    X.append(torch.tensor([[1e3, 1e3, -1e3], [0.0, 0.0, 1e9]]))           # nobody sees these
    return torch.cat(X)


def test_taps_equal_sampling_the_upsampled_map():
    torch.manual_seed(0)
    for (h, w), (H, W), mode in [((13, 17), (26, 35), "bilinear"), ((6, 9), (26, 35), "nearest"),
                                 ((26, 35), (26, 35), "bilinear"), ((1, 1), (5, 7), "bilinear"),
                                 ((3, 4), (26, 35), "bilinear"), ((7, 5), (26, 35), "nearest")]:
        m = torch.rand(1, 5, h, w)
        g = torch.rand(2000, 2) * 2.4 - 1.2  # some outside [-1, 1]: border padding
        g[:4] = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [1.0, -1.0]])
        up = F.interpolate(m, size=(H, W), mode=mode, **({} if mode == "nearest" else {"align_corners": False}))
        want = F.grid_sample(up, g[None, None], mode="bilinear", padding_mode="border",
                             align_corners=False)[0, :, 0].T
        idx, wt = upsampled_taps(g, (h, w), (H, W), mode)
        got = F.embedding_bag(idx, m[0].reshape(5, -1).T, per_sample_weights=wt, mode="sum")
        assert torch.allclose(got, want, atol=5e-6), (h, w, mode)
        assert torch.allclose(wt.sum(-1), torch.ones(2000), atol=1e-6)  # why P commutes


@pytest.mark.parametrize("encoder", ["pyramid", "dino"])
def test_values_and_gradients_equal_the_fused_map_path(encoder):
    ibr, cams = _ibr(encoder)
    X = _anchors(cams)
    old = _old_forward(ibr, cams, X)
    new = ibr(X)
    seen = old.abs().sum(1) > 0
    assert seen.sum() > 200 and (~seen).sum() >= 3   # the hard cases include unseen anchors
    assert torch.equal(new[~seen], torch.zeros_like(new[~seen]))
    assert torch.allclose(new, old, atol=2e-5, rtol=1e-5)
    # gradients w.r.t. every part of P, for a loss mixing all anchors' features
    gw = torch.randn_like(old)
    params = ibr.projection_parameters()
    g_old = torch.autograd.grad((old * gw).sum(), params)
    g_new = torch.autograd.grad((new * gw).sum(), params)
    for a, b in zip(g_old, g_new):
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)
    # a mask selects rows of the same result
    mask = torch.rand(X.shape[0]) < 0.5
    assert torch.allclose(ibr(X, mask), new[mask], atol=1e-6)


@pytest.mark.parametrize("encoder", ["pyramid", "dino"])
def test_views_of_different_sizes_each_keep_their_own(encoder):
    """Photos of several sizes (a portrait one among landscape ones, a third size): each view's
    maps have its own size and the factorised path still equals the definition."""
    (a, ca), (b, cb), (c, cc) = (ring_views(W, H, 3) for W, H in ((70, 52), (52, 70), (41, 33)))
    ibr, cams = _ibr(encoder, views=([a[0], b[1], a[2], c[0]], [ca[0], cb[1], ca[2], cc[0]]))
    assert [tuple(m.shape) for m in ibr.feature_maps()] == [(8, 26, 35), (8, 35, 26), (8, 26, 35), (8, 16, 20)]
    # and the border cases of the other sizes (not those exactly on u = 0, where float32 and float64
    # projections may fall either side)
    edges = [i for i in range(14) if i not in (0, 5)]
    X = torch.cat([_anchors(cams), _anchors([cams[1]], n=0)[edges], _anchors([cams[3]], n=0)[edges]])
    old, new = _old_forward(ibr, cams, X), ibr(X)
    assert (old.abs().sum(1) > 0).sum() > 300
    assert torch.allclose(new, old, atol=2e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="camera '001' is 52x70, its image 70x52"):
        _ibr(encoder, views=([a[0], a[1]], [ca[0], cb[1]]))


def _count_sampling(monkeypatch, ibr) -> list[int]:
    """The number of positions of each call of ``ibr._sample_rows`` from now on."""
    sampled: list[int] = []
    real = ibr._sample_rows

    def counting(P):
        sampled.append(P.shape[0])
        return real(P)

    monkeypatch.setattr(ibr, "_sample_rows", counting)
    return sampled


def test_rows_follow_growth_and_pruning(monkeypatch):
    """Adding, pruning and reordering anchors: carried rows are reused, only new positions are
    sampled, and the result is bit-identical to a fresh module's (which samples all at once)."""
    ibr, cams = _ibr("pyramid")
    X = _anchors(cams)
    sampled = _count_sampling(monkeypatch, ibr)
    a = ibr(X)
    assert sampled == [X.shape[0]]
    assert torch.equal(ibr(X.clone()), a) and len(sampled) == 1  # same positions: no resampling
    torch.manual_seed(5)
    keep = torch.rand(X.shape[0]) > 0.3
    new = torch.randn(37, 3)
    Y = torch.cat([X[keep], new])
    Y = Y[torch.randperm(Y.shape[0])]
    b = ibr(Y)
    assert sampled[1:] == [37]
    fresh, _ = _ibr("pyramid")
    fresh.load_state_dict(ibr.state_dict())
    assert torch.equal(b, fresh(Y))  # bit-identical, as a resumed run needs
    assert torch.allclose(b, _old_forward(ibr, cams, Y), atol=2e-5)
    assert ibr(Y[:0]).shape == (0, 8)


def test_rows_cache_sees_writes_into_the_same_tensor(monkeypatch):
    """The anchor tensor cached last is a hit without comparing its bits, so a write into it in
    place (which bumps its version counter) must still resample what changed."""
    ibr, cams = _ibr("pyramid")
    X = _anchors(cams)
    sampled = _count_sampling(monkeypatch, ibr)
    a = ibr(X)
    assert torch.equal(ibr(X), a) and sampled == [X.shape[0]]  # the same tensor: a hit
    with torch.no_grad():
        X[3] += 0.25 * X[3].abs().max()
    b = ibr(X)
    assert sampled == [X.shape[0], 1]  # only the moved anchor
    fresh, _ = _ibr("pyramid")
    fresh.load_state_dict(ibr.state_dict())
    assert torch.equal(b, fresh(X))
    assert not torch.equal(b[3], a[3]) and torch.equal(b[:3], a[:3])


def test_frozen_projection_cache_follows_parameters_and_anchors():
    ibr, cams = _ibr("pyramid")
    X = _anchors(cams)
    for p in ibr.projection_parameters():
        p.requires_grad_(False)
    a = ibr(X)
    assert not a.requires_grad and torch.equal(ibr(X), a)
    with torch.no_grad():
        ibr.proj["level1"].weight.mul_(2.0)
    b = ibr(X)
    assert not torch.equal(b, a) and torch.allclose(b, _old_forward(ibr, cams, X), atol=2e-5)
    c = ibr(X[:50])
    assert torch.equal(c, b[:50])


def test_neural_gaussians_use_the_features_of_their_visible_anchors():
    """The model passes every anchor and its frustum mask; the decoded features are those of
    the visible anchors, through both the fast path and the definition."""
    cam = small_camera(size=48)
    images = torch.rand(1, 3, 48, 48)
    ibr = IBRFeatures("pyramid", images, [cam], c_r=32)
    model = small_model(300, use_ibr=True)
    model.set_ibr(ibr)
    ct = CameraTensors.of(cam)
    vis = model.visible_anchors(ct.K, ct.w2c, 48, 48)
    assert 0 < vis.sum() < model.num_anchors or vis.all()
    feats = model._ibr(vis)
    want = _old_forward(ibr, [cam], model.anchor.detach()[vis])
    assert torch.allclose(feats, want, atol=2e-5)
    g = model.gaussians(ct)
    g.colors.sum().backward()
    assert all(p.grad is not None for p in ibr.projection_parameters())


@pytest.mark.parametrize("backend", ["fast", "reference"])
def test_projection_node_gradcheck_and_no_grad_values(backend):
    """``project_rows`` on either backend: one node (float64 gradcheck over every level's weight
    and bias, a seen column with zeros), the same values without recording, and a mask's rows
    bit for bit those of all rows (a row's value does not depend on the rows beside it)."""
    g = torch.Generator().manual_seed(3)
    rows = torch.rand(600, 3 + 6 + 12 + 1, generator=g, dtype=torch.float64)
    rows[:, -1] = (torch.rand(600, generator=g) > 0.25).double()
    mask = torch.rand(600, generator=g) > 0.3
    ws = [torch.randn(shape, generator=g, dtype=torch.float64) for shape in ((4, 3, 1, 1), (4, 6, 1, 1), (4, 12))]
    bs = [torch.randn(4, generator=g, dtype=torch.float64) for _ in ws]
    params = [p.requires_grad_() for p in ws + bs]
    set_backend(backend)
    try:
        out = project_rows(rows, ws, bs, mask)
        assert out.grad_fn.name() == {"fast": "_ProjectRowsFastBackward", "reference": "_ProjectRowsBackward"}[backend]
        assert torch.autograd.gradcheck(lambda *p: project_rows(rows[:40], list(p[:3]), list(p[3:])), tuple(params))
        assert torch.autograd.gradcheck(lambda *p: project_rows(rows[:60], list(p[:3]), list(p[3:]), mask[:60]),
                                        tuple(params))
        with torch.no_grad():
            assert torch.equal(project_rows(rows, ws, bs, mask), out.detach())
            every = project_rows(rows, ws, bs)
        if backend == "fast":
            assert torch.equal(every[mask], out.detach())
        want = rows[mask, :-1] @ torch.cat([w.reshape(4, -1) for w in ws], 1).T + rows[mask, -1:] * sum(bs)
        torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
    finally:
        set_backend(None)


def test_fast_projection_gradient_is_the_same_on_any_thread_count():
    """The C++ weight gradient sums fixed blocks of rows in order: 1 and 2 threads agree bit for bit."""
    if not available():
        pytest.skip("the C++ path does not build here")
    g = torch.Generator().manual_seed(4)
    rows = torch.rand(2_000, 26, generator=g)
    mask = torch.rand(2_000, generator=g) > 0.1
    ws = [torch.randn(32, 10, 1, 1, generator=g).requires_grad_(), torch.randn(32, 15, generator=g).requires_grad_()]
    bs = [torch.randn(32, generator=g).requires_grad_() for _ in ws]
    up = torch.randn(int(mask.sum()), 32, generator=g)
    got = []
    for n in (1, 2):
        torch.set_num_threads(n)
        for p in ws + bs:
            p.grad = None
        (project_rows(rows, ws, bs, mask) * up).sum().backward()
        got.append([p.grad.clone() for p in ws + bs])
    torch.set_num_threads(2)
    assert all(torch.equal(a, b) for a, b in zip(*got))
    assert torch.equal(got[0][2], got[0][3])  # the levels' biases are summed: equal gradients