"""The IBR projection ``P`` applied to the anchors' sampled encoder features, as one autograd node.

``P`` is one linear map per encoder level (a 1x1 convolution, or a linear layer for ViT tokens);
on the anchors' view-averaged raw features (:meth:`.features.IBRFeatures.anchor_rows`: the
levels' channels side by side, then a column that is 1 where a view sees the anchor) it is one
product with the levels' weights side by side and their biases summed on that last column. Built
from torch operators that is about eight operators and as many autograd nodes a training step,
each a few dozen microseconds of dispatch on the step's serial path (issue 17); here the weight
matrix is assembled without recording and the backward hands each level's weight and bias its
slice of one product. On the rasterizer's C++ path the rows a view sees are selected, projected
and, backward, summed into the weights' gradients in the extension (``render/csrc/project_rows.h``):
one call each way, split over the threads, with the same values whether recorded or not.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ...render import fast, uses_fast


def _matrix(weights: tuple[torch.Tensor, ...], biases: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """(C_r, D + 1): the levels' weights side by side, then their biases summed."""
    c = weights[0].shape[0]
    return torch.cat([w.reshape(c, -1) for w in weights] + [torch.stack(biases).sum(0)[:, None]], 1)


class _ProjectRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rows, *params):  # type: ignore[override]
        n = len(params) // 2
        ctx.save_for_backward(rows)
        ctx.shapes = [w.shape for w in params[:n]]
        return F.linear(rows, _matrix(params[:n], params[n:]))

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        (rows,) = ctx.saved_tensors
        G = g.t().mm(rows)  # (C_r, D + 1): every weight's gradient side by side, the biases' last
        grads: list[torch.Tensor | None] = [None]
        start = 0
        for shape in ctx.shapes:
            width = shape.numel() // shape[0]
            grads.append(G[:, start:start + width].reshape(shape))
            start += width
        gb = G[:, start]
        # Each level's bias gets the whole last column (they are summed), a tensor of its own.
        grads += [gb.clone() for _ in ctx.shapes]
        return tuple(grads)


class _ProjectRowsFast(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rows, mask, *params):  # type: ignore[override]
        n = len(params) // 2
        out, idx = fast.extension().project_rows_forward(rows, mask, list(params[:n]), list(params[n:]))
        ctx.save_for_backward(rows, idx)
        ctx.shapes = [list(w.shape) for w in params[:n]]
        return out

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        rows, idx = ctx.saved_tensors
        return (None, None, *fast.extension().project_rows_backward(g, rows, idx, ctx.shapes))


def project_rows(rows: torch.Tensor, weights: list[torch.Tensor], biases: list[torch.Tensor],
                 mask: torch.Tensor | None = None) -> torch.Tensor:
    """``rows`` (N, D + 1), or those ``mask`` ((N,) bool) selects, through ``P``:
    ``rows[:, :D] @ [W_1 .. W_L]^T + rows[:, D] * sum(b_l)`` ((M, C_r)), ``weights`` (C_r, D_l, ...)
    and ``biases`` (C_r,) one a level in the rows' order. Differentiable in the weights and biases
    (the rows are sampled features, constants)."""
    grad = torch.is_grad_enabled() and any(p.requires_grad for p in (*weights, *biases))
    if uses_fast(None, rows):
        sel = rows.new_empty(0, dtype=torch.bool) if mask is None else mask
        if grad:  # the rows are sampled features, without gradient: detached only if they had one
            return _ProjectRowsFast.apply(fast.ready(rows, rows.dtype, detach=True), sel, *weights, *biases)
        with torch.no_grad():
            return fast.extension().project_rows_forward(rows, sel, list(weights), list(biases))[0]
    rows = rows if mask is None else rows[mask]
    if not grad:
        return F.linear(rows, _matrix(tuple(weights), tuple(biases)))
    return _ProjectRows.apply(rows.detach(), *weights, *biases)
