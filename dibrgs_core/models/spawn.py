"""Neural Gaussians spawned from the decoder outputs of the visible anchors (Scaffold-GS).

For ``M`` visible anchors with ``k`` offsets each, row ``(a, j)`` (``a * k + j``) is offset
``j`` of anchor ``a``; it becomes a Gaussian when its Tanh opacity is above 0, in row order:

* mean ``anchor[a] + offset[a, j] * scal[a, :3]`` (world units);
* scale ``scal[a, 3:] * sigmoid(cov[a, 7j:7j+3])`` (world-unit standard deviations);
* rotation ``cov[a, 7j+3:7j+7]`` normalised in float64 (w, x, y, z; a quaternion shorter than
  1e-12 is the identity);
* opacity ``nop[a*k + j]``, colour ``color[a, 3j:3j+3]``.

``scal`` is the activated anchor scaling ``exp(clamp(l_v, -30, 20))`` (:func:`activate_scaling`)
of the visible anchors' logs ``l_v``, which :func:`spawn` takes. Two paths with the same maths:
the C++ one of the rasterizer's extension (``render/csrc/spawn.h``; one parallel pass forward
and backward, the activation included) for CPU tensors when the rasterizer's backend resolves to
it, and the torch formulation (any device, the ``reference`` backend).
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
from torch import Tensor

from ..render import Backend, fast, uses_fast

QUAT_EPS = 1e-12  # a quaternion this short has no direction (spawn.h uses the same)
LOG_SCALING_RANGE = (-30.0, 20.0)  # anchor scaling logs are clamped to this before exp (spawn.h too)


def activate_scaling(log_s: Tensor) -> Tensor:
    """Anchor scaling from its log, clamped so that exp stays finite."""
    return torch.exp(log_s.clamp(*LOG_SCALING_RANGE))


class Spawned(NamedTuple):
    """The kept Gaussians (S rows) and the mask ``selected`` (M*k,) of the rows they come from."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    selected: Tensor


def spawn(nop: Tensor, color: Tensor, cov: Tensor, anchor: Tensor, log_scal: Tensor, offset: Tensor,
          backend: Backend | None = None) -> Spawned:
    """Gaussians of the rows with ``nop > 0``.

    Args:
        nop: (M, k) or (M*k,) Tanh opacities (the opacity head's output as it is: a reshape
            would be one more autograd node a step); color: (M, 3k) colours in [0, 1]; cov:
            (M, 7k) raw scale logits and quaternions (7 a row); anchor: (M, 3) anchor positions;
            log_scal: (M, 6) the anchors' scaling logs (activated here:
            :func:`activate_scaling`); offset: (M, k, 3) learned offsets.
        backend: the rasterizer's backend choice (None: :func:`dibrgs_core.render.get_backend`).
    """
    if uses_fast(backend, anchor):
        dt = anchor.dtype
        means, quats, scales, opac, colors, selected = _SpawnFast.apply(
            *(fast.ready(t, dt) for t in (nop, color, cov, anchor, log_scal, offset)))
        return Spawned(means, quats, scales, opac, colors, selected)
    return spawn_reference(nop.reshape(-1), color, cov, anchor, activate_scaling(log_scal), offset)


def true_indices(mask: Tensor, backend: Backend | None = None) -> Tensor:
    """``torch.nonzero(mask).squeeze(1)``: the increasing int64 positions of a (N,) bool mask's
    true entries (the visible anchors' rows, for :func:`take_rows`). On the C++ path one pass
    of the extension: torch's nonzero costs tens of microseconds for a few thousand anchors and
    hundreds for tens of thousands, on the step's serial path."""
    if mask.dim() == 1 and mask.dtype == torch.bool and uses_fast(backend, mask):
        return fast.extension().true_indices(mask)
    return torch.nonzero(mask).squeeze(1)


