"""A small synthetic aerial scene rendered with the project's own rasterizer (fast, no Blender).

Geometry: a coloured ground plane of Gaussians (a street grid pattern) with a few
box "buildings" on it, in metres with z up, seen from the generated-scene camera
layout of ``synth.flights.scene_cameras`` (near-nadir view 000, orbit views 001-020,
60 track poses). Used by the training tests that need many short runs; the
Blender-rendered ``tiny_scene`` fixture is used for the end-to-end test.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch


def _cloud(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    g = np.linspace(-60, 60, 70)
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = [np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)]
    street = ((np.abs(X) % 30) < 4) | ((np.abs(Y) % 30) < 4)
    col = np.where(street.ravel()[:, None], [0.35, 0.35, 0.38], [0.25, 0.55, 0.2])
    cols = [col * (0.85 + 0.3 * rng.random((X.size, 1)))]
    for cx, cy, h, c in [(-15, -15, 18, (0.8, 0.3, 0.2)), (15, 15, 12, (0.9, 0.85, 0.7)),
                         (15, -15, 25, (0.3, 0.4, 0.8)), (-15, 15, 8, (0.7, 0.7, 0.2))]:
        s = np.linspace(-7, 7, 10)
        zz = np.linspace(0, h, max(3, int(h / 1.5)))
        a, b = np.meshgrid(s, s, indexing="ij")
        roof = np.stack([cx + a.ravel(), cy + b.ravel(), np.full(a.size, h)], 1)
        walls = []
        for z in zz:
            for t in s:
                walls += [(cx + t, cy - 7, z), (cx + t, cy + 7, z), (cx - 7, cy + t, z), (cx + 7, cy + t, z)]
        walls = np.array(walls)
        pts += [roof, walls]
        cols += [np.tile(c, (len(roof), 1)), np.tile(np.array(c) * 0.7, (len(walls), 1))]
    return np.concatenate(pts), np.clip(np.concatenate(cols), 0, 1)


def make_synth_scene(root: Path, resolution: int = 48, seed: int = 0) -> Path:
    """Write the synthetic scene in LEVIR-NVS layout to ``root`` and return it."""
    from dibrgs_core.data.scene import View
    from dibrgs_core.data.levir import write_scene
    from dibrgs_core.render import rasterize
    from dibrgs_core.synth.flights import OrbitSpec, scene_cameras

    pts, cols = _cloud(seed)
    spec = OrbitSpec()
    views, track = scene_cameras(resolution, 0.3, spec)
    n = len(pts)
    means = torch.tensor(pts, dtype=torch.float32)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    scales = torch.full((n, 3), 1.1)
    opac = torch.full((n,), 0.95)
    colors = torch.tensor(cols, dtype=torch.float32)
    out = {}
    for cam in views:
        with torch.no_grad():
            img, alpha, depth, _ = rasterize(means, quats, scales, opac, colors,
                                             torch.tensor(cam.w2c, dtype=torch.float32),
                                             torch.tensor(cam.K, dtype=torch.float32), cam.width, cam.height,
                                             background=torch.tensor([0.5, 0.6, 0.7]))
        out[cam.name] = View(cam, img.clamp(0, 1).numpy().astype(np.float32),
                             depth[..., 0].numpy().astype(np.float32))
    write_scene(root, out, track)
    return root
