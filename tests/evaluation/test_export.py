"""3DGS PLY export."""
from __future__ import annotations


import numpy as np



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
