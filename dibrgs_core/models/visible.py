"""The neural Gaussians of a view's visible anchors as one autograd node on the C++ path.

:meth:`NeuralGaussians.decode <dibrgs_core.models.scaffold.NeuralGaussians.decode>` is three
steps: the visible anchors' rows of the model's per-anchor tensors (:func:`.spawn.take_rows`),
the decoder heads (:func:`.decoder.decode`) and the spawning (:func:`.spawn.spawn`). On the C++
path each was an autograd node with its Python around it, and that Python runs between a step's
large kernels on cold caches and on one thread whatever the thread count (the first torch
operator after the compositing's backward took about 27 us against 2-3 us for the next ones,
docs/benchmarks.md, session 43). :func:`decode_visible` runs the same three kernels in one call of
the extension each way (``render/csrc/rasterize.cpp`` ``visible_forward`` / ``visible_backward``):
the same values, bit for bit, as the three nodes.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from ..render import fast, uses_fast
from .decoder import (
    Fusion,
    node_input_grads,
    node_inputs,
    node_parameters,
    split_parameters,
)
from .spawn import Spawned


def decode_visible(anchor: Tensor, feat: Tensor, scaling: Tensor, offset: Tensor, idx: Tensor, ibr: Tensor | None,
                   centre: Tensor, dist_scale: float, fusion: Fusion | None, heads: Sequence[nn.Module]
                   ) -> tuple[Spawned, Tensor] | None:
    """Rows ``idx`` of the model's tensors through the decoder and the spawning, in one node.

    Args:
        anchor (N, 3), feat (N, F), scaling (N, 6) (logs), offset (N, k, 3): the model's
            per-anchor tensors, world units; idx: (M,) int64 rows, strictly increasing (a
            nonzero of the visibility mask).
        ibr: (M, C) IBR features of those rows, or None; centre: (3,) camera centre, world units.
        dist_scale, fusion, heads: as :func:`.decoder.decode` (heads: opacity, covariance,
            colour).

    Returns the spawned Gaussians and the opacity head's output (M*k,), outside the graph (the
    strategy's statistics); None where the C++ path does not apply (another device or backend, a
    head not of the decoder's form, mixed dtypes, a camera centre that wants a gradient): the
    caller then takes the three steps one by one.
    """
    fusion = None if ibr is None else fusion
    node = node_parameters(heads, fusion)
    if (node is None or len(heads) != 3 or centre.requires_grad or feat.dim() != 2 or idx.dtype != torch.int64
            or not uses_fast(None, feat)):
        return None
    acts, params = node
    tensors = [anchor, feat, scaling, offset, centre] + ([ibr] if fusion is not None else []) + params
    if feat.dtype not in (torch.float32, torch.float64) or any(t.dtype != feat.dtype for t in tensors):
        return None
    out = _VisibleFast.apply((acts, fusion is not None, float(dist_scale)), idx, *tensors)
    return Spawned(*out[:6]), out[6].reshape(-1)


class _VisibleFast(torch.autograd.Function):
    """Inputs: spec, idx, anchor, feat, scaling, offset, centre, [ibr], per head W1, b1, W2, b2,
    [Wref, bref, Wmod, bmod]."""

    @staticmethod
    def forward(ctx, spec, idx, anchor, feat, scaling, offset, centre, *rest):  # type: ignore[override]
        acts, fused, dist_scale = spec
        n = len(acts)
        ibr, params, (W1, b1, W2, b2, fusion) = node_inputs(fused, n, rest, feat)
        res = fast.extension().visible_forward([anchor, feat, scaling, offset], idx, ibr, fusion, centre, dist_scale,
                                               W1, b1, W2, b2, list(acts))
        means, quats, scales, opac, colors, selected, start, log_s, offs = res[:9]
        outs, (x, dist, gate, ref), hidden = res[9:9 + n], res[9 + n:13 + n], res[13 + n:]
        ctx.save_for_backward(idx, start, log_s, offs, ibr, x, dist, gate, ref, *hidden, *outs, *params)
        ctx.spec, ctx.rows, ctx.anchors = spec, means.shape[0], anchor.shape[0]
        ctx.mark_non_differentiable(selected, outs[0])
        ctx.set_materialize_grads(False)  # an output nobody used needs no zero gradient made
        return means, quats, scales, opac, colors, selected, outs[0]

    @staticmethod
    def backward(ctx, gm, gq, gs, go, gc, _gsel, _gnop):  # type: ignore[override]
        acts, fused, dist_scale = ctx.spec
        n = len(acts)
        idx, start, log_s, offs, ibr, x, dist, gate, ref, *rest = ctx.saved_tensors
        hidden, outs, params = rest[:n], rest[n:2 * n], rest[2 * n:]
        W1, b1, W2, b2, fusion = split_parameters(params, n)
        r = ctx.rows
        gm, gq, gs, gc = (x.new_zeros(r, w) if g is None else g for g, w in ((gm, 3), (gq, 4), (gs, 3), (gc, 3)))
        go = x.new_zeros(r) if go is None else go
        want_anchor, want_dibr = ctx.needs_input_grad[2], fused and ctx.needs_input_grad[7]
        res = fast.extension().visible_backward(gm, gq, gs, go, gc, start, log_s, offs, idx, ctx.anchors, ibr, fusion,
                                                x, dist, gate, ref, list(hidden), list(outs), dist_scale, W1, b1, W2,
                                                b2, list(acts), want_dibr, want_anchor)
        danchor = res.pop(0) if want_anchor else None
        dfeat, dscaling, doffset, dibr = res[:4]
        want = ctx.needs_input_grad
        return (None, None, danchor, dfeat if want[3] else None, dscaling if want[4] else None,
                doffset if want[5] else None, None, *node_input_grads(fused, dibr if want_dibr else None, res[4:]))
