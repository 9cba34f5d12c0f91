"""Unit tests of the training components: config schedules, neural Gaussians, anchor growth, 3DGS densification,
PLY export and LPIPS loading. No training runs here (see test_train_run.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.training.config import TrainConfig, expon_lr, preset
from dibrgs_core.models.scaffold import NeuralGaussians, build_model
from dibrgs_core.geometry.pointcloud import voxelize
from dibrgs_core.strategy.anchor import AnchorStrategy

torch.set_num_threads(1)


def _cam(eye=(0.0, -30.0, 40.0), size=32) -> Camera:
    f = size * 1.2
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return Camera(K=K, w2c=look_at(np.array(eye), np.zeros(3), np.array([0, 0, 1.0])), width=size, height=size)


def _camt(cam: Camera):
    from dibrgs_core.models.base import CameraTensors

    return CameraTensors.of(cam)


def _model(n=200, seed=0, use_ibr=False) -> NeuralGaussians:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-10, 10, (n, 3)) * np.array([1, 1, 0.1])
    cfg = TrainConfig().model
    model, _ = build_model(pts, np.array([[0, -30, 40.0]]), cfg, use_ibr=use_ibr, scale=1.0)
    return model


# -- config ------------------------------------------------------------------------
def test_paper_schedule_matches_the_paper_and_scales_with_length():
    """The paper preset gives the paper's iteration numbers; shorter runs keep the fractions."""
    from dibrgs_core.strategy.anchor import AnchorStrategy

    cfg = preset("paper")
    assert cfg.iterations == 30000
    assert (cfg.it(cfg.pseudo.start), cfg.it(cfg.pseudo.until), cfg.it(cfg.pseudo.every)) == (3000, 20000, 50)
    assert cfg.it(cfg.lr.projection_freeze) == 20000
    m = _model(20)
    s = AnchorStrategy(m, cfg.growth, cfg.iterations)
    assert (s.start, s.until, s.every, s.stat_start) == (1500, 15000, 100, 500)
    s2 = AnchorStrategy(m, cfg.growth, 3000)
    assert (s2.start, s2.until, s2.every) == (150, 1500, 10)
    # Round trip through JSON-like dicts (checkpoints, config.json).
    c2 = TrainConfig.from_dict(preset("cpu").to_dict())
    assert c2 == preset("cpu")
    with pytest.raises(ValueError):
        TrainConfig.from_dict({"nope": 1})
    with pytest.raises(ValueError):
        preset("gpu")


def test_expon_lr_endpoints_and_monotone():
    assert expon_lr(0, 100, 0.01, 0.0001) == pytest.approx(0.01)
    assert expon_lr(100, 100, 0.01, 0.0001) == pytest.approx(0.0001)
    assert expon_lr(50, 100, 0.01, 0.0001) == pytest.approx(0.001)
    assert expon_lr(10, 100, 0.0, 0.0) == 0.0


# -- neural Gaussians -------------------------------------------------------------
def test_voxelize_merges_points_in_a_cell():
    pts = np.array([[0.01, 0.0, 0.0], [0.02, 0.01, 0.0], [1.0, 1.0, 1.0]])
    v = voxelize(pts, 0.1)
    assert len(v) == 2


def test_anchor_budget_doubles_voxel_and_reports_it():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-10, 10, (5000, 3))
    cfg = TrainConfig().model
    cfg.max_init_anchors = 300
    model, why = build_model(pts, np.array([[0, 0, 50.0]]), cfg, use_ibr=False, scale=1.0)
    assert model.num_anchors <= 300
    assert "doubled" in why and model.voxel_size > 0.03


def test_decode_shapes_activations_and_frustum_culling():
    """Decoded Gaussians: positive opacity only, unit quaternions, scales bounded by the anchor scale,
    colours in [0,1]; anchors behind the camera are culled."""
    m = _model(300)
    with torch.no_grad():
        m.anchor[:5] = torch.tensor([0.0, -60.0, 80.0])  # behind a camera at (0,-30,40) looking at 0
        # Make opacity positive for some Gaussians whatever the random init gives.
        m.mlp_opacity[2].bias.fill_(0.2)
    c = _camt(_cam())
    vis = m.visible_anchors(c.K, c.w2c, 32, 32)
    assert not vis[:5].any() and vis[5:].sum() > 100
    d = m.decode(c.K, c.w2c, c.center, 32, 32)
    n = int(vis.sum()) * m.n_offsets
    assert d.neural_opacity.shape == (n,)
    assert d.means.shape[0] == int(d.selected.sum()) > 0
    assert (d.opacities > 0).all() and (d.opacities <= 1).all()
    assert torch.allclose(d.quats.norm(dim=1), torch.ones(len(d.quats)), atol=1e-5)
    assert ((d.colors >= 0) & (d.colors <= 1)).all()
    s_anchor = m.anchor_scaling()[vis].repeat_interleave(m.n_offsets, 0)[d.selected][:, 3:]
    assert (d.scales <= s_anchor + 1e-6).all()
    # Zero offsets at initialisation: Gaussians sit on their anchors.
    assert torch.allclose(d.means, m.anchor[vis].repeat_interleave(m.n_offsets, 0)[d.selected])


