"""Tests for dibrgs_core.models.ibr.features: DINO key names, weight loading, projection/sampling."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.common.errors import InputError
from dibrgs_core.models.ibr.features import IBRFeatures, build_ibr, resolve_encoder
from dibrgs_core.models.ibr.resnet import ResNetFeatures, dino_resnet50
from dibrgs_core.models.ibr.vit import ViTFeatures, dino_vitb8
from dibrgs_core.models.ibr.weights import load_backbone_weights
from model_synth import ring_views

torch.set_num_threads(2)


# Official names, verified against facebookresearch/dino (hubconf.py builds torchvision's resnet50 with
# fc = Identity; vision_transformer.py: cls_token, pos_embed, patch_embed.proj, blocks.N.{norm1, attn.qkv,
# attn.proj, norm2, mlp.fc1, mlp.fc2}, norm; ViT-B/8 has 12 blocks of width 768 and a 224/8 = 28x28 grid).
def official_resnet50_keys() -> dict[str, tuple]:
    bn = lambda p, c: {f"{p}.weight": (c,), f"{p}.bias": (c,), f"{p}.running_mean": (c,),  # noqa: E731
                       f"{p}.running_var": (c,), f"{p}.num_batches_tracked": ()}
    keys = {"conv1.weight": (64, 3, 7, 7), **bn("bn1", 64)}
    inpl = 64
    for li, (n, planes) in enumerate(zip((3, 4, 6, 3), (64, 128, 256, 512)), start=1):
        for b in range(n):
            p = f"layer{li}.{b}"
            keys[f"{p}.conv1.weight"] = (planes, inpl, 1, 1)
            keys[f"{p}.conv2.weight"] = (planes, planes, 3, 3)
            keys[f"{p}.conv3.weight"] = (planes * 4, planes, 1, 1)
            for j, c in ((1, planes), (2, planes), (3, planes * 4)):
                keys.update(bn(f"{p}.bn{j}", c))
            if b == 0:
                keys[f"{p}.downsample.0.weight"] = (planes * 4, inpl, 1, 1)
                keys.update(bn(f"{p}.downsample.1", planes * 4))
            inpl = planes * 4
    return keys


def official_vitb8_keys() -> dict[str, tuple]:
    d = 768
    keys = {"cls_token": (1, 1, d), "pos_embed": (1, 28 * 28 + 1, d), "patch_embed.proj.weight": (d, 3, 8, 8),
            "patch_embed.proj.bias": (d,), "norm.weight": (d,), "norm.bias": (d,)}
    for i in range(12):
        p = f"blocks.{i}"
        keys.update({f"{p}.norm1.weight": (d,), f"{p}.norm1.bias": (d,), f"{p}.attn.qkv.weight": (3 * d, d),
                     f"{p}.attn.qkv.bias": (3 * d,), f"{p}.attn.proj.weight": (d, d), f"{p}.attn.proj.bias": (d,),
                     f"{p}.norm2.weight": (d,), f"{p}.norm2.bias": (d,), f"{p}.mlp.fc1.weight": (4 * d, d),
                     f"{p}.mlp.fc1.bias": (4 * d,), f"{p}.mlp.fc2.weight": (d, 4 * d), f"{p}.mlp.fc2.bias": (d,)})
    return keys


def test_full_size_keys_match_official_checkpoints():
    want_r = official_resnet50_keys()
    got_r = {k: tuple(v.shape) for k, v in dino_resnet50().state_dict().items()}
    assert len(want_r) == 318  # torchvision resnet50's 320 minus fc.weight/fc.bias
    assert got_r == want_r
    want_v = official_vitb8_keys()
    got_v = {k: tuple(v.shape) for k, v in dino_vitb8().state_dict().items()}
    assert len(want_v) == 150
    assert got_v == want_v


def _tiny_backbones(seed: int = 0) -> tuple[ResNetFeatures, ViTFeatures]:
    torch.manual_seed(seed)
    return ResNetFeatures((1, 1, 1, 1), width=4), ViTFeatures(patch=8, dim=64, depth=2, heads=4, img_size=32)


def test_weights_round_trip_and_dino_checkpoint_layouts(tmp_path):
    r, v = _tiny_backbones(0)
    # torchvision-style file with an fc head and a DINO-style {'teacher': {'backbone.*', 'head.*'}} file
    sd_r = dict(r.state_dict(), **{"fc.weight": torch.zeros(3, 128), "fc.bias": torch.zeros(3)})
    torch.save(sd_r, tmp_path / "r.pth")
    teacher = {f"backbone.{k}": t for k, t in v.state_dict().items()}
    teacher["head.last_layer.weight"] = torch.zeros(2, 2)
    torch.save({"teacher": teacher, "epoch": 3}, tmp_path / "v.pth")
    r2, v2 = _tiny_backbones(1)
    assert not torch.equal(r2.conv1.weight, r.conv1.weight)
    load_backbone_weights(r2, tmp_path / "r.pth", "resnet")
    load_backbone_weights(v2, tmp_path / "v.pth", "vit")
    for a, b in ((r, r2), (v, v2)):
        for k, t in a.state_dict().items():
            assert torch.equal(t, b.state_dict()[k]), k
    x = torch.rand(1, 3, 32, 32)
    r.eval(), r2.eval()
    assert torch.allclose(v(x)[1], v2(x)[1]) and torch.allclose(r(x)[3], r2(x)[3])


def test_bad_checkpoints_raise_input_error_naming_file(tmp_path):
    r, v = _tiny_backbones(0)
    torch.save(v.state_dict(), tmp_path / "vit.pth")
    with pytest.raises(InputError) as e:
        load_backbone_weights(r, tmp_path / "vit.pth", "DINO ResNet-50")
    assert "vit.pth" in str(e.value) and "missing keys" in str(e.value)
    sd = v.state_dict()
    sd["pos_embed"] = torch.zeros(1, 5, 64)
    torch.save(sd, tmp_path / "shape.pth")
    with pytest.raises(InputError, match="shape mismatches.*pos_embed"):
        load_backbone_weights(v, tmp_path / "shape.pth", "vit")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="junk.pth"):
        load_backbone_weights(v, tmp_path / "junk.pth", "vit")
    with pytest.raises(InputError, match="not found"):
        load_backbone_weights(v, tmp_path / "absent.pth", "vit")


def test_vit_interpolates_position_embeddings():
    _, v = _tiny_backbones(0)
    cls, tok = v(torch.rand(2, 3, 48, 64))
    assert cls.shape == (2, 64) and tok.shape == (2, 64, 6, 8)
    assert torch.isfinite(tok).all()


# ---------------------------------------------------------------------------
@pytest.mark.parametrize("encoder", ["pyramid", "dino"])
def test_anchor_samples_its_pixel_and_skips_behind(encoder):
    images, cams = ring_views()
    kw = {}
    if encoder == "dino":
        kw = dict(zip(("resnet", "vit"), _tiny_backbones(0)))
    ibr = IBRFeatures(encoder, images, cams, c_r=8, **kw)
    with torch.no_grad():
        maps = ibr.feature_maps()
    assert [tuple(m.shape) for m in maps] == [(8, 24, 32)] * 2
    # the centre of map cell (row 7, col 11) is full-res pixel ((11+0.5)*2, (7+0.5)*2)
    cam = cams[0]
    u, v = (11 + 0.5) * 2, (7 + 0.5) * 2
    ray = np.linalg.inv(cam.K) @ np.array([u, v, 1.0])
    X = cam.c2w[:3, :3] @ (ray * 2.0) + cam.center  # depth 2 in front of camera 0
    # camera 1 sits on the opposite side; place a copy of camera 0 rotated 180 deg so X is behind it
    back = Camera(K=cam.K, w2c=look_at(cam.center, 2 * cam.center - X, [0, 0, 1]), width=64, height=48)
    ibr2 = IBRFeatures(encoder, images, [cam, back], c_r=8, **kw)
    ibr2.load_state_dict(ibr.state_dict())
    with torch.no_grad():
        f = ibr2(torch.tensor(X[None], dtype=torch.float32))
    assert torch.allclose(f[0], maps[0][:, 7, 11], atol=1e-5)
    uv, z = back.project(X[None])
    assert z[0] < 0
    # an anchor seen by nobody (far outside every frustum) gets zeros
    with torch.no_grad():
        f0 = ibr2(torch.tensor([[1e3, 1e3, -1e3]], dtype=torch.float32))
    assert torch.equal(f0, torch.zeros(1, 8))


def test_a_view_holding_no_data_at_the_projection_does_not_see_the_anchor():
    """An anchor landing on a pixel without data in one view (its fill) averages the other views only;
    elsewhere in that view it is averaged as before."""
    images, cams = ring_views(V=3)
    ibr = IBRFeatures("pyramid", images, cams, c_r=8)
    X = torch.zeros(1, 3)  # the look-at point, inside all three views
    uv, _ = cams[1].project(np.zeros((1, 3)))
    u, v = int(uv[0, 0]), int(uv[0, 1])
    hole = np.ones((48, 64), bool)
    hole[v - 1:v + 2, u - 1:u + 2] = False
    masked = IBRFeatures("pyramid", images, cams, c_r=8, valid=[None, hole, None])
    masked.load_state_dict(ibr.state_dict())
    two = IBRFeatures("pyramid", [images[0], images[2]], [cams[0], cams[2]], c_r=8)
    two.load_state_dict(ibr.state_dict())
    with torch.no_grad():
        assert torch.allclose(masked(X), two(X), atol=1e-6) and not torch.allclose(ibr(X), two(X), atol=1e-3)
        far = torch.tensor([[0.3, -0.2, 0.1]])  # elsewhere in view 1
        assert torch.equal(masked(far), ibr(far))


def test_average_over_views_and_state_dict_small():
    images, cams = ring_views(V=3)
    ibr = IBRFeatures("pyramid", images, cams, c_r=8)
    X = torch.zeros(1, 3)  # the look-at point, inside all three views
    maps = [m.detach() for m in ibr.feature_maps()]
    want = []
    for i, c in enumerate(cams):
        uv, z = c.project(np.zeros((1, 3)))
        assert z[0] > 0 and 0 <= uv[0, 0] < 64 and 0 <= uv[0, 1] < 48
        g = torch.tensor([[[[uv[0, 0] / 32 - 1, uv[0, 1] / 24 - 1]]]], dtype=torch.float32)
        want.append(torch.nn.functional.grid_sample(maps[i][None], g, align_corners=False)[0, :, 0, 0])
    assert torch.allclose(ibr(X)[0], torch.stack(want).mean(0), atol=1e-5)
    # only P is saved: no image-sized buffers
    assert all(k.startswith("proj.") for k in ibr.state_dict())


@pytest.mark.stability
def test_gradients_reach_projection_and_are_finite():
    """IBR feature projection at extreme anchor positions: finite features and gradients reaching P."""
    images, cams = ring_views()
    images[0].zero_()  # an all-black view
    ibr = build_ibr("pyramid", images, cams, c_r=8)
    assert build_ibr("none", images, cams) is None
    X = torch.randn(200, 3) * 2
    X[0] = torch.tensor([0.0, 0.0, 1e9])  # extreme positions
    X[1] = torch.tensor(cams[0].center, dtype=torch.float32)  # exactly at a camera centre
    f = ibr(X)
    assert f.shape == (200, 8) and torch.isfinite(f).all()
    f.square().sum().backward()
    grads = [p.grad for p in ibr.projection_parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0
    # frozen P: maps are cached and still correct
    for p in ibr.projection_parameters():
        p.requires_grad_(False)
    a = ibr(X)
    assert not a.requires_grad and torch.equal(ibr(X), a)
    with torch.no_grad():
        ibr.proj["level0"].bias.add_(1.0)
    assert not torch.equal(ibr(X), a)  # the cache follows parameter changes


@pytest.mark.parametrize("encoder", ["pyramid", "dino"])
def test_forward_equals_sampling_the_fused_maps(encoder):
    """Averaging over views: matches grid_sample on each view's full map, sizes not divisible by 8/32."""
    images, cams = ring_views(W=70, H=52, V=3)  # sizes that do not divide evenly
    kw = dict(zip(("resnet", "vit"), _tiny_backbones(0))) if encoder == "dino" else {}
    ibr = IBRFeatures(encoder, images, cams, c_r=8, **kw)
    torch.manual_seed(1)
    X = torch.randn(300, 3) * 1.5
    with torch.no_grad():
        maps = ibr.feature_maps()
        got = ibr(X)
    want = torch.zeros(300, 8)
    cnt = torch.zeros(300, 1)
    for i, c in enumerate(cams):
        uv, z = c.project(X.double().numpy())
        ok = torch.tensor((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 70) & (uv[:, 1] >= 0) & (uv[:, 1] < 52))
        g = torch.tensor(np.stack([uv[:, 0] / 35 - 1, uv[:, 1] / 26 - 1], -1), dtype=torch.float32)
        s = torch.nn.functional.grid_sample(maps[i][None], g[None, None], mode="bilinear", padding_mode="border",
                                            align_corners=False)[0, :, 0].T
        want += s * ok[:, None]
        cnt += ok[:, None]
    assert (cnt > 0).sum() > 150 and (cnt == 0).sum() > 0
    want = want / cnt.clamp(min=1)
    assert torch.allclose(got, want, atol=1e-4)


