"""3DGS PLY export."""
from __future__ import annotations

import numpy as np
import torch

from dibrgs_core.render import rasterize


def _read_ply(path):
    """(means, quats, scales, opacities, sh_dc (N,3), sh_rest (N,K,3) or None) as a 3DGS viewer reads them."""
    import trimesh

    v = trimesh.load(path).metadata["_ply_raw"]["vertex"]["data"]

    def cols(*names):
        return torch.tensor(np.stack([v[k] for k in names], 1), dtype=torch.float32)

    rest = sorted((k for k in v.dtype.names if k.startswith("f_rest_")), key=lambda k: int(k[7:]))
    n = len(v)
    sh_rest = cols(*rest).reshape(n, 3, -1).transpose(1, 2) if rest else None  # channel-major on file
    return (cols("x", "y", "z"), cols(*(f"rot_{i}" for i in range(4))),
            torch.exp(cols(*(f"scale_{i}" for i in range(3)))), torch.sigmoid(cols("opacity")[:, 0]),
            cols("f_dc_0", "f_dc_1", "f_dc_2"), sh_rest)


def _render_ply(path, cam, background, near, sh_degree=0):
    """Render a PLY file's Gaussians the way 3DGS viewers colour them (SH at the view direction, + 0.5, >= 0)."""
    from dibrgs_core.models.gs3d import eval_sh_split

    means, quats, scales, opac, dc, rest = _read_ply(path)
    d = means - torch.tensor(cam.center, dtype=torch.float32)
    d = d / d.norm(dim=1, keepdim=True)
    rest = torch.zeros(len(means), 0, 3) if rest is None else rest
    rgb = (eval_sh_split(sh_degree, dc[:, None], rest, d) + 0.5).clamp_min(0.0)
    img, *_ = rasterize(means, quats, scales, opac, rgb, torch.tensor(cam.w2c, dtype=torch.float32),
                        torch.tensor(cam.K, dtype=torch.float32), cam.width, cam.height,
                        background=background, near=near)
    return img.clamp(0, 1).numpy()


def test_exported_dibrgs_run_renders_as_the_model_from_the_export_camera(finished_run, tmp_path):
    """What a Gaussian viewer shows of the PLY is the model's own render from the camera it was
    decoded for (positions, wxyz quaternions, log scales, logit opacities, colour as SH DC)."""
    from dibrgs_core.camera.frame import central_camera
    from dibrgs_core.evaluation.evaluate import load_trained
    from dibrgs_core.evaluation.export import export_ply

    tr = load_trained(finished_run)
    assert tr.method == "dibrgs"
    ply = tmp_path / "g.ply"
    assert export_ply(finished_run, ply) > 0
    cam = central_camera(tr.train_cameras)
    got = _render_ply(ply, cam, torch.tensor(tr.cfg.background, dtype=torch.float32), tr.model.near)
    ref, _ = tr.render(cam)
    assert ref.std() > 0.01  # the scene, not the background
    assert np.abs(got - ref).max() < 1e-4


def test_exported_3dgs_spherical_harmonics_render_as_the_model(tmp_path):
    """Degree-3 SH with every coefficient set: the file's channel-major f_rest and the model's
    basis agree, so a viewer's colours are the model's from any direction."""
    from dibrgs_core.evaluation.export import write_gaussian_ply
    from dibrgs_core.models.base import CameraTensors, render_model
    from model_synth import small_camera

    rng = np.random.default_rng(3)
    from dibrgs_core.models.gs3d import Gaussians3D

    m = Gaussians3D(rng.uniform(-10, 10, (300, 3)) * [1, 1, 0.1], rng.uniform(0, 1, (300, 3)), 3)
    with torch.no_grad():
        m.sh_rest.copy_(torch.tensor(rng.normal(0, 0.3, m.sh_rest.shape), dtype=torch.float32))
        m.opacity.fill_(2.0)
        m.log_scales.add_(1.0)
    m.active_sh_degree = 3
    cams = [small_camera(eye=e, size=48) for e in ((0, -30, 40), (25, 5, 30))]
    g = m.export_gaussians(cams)
    ply = tmp_path / "g.ply"
    write_gaussian_ply(ply, g["means"], g["quats"], g["scales"], g["opacities"], g["sh_dc"], g["sh_rest"])
    bg = torch.zeros(3)
    for cam in cams:
        ref = render_model(m, CameraTensors.of(cam), bg)[0].clamp(0, 1).detach().numpy()
        got = _render_ply(ply, cam, bg, m.near, sh_degree=3)
        assert ref.std() > 0.05
        assert np.abs(got - ref).max() < 1e-4, cam.center


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