def test_ibr_gate_starts_small_and_features_change_the_decoding():
    m = _model(100, use_ibr=True)
    f_v = torch.randn(100, 32)
    g = torch.sigmoid(m.e_mod(f_v))
    assert g.max() < 0.02  # sigmoid(-5 + small) ~ 0.007
    idx = torch.arange(100)
    fused = m.fused_features(idx, f_v)
    assert not torch.allclose(fused, m.anchor_feat)
    assert (fused - m.anchor_feat).abs().max() < 0.1
    # Gradient reaches the gate and the reference projection.
    fused.sum().backward()
    assert m.e_mod.weight.grad.abs().sum() > 0 and m.e_ref.weight.grad.abs().sum() > 0


def test_decode_backprop_through_rasterizer_reaches_all_parameters():
    from dibrgs_core.render import rasterize

    m = _model(150)
    with torch.no_grad():
        m.mlp_opacity[2].bias.fill_(0.3)
    c = _camt(_cam())
    d = m.decode(c.K, c.w2c, c.center, 32, 32)
    img, _, _, meta = rasterize(d.means, d.quats, d.scales, d.opacities, d.colors, c.w2c, c.K, 32, 32)
    (img.mean() + d.scales.prod(1).mean()).backward()
    for name in ("offset", "anchor_feat", "scaling"):
        g = getattr(m, name).grad
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0, name
    assert meta["means2d"].grad is not None


# -- anchor growth ----------------------------------------------------------------
def _optimizer(m: NeuralGaussians) -> torch.optim.Adam:
    groups = [{"params": [m.offset], "lr": 0.01, "name": "offset"},
              {"params": [m.anchor_feat], "lr": 0.01, "name": "anchor_feat"},
              {"params": [m.scaling], "lr": 0.01, "name": "scaling"}]
    m.anchor.requires_grad_(False)
    opt = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    for p in (m.offset, m.anchor_feat, m.scaling):
        p.grad = torch.ones_like(p)
    opt.step()
    return opt


def _check_state(m: NeuralGaussians, opt: torch.optim.Adam):
    for g in opt.param_groups:
        p = g["params"][0]
        assert p is getattr(m, g["name"])
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape


def test_growth_adds_anchors_in_empty_cells_with_zero_moments():
    """Large averaged gradients on Gaussians that moved away from their anchor give new anchors,
    at most one per cell and never in a cell already holding one; moments stay aligned."""
    m = _model(50)
    cfg = preset("test")
    s = AnchorStrategy(m, cfg.growth, 30000)
    opt = _optimizer(m)
    n0 = m.num_anchors
    with torch.no_grad():
        m.offset[:10] = 40.0  # Gaussians of the first 10 anchors far out
    s.offset_grad[: 10 * m.n_offsets] = 1.0
    s.offset_denom[:] = 1000
    torch.manual_seed(0)
    r = s.adjust(m, opt)
    assert r.added > 0 and m.num_anchors == n0 + r.added
    _check_state(m, opt)
    new = slice(n0, m.num_anchors)
    assert (opt.state[m.offset]["exp_avg"][new] == 0).all()
    assert (m.offset[new] == 0).all()
    # New anchors do not share a finest-level cell with an old one.
    cells_old = {tuple(c) for c in torch.round(m.anchor[:n0] / m.voxel_size).long().tolist()}
    cells_new = [tuple(c) for c in torch.round(m.anchor[new] / m.voxel_size).long().tolist()]
    assert not any(c in cells_old for c in cells_new)
    assert len(s.offset_grad) == m.num_anchors * m.n_offsets and len(s.anchor_denom) == m.num_anchors


