"""The densification statistic both strategies gather: each Gaussian's screen-space gradient norm.

For every Gaussian a view rasterized with a positive radius, the norm of its mean's gradient in
pixels (the NDC gradient the rasterizer's ``means2d`` carries times half the image size, 3DGS's
and Scaffold-GS's statistic; NaN and +inf count 0) is added to a running sum of its slot and 1 to
the slot's count. A 3DGS Gaussian is its own slot; a neural Gaussian's slot is its anchor's
offset (anchor ``a``, offset ``o``: ``a k + o``). On the rasterizer's C++ path one pass of the
extension (``grad_norm_stats``); torch's masked reads and writes were a nonzero and a gather
each, about 1.5 ms of a 256x256 step while statistics are gathered (half of training).
Both paths give the same sums, bit for bit.
"""
from __future__ import annotations

import torch

from ..models.spawn import true_indices
from ..render import fast, uses_fast


@torch.no_grad()
def add_grad_norms(acc: torch.Tensor, denom: torch.Tensor, grad: torch.Tensor, visible: torch.Tensor,
                   width: int, height: int, aidx: torch.Tensor | None = None,
                   selected: torch.Tensor | None = None, k: int = 1) -> None:
    """Add this view's gradient norms into ``acc`` and counts into ``denom`` (float32, one entry a
    slot), in place. ``grad`` (G, 2): the rasterized Gaussians' ``means2d`` gradient; ``visible``
    (G,) bool: those with a positive radius. Neural Gaussians: ``aidx`` (M,) int64 the visible
    anchors, ``selected`` (M k,) bool which of their offsets were rasterized (in order)."""
    g = grad.detach()
    anchors = aidx is not None
    if (g.dtype == torch.float32 and acc.dtype == torch.float32 and acc.is_contiguous() and denom.is_contiguous()
            and uses_fast(None, g)):
        empty = torch.empty(0, dtype=torch.int64)
        fast.extension().grad_norm_stats(acc, denom, g, visible.reshape(-1), width / 2.0, height / 2.0,
                                         aidx if anchors else empty,
                                         selected if anchors else empty.bool(), k if anchors else 1)
        return
    seen = true_indices(visible.reshape(-1))
    if anchors:
        q = true_indices(selected)[seen]  # offset slots among the visible anchors' M k
        slot = aidx[q // k] * k + q % k
    else:
        slot = seen
    px = g.index_select(0, seen) * torch.tensor([width / 2.0, height / 2.0], dtype=g.dtype)
    norm = torch.nan_to_num(px.norm(dim=1), nan=0.0, posinf=0.0).to(acc.dtype)
    acc.index_add_(0, slot, norm)
    denom.index_add_(0, slot, torch.ones_like(norm))
