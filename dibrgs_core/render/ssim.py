"""SSIM map of two images on the C++ path (``csrc/ssim.h``), for the training loss.

The kernel lives in the rasterizer's extension (one build, one cache: :mod:`.fast`);
:func:`dibrgs_core.training.losses.ssim_map` calls it for CPU tensors when the
rasterizer's backend resolves to the C++ path, and keeps the torch formulation for
everything else.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .fast import extension


class _SSIMMap(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, g):  # type: ignore[override]
        s, a, b, c = extension().ssim_forward(x, y, g)
        ctx.save_for_backward(x, y, g, a, b, c)
        return s

    @staticmethod
    def backward(ctx, gs):  # type: ignore[override]
        x, y, g, a, b, c = ctx.saved_tensors
        return extension().ssim_backward(gs, x, y, a, b, c, g), None, None


def ssim_map_fast(x: Tensor, y: Tensor, window: Tensor) -> Tensor:
    """C++ per-pixel SSIM of (H, W, C) CPU images ``x`` against ``y`` (separable ``window``, odd
    length; borders replicated): the maths of :func:`dibrgs_core.training.losses.ssim_map`, in one
    pass over the image instead of about thirty torch operators. Differentiable in ``x`` only."""
    dt = x.dtype
    return _SSIMMap.apply(x.contiguous(), y.detach().to(dt).contiguous(), window.detach().to(dt).contiguous())