def test_height_map_vetoes_growth_at_the_coarsest_level_only():
    from dibrgs_core.geometry.height_map import HeightMap

    m = _model(60)
    cfg = preset("test").growth
    pts = m.anchor.detach().numpy()
    hm = HeightMap.build(pts, np.eye(3), np.zeros(3), cell=5.0, relax=1.0, margin=0.0)
    with torch.no_grad():
        m.offset[:10, :, 2] = 40.0  # straight up, far above every bound
    opt = _optimizer(m)
    cfg.update_depth = 1  # coarsest level only
    s = AnchorStrategy(m, cfg, 30000, height_map=hm)
    s.offset_grad[: 10 * m.n_offsets] = 1.0
    s.offset_denom[:] = 1000
    r = s.adjust(m, opt)
    assert r.added == 0 and r.vetoed > 0
    # Without the height map the same Gaussians grow anchors.
    m2 = _model(60)
    with torch.no_grad():
        m2.offset[:10, :, 2] = 40.0
    opt2 = _optimizer(m2)
    s2 = AnchorStrategy(m2, cfg, 30000)
    s2.offset_grad[: 10 * m2.n_offsets] = 1.0
    s2.offset_denom[:] = 1000
    assert s2.adjust(m2, opt2).added > 0
    # At finer levels the veto does not apply.
    cfg3 = preset("test").growth
    m3 = _model(60)
    with torch.no_grad():
        m3.offset[:10, :, 2] = 40.0
    opt3 = _optimizer(m3)
    s3 = AnchorStrategy(m3, cfg3, 30000, height_map=hm)
    s3.offset_grad[: 10 * m3.n_offsets] = 1.0
    s3.offset_denom[:] = 1000
    torch.manual_seed(1)
    r3 = s3.adjust(m3, opt3)
    assert r3.added > 0 and r3.vetoed > 0
    _check_state(m3, opt3)


def test_pruning_removes_transparent_anchors_after_enough_visits():
    m = _model(40)
    opt = _optimizer(m)
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
    _check_state(m, opt)
    assert len(s.opacity_accum) == 35 and s.anchor_denom[:2].tolist() == [10, 10]


def test_update_accumulates_ndc_gradients_of_rasterized_gaussians():
    from dibrgs_core.render import rasterize

    m = _model(80)
    with torch.no_grad():
        m.mlp_opacity[2].bias.fill_(0.3)
    s = AnchorStrategy(m, preset("test").growth, 30000)
    c = _camt(_cam())
    d = m.decode(c.K, c.w2c, c.center, 32, 32)
    img, _, _, meta = rasterize(d.means, d.quats, d.scales, d.opacities, d.colors, c.w2c, c.K, 32, 32)
    img.mean().backward()
    s.update(d, meta["means2d"].grad, meta["radii"], 32, 32)
    seen = int((meta["radii"] > 0).sum())
    assert int(s.offset_denom.sum()) == seen > 0
    g = meta["means2d"].grad[meta["radii"] > 0] * torch.tensor([16.0, 16.0])
    assert float(s.offset_grad.sum()) == pytest.approx(float(g.norm(dim=1).sum()), rel=1e-5)
    assert int(s.anchor_denom.sum()) == int(d.anchor_visible.sum())


# -- 3DGS -------------------------------------------------------------------------
def test_gs3d_clone_split_prune_keep_optimizer_consistent():
    from dibrgs_core.training.config import GS3DConfig
    from dibrgs_core.models.gs3d import GAUSS_PARAMS, Gaussians3D, eval_sh
    from dibrgs_core.strategy.densify import DensifyStrategy
    from dibrgs_core.training.methods import gs3d_optimizer

    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (100, 3))
    cols = rng.uniform(0, 1, (100, 3))
    g = Gaussians3D(pts, cols, 3)
    # SH with zero higher bands reproduces the initial colours from any direction.
    sh = torch.cat([g.sh_dc, g.sh_rest], 1)
    rgb = eval_sh(3, sh, torch.nn.functional.normalize(torch.randn(100, 3), dim=1)) + 0.5
    assert torch.allclose(rgb, torch.tensor(cols, dtype=torch.float32), atol=1e-5)
    cfg = GS3DConfig()
    opt = gs3d_optimizer(g, cfg, extent=10.0)
    for p in g.parameters():
        p.grad = torch.ones_like(p)
    opt.step()
    st = DensifyStrategy(g, cfg, 30000, extent=10.0)
    with torch.no_grad():
        g.log_scales[:10] = math.log(2.0)   # large -> split
        g.log_scales[10:20] = math.log(0.01)  # small -> clone
        g.opacity[90:] = -10.0  # transparent -> pruned
    st.grad_accum[:20] = 1.0
    st.denom[:] = 1.0
    st._densify_and_prune(1000, g, opt)
    assert g.num_gaussians == 100 + 10 + 2 * 10 - 10 - 10  # +clones, +2 per split, -split originals, -pruned
    for grp in opt.param_groups:
        p = grp["params"][0]
        assert p is getattr(g, grp["name"]) and opt.state[p]["exp_avg"].shape == p.shape
    assert set(GAUSS_PARAMS) == {grp["name"] for grp in opt.param_groups}