def take_rows(tensors: Sequence[Tensor], idx: Tensor, backend: Backend | None = None) -> list[Tensor]:
    """``[t.index_select(0, idx) for t in tensors]``: rows ``idx`` (int64) of tensors (N, ...)
    that share their rows (a model's per-anchor parameters).

    On the C++ path (``render/csrc/rows.h``; one autograd node for all of them, each node costs
    tens of microseconds in Python), when ``idx`` is strictly increasing (a nonzero of a mask, as
    the visible anchors are), a gradient is one parallel pass of row copies into otherwise zero
    rows; torch's index_add into a zeroed tensor runs on one thread. Other indices (repeats, any
    order) fall back to that index_add; other devices and the reference backend use
    index_select."""
    tensors = list(tensors)
    if tensors and idx.dtype == torch.int64 and all(
            t.dtype in (torch.float32, torch.float64) for t in tensors) and uses_fast(backend, tensors[0]):
        return list(_TakeRows.apply(idx, *tensors))
    return [t.index_select(0, idx) for t in tensors]


class _TakeRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, idx, *tensors):  # type: ignore[override]
        outs, increasing = fast.extension().take_rows_forward(list(tensors), idx)
        ctx.save_for_backward(idx)
        ctx.shapes, ctx.increasing = [t.shape for t in tensors], increasing
        ctx.set_materialize_grads(False)  # a row set nobody used needs no gradient
        return tuple(outs)

    @staticmethod
    def backward(ctx, *grads):  # type: ignore[override]
        (idx,) = ctx.saved_tensors
        want = [i for i, g in enumerate(grads) if g is not None and ctx.needs_input_grad[1 + i]]
        out: list[Tensor | None] = [None] * len(grads)
        if ctx.increasing:
            got = fast.extension().take_rows_backward([grads[i] for i in want], idx, ctx.shapes[0][0])
        else:
            got = [grads[i].new_zeros(ctx.shapes[i]).index_add_(0, idx, grads[i]) for i in want]
        for i, g in zip(want, got):
            out[i] = g
        return (None, *out)


def spawn_reference(nop: Tensor, color: Tensor, cov: Tensor, anchor: Tensor, scal: Tensor, offset: Tensor
                    ) -> Spawned:
    """:func:`spawn` in torch operators (autograd, any device)."""
    k = offset.shape[1]
    selected = nop > 0.0
    # One nonzero and integer gathers: boolean-mask indexing would search the mask again for
    # each tensor, and its backward is a slower scatter.
    sel = torch.nonzero(selected).squeeze(1)  # row = visible anchor * k + offset number
    owner = torch.div(sel, k, rounding_mode="floor")
    colors = color.reshape(-1, 3).index_select(0, sel)
    c = cov.reshape(-1, 7).index_select(0, sel)
    s = scal.index_select(0, owner)
    scales = s[:, 3:] * torch.sigmoid(c[:, :3])
    q = c[:, 3:7]
    qd = q.double()  # its squares overflow float32 from |q| ~ 1.8e19
    qn = qd.norm(dim=1, keepdim=True)
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=qd.dtype, device=q.device)
    quats = torch.where(qn > QUAT_EPS, qd / qn.clamp_min(QUAT_EPS), ident).to(q.dtype)
    means = anchor.index_select(0, owner) + offset.reshape(-1, 3).index_select(0, sel) * s[:, :3]
    return Spawned(means, quats, scales, nop.index_select(0, sel), colors, selected)


class _SpawnFast(torch.autograd.Function):
    @staticmethod
    def forward(ctx, nop, color, cov, anchor, log_scal, offset):  # type: ignore[override]
        # nop is read by its values (M k of them), whatever its shape: no reshape (a view, but tens
        # of microseconds of dispatch in place, between the heavy passes).
        means, quats, scales, opac, colors, start, selected = fast.extension().spawn_forward(
            nop, color, cov, anchor, log_scal, offset)
        ctx.save_for_backward(nop, cov, log_scal, offset, start)
        ctx.mark_non_differentiable(selected)
        ctx.set_materialize_grads(False)  # the row mask's gradient was a zero tensor made every step
        ctx.rows = means.shape[0]
        return means, quats, scales, opac, colors, selected

    @staticmethod
    def backward(ctx, gm, gq, gs, go, gc, _gsel):  # type: ignore[override]
        nop, cov, log_scal, offset, start = ctx.saved_tensors
        n = ctx.rows
        gm, gq, gs, gc = (nop.new_zeros(n, w) if g is None else g for g, w in ((gm, 3), (gq, 4), (gs, 3), (gc, 3)))
        go = nop.new_zeros(n) if go is None else go
        # dnop comes back in nop's shape (empty_like).
        return tuple(fast.extension().spawn_backward(gm, gq, gs, go, gc, nop, cov, log_scal, offset, start))
