"""Scaffold anchor growth and pruning with the height veto (strategy.anchor)."""
from __future__ import annotations


import numpy as np
import pytest
import torch

from dibrgs_core.strategy.anchor import AnchorStrategy
from dibrgs_core.training.config import preset
from model_synth import camera_tensors, check_optimizer_state, small_camera, small_model, stepped_optimizer


def test_growth_adds_anchors_in_empty_cells_with_zero_moments():
    """Large averaged gradients on Gaussians that moved away from their anchor give new anchors,
    at most one per cell and never in a cell already holding one; moments stay aligned."""
    m = small_model(50)
    cfg = preset("test")
    s = AnchorStrategy(m, cfg.growth, 30000)
    opt = stepped_optimizer(m)
    n0 = m.num_anchors
    with torch.no_grad():
        m.offset[:10] = 40.0  # Gaussians of the first 10 anchors far out
    s.offset_grad[: 10 * m.n_offsets] = 1.0
    s.offset_denom[:] = 1000
    torch.manual_seed(0)
    r = s.adjust(m, opt)
    assert r.added > 0 and m.num_anchors == n0 + r.added
    check_optimizer_state(m, opt)
    new = slice(n0, m.num_anchors)
    assert (opt.state[m.offset]["exp_avg"][new] == 0).all()
    assert (m.offset[new] == 0).all()
    # New anchors do not share a finest-level cell with an old one.
    o = torch.tensor(m.grid_origin)
    cells_old = {tuple(c) for c in torch.round((m.anchor[:n0] - o) / m.voxel_size).long().tolist()}
    cells_new = [tuple(c) for c in torch.round((m.anchor[new] - o) / m.voxel_size).long().tolist()]
    assert not any(c in cells_old for c in cells_new)
    assert len(s.offset_grad) == m.num_anchors * m.n_offsets and len(s.anchor_denom) == m.num_anchors


def test_a_moved_cloud_gets_the_moved_anchors_and_grows_them_alike():
    """The anchor grid goes through a point of the cloud, not the coordinate origin: the same cloud
    moved by a shift that is no multiple of the voxel starts from the same anchors, moved, and
    growth adds the same ones (measured before: another grid, other anchors, 0.1-0.35 dB apart)."""
    from dibrgs_core.models.scaffold import NeuralGaussians, build_model

    rng = np.random.default_rng(3)
    pts = rng.uniform(-10, 10, (400, 3)) * np.array([1, 1, 0.1])
    shift = np.array([3.3337, -1.2101, 0.5173])
    cfg = preset("test")
    runs = []
    for p in (pts, pts + shift):
        m, _ = build_model(p, np.array([[0, -30, 40.0]]) + (p[0] - pts[0]), cfg.model, use_ibr=False, scale=1.0)
        assert np.allclose(m.grid_origin, p.min(axis=0))
        s = AnchorStrategy(m, cfg.growth, 30000)
        opt = stepped_optimizer(m)
        with torch.no_grad():
            m.offset[:40] = 5.0
        s.offset_grad[: 40 * m.n_offsets] = 1.0
        s.offset_denom[:] = 1000
        torch.manual_seed(0)
        runs.append((m, s.adjust(m, opt).added))
    (a, added_a), (b, added_b) = runs
    assert added_a > 0 and added_a == added_b and a.num_anchors == b.num_anchors
    assert torch.allclose(b.anchor, a.anchor + torch.tensor(shift, dtype=torch.float32), atol=1e-4)
    # The grid is the model's: saved and loaded with it; model files without one keep (0, 0, 0).
    st = b.state()
    assert NeuralGaussians.from_state(st, cfg.model).grid_origin == b.grid_origin
    del st["model_meta"]["grid_origin"]
    assert NeuralGaussians.from_state(st, cfg.model).grid_origin == (0.0, 0.0, 0.0)


