"""The visible anchors' neural Gaussians in one C++ node against the three nodes it replaces."""
from __future__ import annotations

import pytest
import torch
from threads import torch_threads
from torch import nn

from dibrgs_core.models.decoder import decode
from dibrgs_core.models.scaffold import _mlp
from dibrgs_core.models.spawn import spawn, take_rows, true_indices
from dibrgs_core.models.visible import decode_visible

F, C, H, K = 8, 6, 8, 4


def _model(N: int, dtype: torch.dtype, seed: int = 0):
    torch.manual_seed(seed)
    heads = [_mlp(F + 4, H, K, nn.Tanh()), _mlp(F + 4, H, 7 * K, None), _mlp(F + 4, H, 3 * K, nn.Sigmoid())]
    fusion = (nn.Linear(C, F), nn.Linear(C, F))
    for m in heads + list(fusion):
        m.to(dtype)
    g = torch.Generator().manual_seed(seed + 1)
    anchor = torch.randn(N, 3, generator=g, dtype=dtype) * 30.0 + 100.0
    feat = torch.randn(N, F, generator=g, dtype=dtype)
    scaling = torch.randn(N, 6, generator=g, dtype=dtype) - 2.0
    offset = torch.randn(N, K, 3, generator=g, dtype=dtype)
    visible = torch.rand(N, generator=g) < 0.7
    ibr = torch.randn(int(visible.sum()), C, generator=g, dtype=dtype)
    return heads, fusion, [anchor, feat, scaling, offset], visible, ibr


def _run(fused_node: bool, heads, fusion, tensors, visible, ibr, anchor_grad: bool, with_fusion: bool):
    tensors = [t.detach().clone().requires_grad_(i > 0 or anchor_grad) for i, t in enumerate(tensors)]
    ibr = ibr.detach().clone().requires_grad_() if with_fusion else None
    weights = [p for m in heads + list(fusion) for p in m.parameters()]
    for p in weights:
        p.grad = None
    centre = torch.tensor([90.0, 110.0, 20.0], dtype=tensors[0].dtype)
    idx = true_indices(visible)
    fus = fusion if with_fusion else None
    if fused_node:
        fused = decode_visible(*tensors, idx, ibr, centre, 80.0, fus, heads)
        assert fused is not None
        g, nop = fused
        assert type(g.means.grad_fn).__name__ == "_VisibleFastBackward"
    else:
        anchor, feat, log_s, offset = take_rows(tensors, idx)
        opacity, cov, color = decode(feat, ibr, anchor, centre, 80.0, fus, heads)
        g = spawn(opacity, color, cov, anchor, log_s, offset)
        nop = opacity.reshape(-1)
    outs = [g.means, g.quats, g.scales, g.opacities, g.colors]
    gen = torch.Generator().manual_seed(7)
    sum((torch.randn(o.shape, generator=gen, dtype=o.dtype) * o).sum() for o in outs).backward()
    grads = [None if t is None or t.grad is None else t.grad.clone() for t in tensors + [ibr] + weights]
    return [o.detach() for o in outs] + [g.selected, nop.detach()], grads


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("with_fusion", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("N", [0, 9, 1500])
def test_one_node_gives_the_three_nodes_bits(threads, with_fusion, dtype, N):
    """Gaussians, kept rows, neural opacities and every gradient (the anchors' too, when they want
    one) equal the take_rows -> decoder -> spawn nodes' bit for bit; 1,500 anchors (about 1,050
    visible) split into blocks on two threads, 9 stay one block, 0 visible spawns nothing."""
    heads, fusion, tensors, visible, ibr = _model(N, dtype)
    if N == 0:
        visible, ibr = torch.zeros(0, dtype=torch.bool), ibr[:0]
    with torch_threads(threads):
        for anchor_grad in (False, True):
            a_out, a_grads = _run(True, heads, fusion, tensors, visible, ibr, anchor_grad, with_fusion)
            b_out, b_grads = _run(False, heads, fusion, tensors, visible, ibr, anchor_grad, with_fusion)
            for i, (a, b) in enumerate(zip(a_out, b_out)):
                assert a.shape == b.shape and torch.equal(a, b), i
            for i, (a, b) in enumerate(zip(a_grads, b_grads)):
                assert (a is None) == (b is None), i
                assert a is None or torch.equal(a, b), i
            assert (a_grads[0] is not None) is anchor_grad
    if N > 100:
        assert 0 < int(a_out[5].sum()) < a_out[5].numel()  # some rows kept, some not


def test_falls_back_where_the_c_path_does_not_apply():
    """A head not of the decoder's form, a centre that wants a gradient or mixed dtypes: None (the
    caller takes the three steps)."""
    heads, fusion, tensors, visible, ibr = _model(20, torch.float32)
    idx = true_indices(visible)
    centre = torch.tensor([90.0, 110.0, 20.0])
    assert decode_visible(*tensors, idx, ibr, centre, 80.0, fusion, heads) is not None
    odd = [nn.Sequential(nn.Linear(F + 4, K)), heads[1], heads[2]]
    assert decode_visible(*tensors, idx, ibr, centre, 80.0, fusion, odd) is None
    assert decode_visible(*tensors, idx, ibr, centre.clone().requires_grad_(), 80.0, fusion, heads) is None
    assert decode_visible(tensors[0].double(), *tensors[1:], idx, ibr, centre, 80.0, fusion, heads) is None


def test_model_decode_takes_one_node_and_keeps_the_strategy_inputs():
    """NeuralGaussians.decode on the C++ path: one node from the Gaussians back to the anchors'
    parameters, neural opacities of every visible anchor's offsets outside the graph."""
    from dibrgs_core.models.config import ModelConfig
    from dibrgs_core.models.scaffold import NeuralGaussians

    g = torch.Generator().manual_seed(3)
    model = NeuralGaussians(torch.rand(300, 3, generator=g) * 10.0, 0.5, 20.0, ModelConfig(), use_ibr=False)
    K_ = torch.tensor([[100.0, 0.0, 64.0], [0.0, 100.0, 48.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    w2c[2, 3] = 25.0
    d = model.decode(K_, w2c, torch.tensor([0.0, 0.0, -25.0]), 128, 96)
    assert type(d.means.grad_fn).__name__ == "_VisibleFastBackward"
    assert d.neural_opacity.shape == (d.anchor_index.numel() * model.n_offsets,)
    assert not d.neural_opacity.requires_grad
    assert int(d.selected.sum()) == d.means.shape[0]
    d.means.sum().backward()
    assert model.offset.grad is not None and model.anchor_feat.grad is not None