def test_resolve_encoder(tmp_path):
    r, v = tmp_path / "r.pth", tmp_path / "v.pth"
    r.write_bytes(b"x"), v.write_bytes(b"x")
    assert resolve_encoder("auto", (r, v))[0] == "dino"
    name, why = resolve_encoder("auto", (r, None))
    assert name == "pyramid" and "no DINO weights" in why
    assert resolve_encoder("none", (None, None))[0] == "none"
    with pytest.raises(InputError):
        resolve_encoder("dino", (None, v))
    with pytest.raises(InputError, match="missing.pth"):
        resolve_encoder("dino", (r, tmp_path / "missing.pth"))
    with pytest.raises(InputError):
        resolve_encoder("clip", (None, None))


@pytest.mark.slow
def test_dino_encoder_from_weight_files_of_the_official_size(tmp_path):
    """The paper's encoder as a user gets it: ``--dino-resnet`` / ``--dino-vit`` files of the full-size
    ResNet-50 and ViT-B/8 (random weights here, in the official layouts: torchvision's with its fc
    head, DINO's teacher checkpoint), built and loaded from the paths: the features are those of
    the same networks handed over in memory."""
    torch.manual_seed(3)
    resnet, vit = dino_resnet50().eval(), dino_vitb8().eval()
    torch.save(dict(resnet.state_dict(), **{"fc.weight": torch.zeros(2, 2048), "fc.bias": torch.zeros(2)}),
               tmp_path / "dino_resnet50_pretrain.pth")
    torch.save({"teacher": {f"backbone.{k}": t for k, t in vit.state_dict().items()}},
               tmp_path / "dino_vitbase8_pretrain.pth")
    images, cams = ring_views()
    from_files = IBRFeatures("dino", images, cams, c_r=8, dino_resnet=tmp_path / "dino_resnet50_pretrain.pth",
                             dino_vit=tmp_path / "dino_vitbase8_pretrain.pth")
    in_memory = IBRFeatures("dino", images, cams, c_r=8, resnet=resnet, vit=vit)
    # The backbones' feature levels, before the projection (random per instance).
    a = {k: t for k, t in from_files.named_buffers() if k.startswith("feat_")}
    b = {k: t for k, t in in_memory.named_buffers() if k.startswith("feat_")}
    assert a.keys() == b.keys() and len(a) >= 2
    for k, t in a.items():
        assert torch.isfinite(t).all() and t.abs().max() > 0 and torch.allclose(t, b[k], atol=1e-5), k
