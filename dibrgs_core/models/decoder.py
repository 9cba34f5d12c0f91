"""The decoder of the neural Gaussians: IBR fusion, the decoders' input and their MLP heads.

For the ``M`` visible anchors of a view (paper Sec. "Adaptive Feature Fusion"; Scaffold-GS):

* fused feature ``f = f_s + sigmoid(E_mod(f_v)) * E_ref(f_v)`` (``f_s`` without IBR features);
* input ``x = [f, view / dist, dist / dist_scale]`` with ``view = anchor - camera centre`` (world
  units) and ``dist = max(|view|, 1e-8)`` (``|view|`` summed in float64);
* a head is ``nn.Sequential(Linear(D, H), ReLU(), Linear(H, O))`` optionally followed by ``Tanh``
  or ``Sigmoid`` (the opacity, covariance and colour decoders); :func:`decode` returns each
  head's output for ``x``.

Two paths with the same maths: the C++ one of the rasterizer's extension
(``render/csrc/decoder.h``: the rows cut into one block a thread, fusion, input and heads of a
block in one pass, forward and backward, one autograd node) for CPU tensors when the
rasterizer's backend resolves to it, and torch modules otherwise (:func:`decode_reference`).
The C++ path sums the weight gradients over its blocks, so they differ from torch's in the
last bits.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from ..render import Backend, fast, uses_fast

#: Activation codes of decoder.h (``decoder::Act``).
_ACTS: dict[type | None, int] = {None: 0, nn.Tanh: 1, nn.Sigmoid: 2}
#: The camera distance is clamped at this (world units; decoder.h's DIST_EPS).
DIST_EPS = 1e-8

Fusion = tuple[nn.Linear, nn.Linear]  # (E_ref, E_mod)


def head_activation(head: nn.Module) -> int | None:
    """decoder.h's code of a head's activation, or None when ``head`` is not a head as above."""
    return _activation(_layers_of(head))


def _layers_of(head: nn.Module) -> tuple[nn.Module, ...]:
    # Iterating a Sequential reads its layers as they are; children() and indexing each cost a
    # few microseconds of Python a call, a dozen calls a step.
    return tuple(head) if isinstance(head, nn.Sequential) else ()


def _activation(layers: tuple[nn.Module, ...]) -> int | None:
    if not (3 <= len(layers) <= 4 and isinstance(layers[0], nn.Linear) and isinstance(layers[1], nn.ReLU)
            and isinstance(layers[2], nn.Linear) and layers[0].bias is not None and layers[2].bias is not None):
        return None
    return _ACTS.get(type(layers[3]) if len(layers) == 4 else None)


def fuse(feat: Tensor, ibr: Tensor | None, fusion: Fusion | None) -> Tensor:
    """``f_s + sigmoid(E_mod(f_v)) * E_ref(f_v)`` (feat (M, F), ibr (M, C)); ``feat`` without either."""
    if fusion is None or ibr is None:
        return feat
    e_ref, e_mod = fusion
    return feat + torch.sigmoid(e_mod(ibr)) * e_ref(ibr)


def decode_reference(feat: Tensor, ibr: Tensor | None, anchor: Tensor, centre: Tensor, dist_scale: float,
                     fusion: Fusion | None, heads: Sequence[nn.Module]) -> list[Tensor]:
    """:func:`decode` in torch operators (autograd, any device)."""
    view = anchor - centre
    # Summed in float64 as decoder.h does: squares of distances above ~1.8e19 overflow float32.
    dist = view.double().norm(dim=1, keepdim=True).clamp_min(DIST_EPS).to(view.dtype)
    x = torch.cat([fuse(feat, ibr, fusion), view / dist, dist / dist_scale], dim=1)
    return [h(x) for h in heads]


def decode(feat: Tensor, ibr: Tensor | None, anchor: Tensor, centre: Tensor, dist_scale: float,
           fusion: Fusion | None, heads: Sequence[nn.Module], backend: Backend | None = None) -> list[Tensor]:
    """Each head's output (M, O_h) for the visible anchors.

    Args:
        feat: (M, F) the anchors' own features; ibr: (M, C) their IBR features or None.
        anchor: (M, 3) positions and centre: (3,) the camera centre, world units.
        dist_scale: the camera distance that the decoders see as 1 (world units).
        fusion: (E_ref, E_mod) Linear(C, F) layers, or None (no IBR fusion).
        heads: decoder heads as in the module docstring, fed ``F + 4`` inputs.
        backend: the rasterizer's backend choice (None: :func:`dibrgs_core.render.get_backend`).
    """
    fusion = None if ibr is None else fusion
    node = node_parameters(heads, fusion)
    # The C++ node gives the camera centre no gradient: a centre that wants one takes the torch path.
    if (node is not None and feat.dim() == 2 and feat.dtype in (torch.float32, torch.float64)
            and not centre.requires_grad and uses_fast(backend, feat)):
        acts, params = node
        tensors = [feat, anchor, centre] + ([ibr] if fusion is not None else []) + params
        if all(t.dtype == feat.dtype for t in tensors):
            return list(_DecodeFast.apply((acts, fusion is not None, float(dist_scale)), *tensors))
    return decode_reference(feat, ibr, anchor, centre, dist_scale, fusion, heads)


def node_parameters(heads: Sequence[nn.Module], fusion: Fusion | None) -> tuple[tuple[int, ...], list[Tensor]] | None:
    """decoder.h's activation code of each head and the C++ path's parameter list (per head W1,
    b1, W2, b2, then the fusion's Wref, bref, Wmod, bmod when ``fusion`` is given); None when there
    is no head or a head is not of the module docstring's form."""
    layers = [_layers_of(h) for h in heads]
    acts = tuple(_activation(ls) for ls in layers)
    if not heads or None in acts:
        return None
    params: list[Tensor] = []
    for ls in layers:
        params += [ls[0].weight, ls[0].bias, ls[2].weight, ls[2].bias]
    if fusion is not None:
        params += [fusion[0].weight, fusion[0].bias, fusion[1].weight, fusion[1].bias]
    return acts, params  # type: ignore[return-value]


def split_parameters(params: Sequence[Tensor], n: int) -> tuple[list[Tensor], ...]:
    """W1, b1, W2, b2 of the ``n`` heads and the fusion's [Wref, bref, Wmod, bmod] (or []) from
    :func:`node_parameters`' list."""
    return (*(list(params[i:4 * n:4]) for i in range(4)), list(params[4 * n:]))


def node_inputs(fused: bool, n: int, rest: Sequence[Tensor], like: Tensor
                ) -> tuple[Tensor, list[Tensor], tuple[list[Tensor], ...]]:
    """A C++ decoder node's trailing inputs ``[ibr], *params`` (``n`` heads' parameters in
    :func:`node_parameters`' order) as the extension takes them: the IBR features (an empty tensor
    like ``like`` without fusion), the parameters and their :func:`split_parameters` split."""
    ibr = rest[0] if fused else like.new_empty(0)
    params = list(rest[1:] if fused else rest)
    return ibr, params, split_parameters(params, n)


def node_input_grads(fused: bool, dibr: Tensor | None, grads: Sequence[Tensor]) -> list[Tensor | None]:
    """The gradients of a node's trailing inputs ``[ibr], *params`` from ``dibr`` (None when not
    wanted) and the extension's weight gradients (the fusion's four first, then the heads')."""
    fusion_grads, head_grads = (grads[:4], grads[4:]) if fused else ([], grads)
    return [*([dibr] if fused else []), *head_grads, *fusion_grads]


class _DecodeFast(torch.autograd.Function):
    """Inputs: feat, anchor, centre, [ibr], per head W1, b1, W2, b2, [Wref, bref, Wmod, bmod]."""

    @staticmethod
    def forward(ctx, spec, feat, anchor, centre, *rest):  # type: ignore[override]
        acts, fused, dist_scale = spec
        n = len(acts)
        ibr, params, (W1, b1, W2, b2, fusion) = node_inputs(fused, n, rest, feat)
        res = fast.extension().decoder_forward(feat, ibr, fusion, anchor, centre, dist_scale, W1, b1, W2, b2,
                                               list(acts))
        outs, (x, dist, gate, ref), hidden = res[:n], res[n:n + 4], res[n + 4:]
        ctx.save_for_backward(ibr, x, dist, gate, ref, *hidden, *outs, *params)
        ctx.spec = spec
        ctx.set_materialize_grads(False)
        return tuple(outs)

    @staticmethod
    def backward(ctx, *gouts):  # type: ignore[override]
        acts, fused, dist_scale = ctx.spec
        n = len(acts)
        ibr, x, dist, gate, ref, *rest = ctx.saved_tensors
        hidden, outs, params = rest[:n], rest[n:2 * n], rest[2 * n:]
        W1, b1, W2, b2, fusion = split_parameters(params, n)
        want_dibr = fused and ctx.needs_input_grad[4]
        grads = [torch.zeros_like(o) if g is None else g for g, o in zip(gouts, outs)]
        res = fast.extension().decoder_backward(grads, ibr, fusion, x, dist, gate, ref, list(hidden), list(outs),
                                                dist_scale, W1, b1, W2, b2, list(acts), want_dibr)
        dfeat, danchor, dibr = res[:3]
        return (None, dfeat, danchor, None, *node_input_grads(fused, dibr if want_dibr else None, res[3:]))