@pytest.mark.stability
def test_growth_stays_on_the_grid_when_a_stray_point_sets_its_corner_far_out():
    """One point 1e7 voxels below the cloud puts the grid's corner there: growth, measuring from it
    in float64, still adds anchors at the centres of empty cells of that grid next to the cloud."""
    from dibrgs_core.models.scaffold import build_model

    rng = np.random.default_rng(4)
    pts = rng.uniform(-10, 10, (400, 3)) * np.array([1, 1, 0.1])
    cfg = preset("test")
    voxel = cfg.model.anchor_voxel
    stray = np.concatenate([pts, [[0.0, 0.0, -1e7 * voxel]]])
    m, _ = build_model(stray, np.array([[0, -30, 40.0]]), cfg.model, use_ibr=False, scale=1.0)
    assert m.grid_origin[2] == -1e7 * voxel
    s = AnchorStrategy(m, cfg.growth, 30000)
    opt = stepped_optimizer(m)
    n0 = m.num_anchors
    with torch.no_grad():
        m.offset[:40] = 5.0
    s.offset_grad[: 40 * m.n_offsets] = 1.0
    s.offset_denom[:] = 1000
    torch.manual_seed(0)
    assert s.adjust(m, opt).added > 0
    new = m.anchor[n0:].double()
    assert torch.isfinite(new).all() and (new[:, 2].abs() < 100).all()
    # Every level's cell centres are whole voxels from the corner. Float32 anchors near the cloud:
    # on the grid to their own rounding (float32 arithmetic from a corner this far out misses).
    k = (new - torch.tensor(m.grid_origin, dtype=torch.float64)) / m.voxel_size
    assert (k - k.round()).abs().max() < 1e-3


def test_height_map_vetoes_growth_at_the_coarsest_level_only():
    from dibrgs_core.geometry.height_map import HeightMap

    m = small_model(60)
    cfg = preset("test").growth
    pts = m.anchor.detach().numpy()
    hm = HeightMap.build(pts, np.eye(3), np.zeros(3), cell=5.0, relax=1.0, margin=0.0)
    with torch.no_grad():
        m.offset[:10, :, 2] = 40.0  # straight up, far above every bound
    opt = stepped_optimizer(m)
    cfg.update_depth = 1  # coarsest level only
    s = AnchorStrategy(m, cfg, 30000, height_map=hm)
    s.offset_grad[: 10 * m.n_offsets] = 1.0
    s.offset_denom[:] = 1000
    r = s.adjust(m, opt)
    assert r.added == 0 and r.vetoed > 0
    # Without the height map the same Gaussians grow anchors.
    m2 = small_model(60)
    with torch.no_grad():
        m2.offset[:10, :, 2] = 40.0
    opt2 = stepped_optimizer(m2)
    s2 = AnchorStrategy(m2, cfg, 30000)
    s2.offset_grad[: 10 * m2.n_offsets] = 1.0
    s2.offset_denom[:] = 1000
    assert s2.adjust(m2, opt2).added > 0
    # At finer levels the veto does not apply.
    cfg3 = preset("test").growth
    m3 = small_model(60)
    with torch.no_grad():
        m3.offset[:10, :, 2] = 40.0
    opt3 = stepped_optimizer(m3)
    s3 = AnchorStrategy(m3, cfg3, 30000, height_map=hm)
    s3.offset_grad[: 10 * m3.n_offsets] = 1.0
    s3.offset_denom[:] = 1000
    torch.manual_seed(1)
    r3 = s3.adjust(m3, opt3)
    assert r3.added > 0 and r3.vetoed > 0
    check_optimizer_state(m3, opt3)


