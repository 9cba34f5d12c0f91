"""Dense float64 brute-force renderer: every Gaussian against every pixel.

Used as the oracle in tests/test_rasterizer*.py. It takes the screen-space
quantities of ``project_gaussians`` and applies the rasterizer's rules
directly, one pixel at a time (no tiles lists, no chunking): a Gaussian is
considered at a pixel only when the pixel's 16x16 tile lies in the Gaussian's
3-sigma tile square ``floor((m - r) / 16) .. ceil((m + r) / 16)``; Gaussians in
increasing depth (ties by index); skip ``power > 0``; ``alpha = min(0.99,
o exp(power))``; skip ``alpha < 1/255``; stop when ``T (1 - alpha) < 1e-4``.
"""
from __future__ import annotations

import math

import numpy as np


def brute_composite(means2d, conics, opacities, feats, depths, radii, width, height, return_count=False):
    """(H, W, C) float64 composite of the given per-Gaussian arrays (numpy or torch); with
    ``return_count`` also the number of (pixel, Gaussian) pairs composited."""
    m = np.asarray(means2d, dtype=np.float64)
    con = np.asarray(conics, dtype=np.float64)
    op = np.asarray(opacities, dtype=np.float64)
    f = np.asarray(feats, dtype=np.float64)
    z = np.asarray(depths, dtype=np.float64)
    r = np.asarray(radii).astype(np.float64)
    order = [i for i in np.argsort(z, kind="stable") if r[i] > 0]
    out = np.zeros((height, width, f.shape[1]))
    count = 0
    x0 = np.floor((m[:, 0] - r) / 16)
    x1 = np.ceil((m[:, 0] + r) / 16)
    y0 = np.floor((m[:, 1] - r) / 16)
    y1 = np.ceil((m[:, 1] + r) / 16)
    for py in range(height):
        for px in range(width):
            tx, ty = px // 16, py // 16
            T = 1.0
            acc = np.zeros(f.shape[1])
            for i in order:
                if not (x0[i] <= tx < x1[i] and y0[i] <= ty < y1[i]):
                    continue
                dx = m[i, 0] - (px + 0.5)
                dy = m[i, 1] - (py + 0.5)
                power = -0.5 * (con[i, 0] * dx * dx + con[i, 2] * dy * dy) - con[i, 1] * dx * dy
                if power > 0:
                    continue
                a = min(0.99, op[i] * math.exp(power))
                if a < 1.0 / 255.0:
                    continue
                if T * (1 - a) < 1e-4:
                    break
                acc += a * T * f[i]
                T *= 1 - a
                count += 1
            out[py, px] = acc
    return (out, count) if return_count else out
