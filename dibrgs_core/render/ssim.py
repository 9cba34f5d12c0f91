"""SSIM map of two images on the C++ path (``csrc/ssim.h``), for the training loss.

The kernel lives in the rasterizer's extension (one build, one cache: :mod:`.fast`);
:func:`dibrgs_core.training.losses.ssim_map` calls it for CPU tensors when the
rasterizer's backend resolves to the C++ path, and keeps the torch formulation for
everything else.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .fast import extension, ready


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
    return _SSIMMap.apply(ready(x, dt), ready(y, dt, detach=True), ready(window, dt, detach=True))


class _Photometric(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, g, wl, ws, lam):  # type: ignore[override]
        loss, a, b, c = extension().photometric_forward(x, y, g, wl, ws, lam)
        ctx.save_for_backward(x, y, g, wl, ws, a, b, c)
        ctx.lam = lam
        return loss

    @staticmethod
    def backward(ctx, gl):  # type: ignore[override]
        x, y, g, wl, ws, a, b, c = ctx.saved_tensors
        dx = extension().photometric_backward(gl, x, y, a, b, c, g, wl, ws, ctx.lam)
        return dx, None, None, None, None, None


def photometric_fast(x: Tensor, y: Tensor, window: Tensor, wl: Tensor, ws: Tensor, lam: float) -> Tensor:
    """``(1 - lam) sum(|x - y| wl) + lam sum((1 - SSIM(x, y)) ws)`` of (H, W, C) CPU images in one
    autograd node, ``wl`` and ``ws`` (H, W, C) weights (sums over every value;
    :func:`dibrgs_core.training.losses.photometric_loss` picks them). The
    loss of a step was about twenty torch operators and a dozen autograd nodes around the SSIM
    kernels, a millisecond of dispatch a step on either thread count. Differentiable in ``x``
    only."""
    dt = x.dtype
    return _Photometric.apply(ready(x, dt), ready(y, dt, detach=True), ready(window, dt, detach=True),
                              ready(wl, dt, detach=True), ready(ws, dt, detach=True), float(lam))