def test_pruning_removes_transparent_anchors_after_enough_visits():
    m = small_model(40)
    opt = stepped_optimizer(m)
    cfg = preset("test").growth
    s = AnchorStrategy(m, cfg, 30000)  # every = 100 its -> judged after > 80 visits
    s.anchor_denom[:] = 90
    s.opacity_accum[:] = 1.0
    s.opacity_accum[:7] = 0.0  # transparent
    s.anchor_denom[5:7] = 10   # ... but not yet visited often enough
    keep_feat = m.anchor_feat.detach()[7:].clone()
    r = s.adjust(m, opt)
    assert r.pruned == 5 and m.num_anchors == 35
    assert torch.equal(m.anchor_feat.detach()[2:], keep_feat)
    check_optimizer_state(m, opt)
    assert len(s.opacity_accum) == 35 and s.anchor_denom[:2].tolist() == [10, 10]


def test_update_accumulates_ndc_gradients_of_rasterized_gaussians():
    from dibrgs_core.render import rasterize

    m = small_model(80)
    with torch.no_grad():
        m.mlp_opacity[2].bias.fill_(0.3)
    s = AnchorStrategy(m, preset("test").growth, 30000)
    c = camera_tensors(small_camera())
    d = m.decode(c.K, c.w2c, c.center, 32, 32)
    img, _, _, meta = rasterize(d.means, d.quats, d.scales, d.opacities, d.colors, c.w2c, c.K, 32, 32)
    inside, after = s.stat_start + 1, s.until
    assert s.collects(inside) and not s.collects(after)
    s.step_pre_backward(m, None, after, meta)
    assert not meta["means2d"].retains_grad  # no statistics after growth: no copy of the gradient
    s.step_pre_backward(m, None, inside, meta)
    assert meta["means2d"].retains_grad
    img.mean().backward()
    s.update(d, meta["means2d"].grad, meta["visible"], 32, 32)
    seen = int((meta["radii"] > 0).sum())
    assert int(s.offset_denom.sum()) == seen > 0
    g = meta["means2d"].grad[meta["radii"] > 0] * torch.tensor([16.0, 16.0])
    assert float(s.offset_grad.sum()) == pytest.approx(float(g.norm(dim=1).sum()), rel=1e-5)
    assert int(s.anchor_denom.sum()) == int(d.anchor_visible.sum())


def test_growth_respects_the_anchor_ceiling():
    m = small_model(50)
    cfg = preset("test").growth
    cfg.max_anchors = 55
    s = AnchorStrategy(m, cfg, 30000)
    opt = stepped_optimizer(m)
    with torch.no_grad():
        m.offset[:, :, :2] = torch.randn(50, 10, 2) * 30.0
    s.offset_grad[:] = 1.0
    s.offset_denom[:] = 1000
    r = s.adjust(m, opt)
    assert r.added == 5 and m.num_anchors == 55 and s.capped > 0
    check_optimizer_state(m, opt)


def test_new_cells_match_row_wise_unique():
    """Growth's cell bookkeeping (packed one-dimensional keys, or rows when the cells span more
    than 62 bits) gives torch's row-wise unique: the same cells in the same order, the same inverse
    and the same new cells, so growth adds the same anchors in the same order."""
    from dibrgs_core.strategy.anchor import _new_cells

    g = torch.Generator().manual_seed(0)
    seen = set()
    for trial in range(60):
        n, m = int(torch.randint(1, 300, (1,), generator=g)), int(torch.randint(1, 200, (1,), generator=g))
        scale = [3, 50, 10**6, 10**15, 2**62][trial % 5]  # the last two overflow the packed keys
        cand = torch.randint(-scale, scale, (n, 3), generator=g)
        cand = torch.cat([cand, cand[: n // 2]])  # repeated cells
        existing = torch.cat([torch.randint(-scale, scale, (m, 3), generator=g), cand[: n // 3]])
        cells, inv, new = _new_cells(cand, existing)
        want, want_inv = torch.unique(cand, dim=0, return_inverse=True)
        assert torch.equal(cells, want) and torch.equal(inv, want_inv)
        taken = {tuple(r) for r in existing.tolist()}
        assert new.tolist() == [tuple(r) not in taken for r in want.tolist()]
        seen.update(new.tolist())
    assert seen == {True, False}  # both new and occupied cells were met
