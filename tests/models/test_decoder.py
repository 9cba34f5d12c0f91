"""The decoder of the neural Gaussians (IBR fusion, input, MLP heads): the C++ pass against torch."""
from __future__ import annotations

import pytest
import torch
from threads import torch_threads
from torch import nn

from dibrgs_core.models.decoder import decode, decode_reference, head_activation
from dibrgs_core.models.scaffold import _mlp

F, C, H, K = 8, 6, 8, 3


def _layers(dtype: torch.dtype, seed: int = 0) -> tuple[list[nn.Module], tuple[nn.Linear, nn.Linear]]:
    torch.manual_seed(seed)
    heads = [_mlp(F + 4, H, K, nn.Tanh()), _mlp(F + 4, H, 7 * K, None), _mlp(F + 4, H, 3 * K, nn.Sigmoid())]
    fusion = (nn.Linear(C, F), nn.Linear(C, F))
    for m in heads + list(fusion):
        m.to(dtype)
    return heads, fusion


def _inputs(M: int, dtype: torch.dtype, seed: int = 1) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    feat = torch.randn(M, F, generator=g, dtype=dtype)
    ibr = torch.randn(M, C, generator=g, dtype=dtype)
    anchor = torch.randn(M, 3, generator=g, dtype=dtype) * 30.0 + 100.0
    return [t.requires_grad_() for t in (feat, ibr, anchor)]


def _run(backend: str, feat, ibr, anchor, centre, heads, fusion, weights):
    for p in weights:
        p.grad = None
    outs = decode(feat, ibr, anchor, centre, 80.0, fusion, heads, backend)
    node = type(outs[0].grad_fn).__name__
    assert (node == "_DecodeFastBackward") is (backend == "fast"), node  # the path asked for ran
    g = torch.Generator().manual_seed(7)
    sum((torch.randn(o.shape, generator=g, dtype=o.dtype) * o).sum() for o in outs).backward()
    grads = [None if t is None or t.grad is None else t.grad.clone() for t in [feat, ibr, anchor] + weights]
    for t in (feat, ibr, anchor):
        if t is not None:
            t.grad = None
    return [o.detach() for o in outs], grads


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("M", [0, 5, 700])
def test_fast_matches_torch(threads, fused, M):
    """Outputs and every gradient; 700 rows split into blocks on two threads, 5 stay one block."""
    heads, fusion = _layers(torch.float32)
    weights = [p for m in heads + list(fusion) for p in m.parameters()]
    feat, ibr, anchor = _inputs(M, torch.float32)
    centre = torch.tensor([90.0, 110.0, 20.0])
    if M > 2:
        with torch.no_grad():
            anchor[2] = centre  # at the camera: the clamped distance
    with torch_threads(threads):
        args = (feat, ibr if fused else None, anchor, centre, heads, fusion if fused else None, weights)
        fast, ref = _run("fast", *args), _run("reference", *args)
    for a, b in zip(fast[0], ref[0]):
        assert a.shape == b.shape == (M, a.shape[1])
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(fast[1], ref[1]):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    assert (fast[1][1] is None) == (not fused)  # the IBR features get a gradient only through the fusion
    if M:
        assert all(torch.isfinite(g).all() for g in fast[1] if g is not None)
        assert float(fast[1][2].abs().sum()) > 0


def _mkl_max_threads():
    """MKL's thread count for the calling thread, read through torch's own MKL (None without one)."""
    import ctypes
    from pathlib import Path

    lib = Path(torch.__file__).parent / "lib" / "libtorch_cpu.so"
    try:
        fn = ctypes.CDLL(str(lib)).MKL_Get_Max_Threads
    except (OSError, AttributeError):
        return None
    fn.restype = ctypes.c_int
    return fn


def test_blocks_give_back_mkls_thread_count():
    """The blocks run MKL on one thread each (csrc/decoder.h SerialMkl) and then restore MKL's count:
    products the calling thread runs afterwards still have both threads."""
    get = _mkl_max_threads()
    if get is None:
        pytest.skip("this torch has no MKL")
    heads, fusion = _layers(torch.float32)
    weights = [p for m in heads + list(fusion) for p in m.parameters()]
    feat, ibr, anchor = _inputs(700, torch.float32)
    with torch_threads(2):
        before = get()
        _run("fast", feat, ibr, anchor, torch.tensor([90.0, 110.0, 20.0]), heads, fusion, weights)
        after = get()
    assert before == after == 2


def test_fast_gradients_against_finite_differences():
    heads, fusion = _layers(torch.float64, seed=3)
    feat, ibr, anchor = _inputs(4, torch.float64, seed=4)
    centre = torch.tensor([95.0, 105.0, 30.0], dtype=torch.float64)
    params = [p for m in heads + list(fusion) for p in m.parameters()]

    def f(feat, ibr, anchor, *_params):
        return tuple(decode(feat, ibr, anchor, centre, 50.0, fusion, heads, "fast"))

    torch.autograd.gradcheck(f, (feat, ibr, anchor, *params))


def test_other_modules_and_a_centre_with_gradient_use_torch():
    """A head that is not Linear-ReLU-Linear(-Tanh|Sigmoid) runs as its own module on any backend, and a
    camera centre that wants a gradient gets it (the C++ node gives it none)."""
    heads, fusion = _layers(torch.float32)
    odd = nn.Sequential(nn.Linear(F + 4, H), nn.GELU(), nn.Linear(H, 2))
    assert head_activation(odd) is None and [head_activation(h) for h in heads] == [1, 0, 2]
    feat, ibr, anchor = _inputs(10, torch.float32)
    centre = torch.zeros(3)
    out = decode(feat, ibr, anchor, centre, 80.0, fusion, heads + [odd], "fast")
    ref = decode_reference(feat, ibr, anchor, centre, 80.0, fusion, heads + [odd])
    assert out[-1].grad_fn is not None and "Addmm" in type(out[-1].grad_fn).__name__
    for a, b in zip(out, ref):
        torch.testing.assert_close(a, b)
    centre = torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
    outs = decode(feat, ibr, anchor, centre, 80.0, fusion, heads, "fast")
    sum(o.sum() for o in outs).backward()
    assert centre.grad is not None and float(centre.grad.abs().sum()) > 0


@pytest.mark.parametrize("backend", ["fast", "reference"])
@pytest.mark.parametrize("scale", [1e-30, 1e25])
def test_finite_at_extreme_distances(scale, backend):
    """Camera distances whose squares leave float32 (1e25: 1e50) or fall below the clamp (1e-30):
    the distance is summed in float64, outputs and gradients stay finite."""
    heads, fusion = _layers(torch.float32)
    feat, ibr, _ = _inputs(300, torch.float32)
    g = torch.Generator().manual_seed(5)
    anchor = (torch.randn(300, 3, generator=g) * scale).requires_grad_()
    outs = decode(feat, ibr, anchor, torch.zeros(3), max(scale, 1e-6), fusion, heads, backend)
    sum(o.sum() for o in outs).backward()
    assert all(torch.isfinite(o).all() for o in outs)
    for t in [feat, ibr, anchor] + [p for m in heads + list(fusion) for p in m.parameters()]:
        assert t.grad is not None and torch.isfinite(t.grad).all()