# -- export -----------------------------------------------------------------------
def test_ply_writer_reads_back_with_trimesh(tmp_path):
    import trimesh

    from dibrgs_core.evaluation.export import SH_C0, write_gaussian_ply

    rng = np.random.default_rng(0)
    n = 50
    means = rng.normal(size=(n, 3))
    q = rng.normal(size=(n, 4))
    scales = rng.uniform(0.01, 1, (n, 3))
    op = rng.uniform(0.01, 0.99, n)
    rgb = rng.uniform(0, 1, (n, 3))
    rest = rng.normal(size=(n, 15, 3))
    p = tmp_path / "g.ply"
    assert write_gaussian_ply(p, means, q, scales, op, (rgb - 0.5) / SH_C0, rest) == n
    m = trimesh.load(p)
    v = m.metadata["_ply_raw"]["vertex"]["data"]
    assert np.allclose(np.stack([v["x"], v["y"], v["z"]], 1), means, atol=1e-6)
    assert np.allclose(1 / (1 + np.exp(-v["opacity"])), op, atol=1e-5)
    assert np.allclose(np.exp(np.stack([v[f"scale_{i}"] for i in range(3)], 1)), scales, rtol=1e-5)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    assert np.allclose(np.stack([v[f"rot_{i}"] for i in range(4)], 1), qn, atol=1e-6)
    assert np.allclose(v["f_rest_0"], rest[:, 0, 0], atol=1e-6)  # channel-major: R of band 1 first
    assert np.allclose(v["f_rest_15"], rest[:, 0, 1], atol=1e-6)
    assert np.allclose(v["f_dc_1"] * SH_C0 + 0.5, rgb[:, 1], atol=1e-5)


# -- LPIPS --------------------------------------------------------------------------
def test_lpips_loads_official_layout_and_is_a_distance(tmp_path):
    from dibrgs_core.common.errors import InputError
    from dibrgs_core.evaluation.lpips import LPIPS, load_lpips
    from dibrgs_core.evaluation.evaluate import avge

    torch.manual_seed(0)
    net = LPIPS("alex")
    with torch.no_grad():
        for k in range(5):
            getattr(net, f"lin{k}").model[1].weight.abs_()
    full = tmp_path / "lpips_alex_full.pth"
    torch.save(net.state_dict(), full)
    assert "net.slice1.0.weight" in net.state_dict() and "lin4.model.1.weight" in net.state_dict()
    lp = load_lpips(full)
    a = torch.rand(40, 40, 3)
    b = (a + 0.2 * torch.randn_like(a)).clamp(0, 1)
    assert float(lp(a, a)) == pytest.approx(0.0, abs=1e-7)
    assert float(lp(a, b)) > 0
    heads = tmp_path / "alex.pth"
    torch.save({k: v for k, v in net.state_dict().items() if k.startswith("lin")}, heads)
    with pytest.raises(InputError, match="backbone"):
        load_lpips(heads)
    bb = tmp_path / "alexnet_tv.pth"
    torch.save({f"features.{k.split('.')[2]}.{k.split('.')[3]}": v for k, v in net.state_dict().items()
                if k.startswith("net.")}, bb)
    lp2 = load_lpips(heads, bb)
    assert float(lp2(a, b)) == pytest.approx(float(lp(a, b)), rel=1e-6)
    with pytest.raises(InputError):
        load_lpips(tmp_path / "missing.pth")
    # AVGE is the geometric mean of MSE, sqrt(1-SSIM) and LPIPS.
    assert avge(20.0, 0.75, 0.1) == pytest.approx((0.01 * 0.5 * 0.1) ** (1 / 3))


def test_growth_respects_the_anchor_ceiling():
    m = _model(50)
    cfg = preset("test").growth
    cfg.max_anchors = 55
    s = AnchorStrategy(m, cfg, 30000)
    opt = _optimizer(m)
    with torch.no_grad():
        m.offset[:, :, :2] = torch.randn(50, 10, 2) * 30.0
    s.offset_grad[:] = 1.0
    s.offset_denom[:] = 1000
    r = s.adjust(m, opt)
    assert r.added == 5 and m.num_anchors == 55 and s.capped > 0
    _check_state(m, opt)
