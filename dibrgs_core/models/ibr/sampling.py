"""Sampling an upsampled map at points without building the upsampled map.

``F.grid_sample(F.interpolate(m, size=S, mode=mode), grid, mode="bilinear",
padding_mode="border", align_corners=False)`` is linear in ``m``: each point reads
2 x 2 pixels of the upsampled map, and each of those is a blend of up to 2 x 2
pixels of ``m`` (bilinear; one pixel for nearest). :func:`upsampled_taps` returns
those 16 taps' flat indices into ``m`` and their weights, so one gather
(``F.embedding_bag``) gives the same value for any number of channels, at a cost
proportional to the points rather than to the upsampled map.

The taps' weights sum to 1 (border padding keeps every corner inside the map;
both interpolations are partitions of unity), which is why a per-pixel affine map
(a 1x1 convolution, ``W f + b``) commutes with the whole operation.
"""
from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

Upsampling = Literal["bilinear", "nearest"]


def axis_sources(n_in: int, n_out: int, mode: Upsampling) -> tuple[torch.Tensor, torch.Tensor]:
    """For each output index of ``F.interpolate(size=n_out, align_corners=False)`` along one
    axis of length ``n_in``: its two source indices (n_out, 2) and weights (n_out, 2).

    Read from torch's own interpolation of the identity, so the indices and weights
    round exactly as ``F.interpolate`` does (2-D bilinear is this 1-D rule per axis).
    """
    if mode == "nearest":
        src = F.interpolate(torch.arange(n_in, dtype=torch.float32)[None, None], size=n_out,
                            mode="nearest")[0, 0].long()
        return torch.stack([src, src], 1), torch.tensor([1.0, 0.0]).repeat(n_out, 1)
    m = F.interpolate(torch.eye(n_in)[:, None], size=n_out, mode="linear", align_corners=False)[:, 0].T
    w, idx = m.topk(min(2, n_in), dim=1)
    if n_in == 1:
        idx, w = idx.repeat(1, 2), torch.cat([w, torch.zeros_like(w)], 1)
    return idx, w


def grid_corners(g: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``grid_sample``'s two corners (..., 2) and weights (..., 2) along one axis of ``size``
    pixels for normalised coordinates ``g`` (bilinear, border padding, align_corners=False)."""
    x = (((g + 1.0) * size - 1.0) / 2.0).clamp(0.0, size - 1.0)
    x0 = x.floor()
    a1 = x - x0
    i0 = x0.long()
    return torch.stack([i0, (i0 + 1).clamp(max=size - 1)], -1), torch.stack([1.0 - a1, a1], -1)


def upsampled_taps(grid: torch.Tensor, in_size: tuple[int, int], out_size: tuple[int, int],
                   mode: Upsampling) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat indices (..., 16) into an ``in_size`` (h, w) map and weights (..., 16) such that
    ``sum_k w[k] * m.flatten()[idx[k]]`` equals bilinear border ``grid_sample`` at ``grid``
    (..., 2) (normalised x, y) of ``m`` upsampled to ``out_size`` (H, W) with ``mode``."""
    (h, w), (H, W) = in_size, out_size
    taps = []
    for g, n_in, n_out in ((grid[..., 0], w, W), (grid[..., 1], h, H)):
        ci, cw = grid_corners(g, n_out)                # (..., 2) corners in the upsampled map
        si, sw = axis_sources(n_in, n_out, mode)       # (n_out, 2) sources of each upsampled pixel
        taps.append((si[ci].flatten(-2), (cw[..., :, None] * sw[ci]).flatten(-2)))  # (..., 4)
    (ix, wx), (iy, wy) = taps
    idx = (iy[..., :, None] * w + ix[..., None, :]).flatten(-2)
    wt = (wy[..., :, None] * wx[..., None, :]).flatten(-2)
    return idx, wt
