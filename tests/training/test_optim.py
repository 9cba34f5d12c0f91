"""The one-loop Adam step (training/optim.py, render/csrc/adam.h) against torch's own Adam."""
from __future__ import annotations

import pytest
import torch
from threads import torch_threads

from dibrgs_core import render
from dibrgs_core.training.optim import Adam, step_together

# A Scaffold model's tensors in miniature: offsets, features, scalings, MLP weights and biases.
SHAPES = [(301, 10, 3), (301, 32), (301, 6), (32, 36), (32,), (10, 32), (10,), (1,)]
# Ten times the anchors: about 208,000 elements, as in a real step, above chunks.h's SERIAL_BELOW.
LARGE = [(3001, 10, 3), (3001, 32), (3001, 6), (32, 36), (32,), (70, 32), (70,), (1,)]


def pair(shapes=SHAPES, **kw):
    """The same parameters twice, one group each (its own learning rate), under torch's Adam and ours."""
    torch.manual_seed(0)
    base = [torch.randn(s) for s in shapes]
    out = []
    for cls in (torch.optim.Adam, Adam):
        ps = [b.clone().requires_grad_() for b in base]
        groups = [{"params": [p], "lr": 1e-3 * (i + 1)} for i, p in enumerate(ps)]
        out.append((ps, cls(groups, lr=0.0, eps=1e-15, **kw)))
    return out


def run(steps: int, pairs, skip_every: int = 0, shapes=SHAPES) -> None:
    gen = torch.Generator().manual_seed(1)
    for it in range(steps):
        # Gradients over six orders of magnitude, and now and then a parameter without one.
        grads = [torch.randn(s, generator=gen) * 10.0 ** (it % 6 - 3) for s in shapes]
        for ps, opt in pairs:
            for i, (p, g) in enumerate(zip(ps, grads)):
                p.grad = None if skip_every and (it + i) % skip_every == 0 else g.clone()
            opt.step()


@pytest.mark.parametrize("kw", [{}, {"weight_decay": 0.01, "decoupled_weight_decay": True},
                                {"weight_decay": 0.01}, {"betas": (0.5, 0.9)}],
                         ids=["adam", "adamw", "l2", "betas"])
def test_the_one_loop_step_follows_torch(kw):
    (a, ta), (b, ours) = pair(**kw)
    run(40, [(a, ta), (b, ours)], skip_every=7)
    for p, q in zip(a, b):
        assert torch.allclose(p, q, rtol=1e-5, atol=1e-6), float((p - q).abs().max())
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.allclose(ta.state[p][key], ours.state[q][key], rtol=1e-5, atol=1e-12)
        assert float(ta.state[p]["step"]) == float(ours.state[q]["step"])
    # Same state layout: torch's Adam continues from ours and ours from torch's.
    ta.load_state_dict(ours.state_dict())


def test_the_step_split_over_two_threads_follows_torch():
    """Above SERIAL_BELOW elements the step runs as one equal run of elements a thread, cutting a
    tensor anywhere (csrc/chunks.h): the same values as torch's step on both sides of the cut."""
    (a, ta), (b, ours) = pair(LARGE)
    with torch_threads(2):
        run(12, [(a, ta), (b, ours)], skip_every=5, shapes=LARGE)
    for p, q in zip(a, b):
        assert torch.allclose(p, q, rtol=1e-5, atol=1e-6), float((p - q).abs().max())
        assert torch.allclose(ta.state[p]["exp_avg"], ours.state[q]["exp_avg"], rtol=1e-5, atol=1e-12)


def spy_on_adam_step(monkeypatch) -> list[int]:
    """The real extension behind a spy: the list it returns gets each adam_step call's tensor count."""
    from dibrgs_core.render import fast

    ext = fast.extension()
    calls: list[int] = []

    class Spy:
        def __getattr__(self, name):
            return getattr(ext, name)

        def adam_step(self, *args):
            calls.append(len(args[0]))
            return ext.adam_step(*args)

    monkeypatch.setattr(fast, "extension", lambda: Spy())
    return calls


def test_the_step_runs_in_the_extension_when_the_rasterizer_does(monkeypatch):
    """With the reference path torch's step runs; both give the same values. A spy on the real
    extension counts its calls."""
    (a, ta), (b, ours) = pair()
    calls = spy_on_adam_step(monkeypatch)
    run(3, [(b, ours)])
    assert calls == [len(SHAPES)] * 3
    render.set_backend("reference")
    try:
        run(3, [(b, ours)])
    finally:
        render.set_backend(None)
    assert len(calls) == 3
    run(3, [(a, ta)])
    run(3, [(a, ta)])
    for p, q in zip(a, b):
        assert torch.allclose(p, q, rtol=1e-5, atol=1e-6)


def test_a_group_whose_tensors_get_gradients_at_different_steps_follows_torch():
    """Several tensors a group (the decoders' layers), some without a gradient at first: the state
    is made for the whole group when one needs it, and a tensor without a gradient is left as it is."""
    torch.manual_seed(2)
    base = [torch.randn(s) for s in SHAPES[3:7]]
    pairs = []
    for cls in (torch.optim.Adam, Adam):
        ps = [b.clone().requires_grad_() for b in base]
        pairs.append((ps, cls([{"params": ps[:3], "lr": 1e-2}, {"params": ps[3:], "lr": 3e-3}], lr=0.0)))
    gen = torch.Generator().manual_seed(5)
    for it in range(6):
        grads = [torch.randn(b.shape, generator=gen) for b in base]
        for ps, opt in pairs:
            for i, (p, g) in enumerate(zip(ps, grads)):
                p.grad = g.clone() if it >= 2 or i != 1 else None  # the second tensor waits two steps
            opt.step()
    (a, ta), (b, ours) = pairs
    for p, q in zip(a, b):
        assert torch.allclose(p, q, rtol=1e-5, atol=1e-6)
        assert float(ta.state[p]["step"]) == float(ours.state[q]["step"])
    assert float(ours.state[b[1]]["step"]) == 4.0 and float(ours.state[b[0]]["step"]) == 6.0


def test_other_dtypes_and_non_contiguous_tensors_take_torchs_step():
    p64 = torch.randn(5, dtype=torch.float64, requires_grad=True)
    pt = torch.randn(4, 3).t().contiguous().t().requires_grad_()  # non-contiguous
    ref64, reft = p64.detach().clone().requires_grad_(), pt.detach().clone().requires_grad_()
    ours, theirs = Adam([p64, pt], lr=0.1), torch.optim.Adam([ref64, reft], lr=0.1)
    for _ in range(3):
        for x in (p64, ref64):
            x.grad = torch.ones_like(x)
        for x in (pt, reft):
            x.grad = torch.ones_like(x)
        ours.step()
        theirs.step()
    assert torch.equal(p64, ref64) and torch.equal(pt, reft)


def test_a_step_bumps_the_parameters_version_as_torchs_does():
    """Caches keyed on a parameter's version (the IBR features) must see the update."""
    (a, ta), (b, ours) = pair()
    before = [p._version for p in b]
    run(1, [(b, ours)])
    assert all(p._version > v for p, v in zip(b, before))


def test_optimisers_step_together_in_one_call_as_each_alone(monkeypatch):
    """A model's Adam and an AdamW (the IBR projection's) stepped together: one extension call,
    the values of each stepping alone; an optimiser with a step hook takes its own step, hook
    included, and one of another class its own."""

    def make():
        torch.manual_seed(0)
        a = [torch.randn(s).requires_grad_() for s in SHAPES[:4]]
        b = [torch.randn(s).requires_grad_() for s in SHAPES[4:]]
        c = [torch.randn(3).requires_grad_()]
        return (a, Adam(a, lr=1e-2)), (b, Adam(b, lr=3e-3, weight_decay=0.01, decoupled_weight_decay=True)), \
            (c, torch.optim.SGD(c, lr=0.1))

    def grads(groups, it):
        gen = torch.Generator().manual_seed(it)
        for ps, _ in groups:
            for p in ps:
                p.grad = torch.randn(p.shape, generator=gen)

    alone, together = make(), make()
    calls = spy_on_adam_step(monkeypatch)
    for it in range(5):
        grads(alone, it)
        grads(together, it)
        for _, opt in alone:
            opt.step()
        step_together([opt for _, opt in together])
    assert calls == [4, 4, 8] * 5  # each alone, then both in one call
    for (pa, _), (pb, _) in zip(alone, together):
        for p, q in zip(pa, pb):
            assert torch.equal(p, q)
    seen = []
    together[1][1].register_step_pre_hook(lambda opt, args, kwargs: seen.append(opt))
    grads(together, 9)
    calls.clear()
    step_together([opt for _, opt in together])
    assert seen == [together[1][1]] and calls == [4, 4]


def test_a_group_option_the_loop_lacks_and_a_closure_take_torchs_step(monkeypatch):
    """An optimiser with an ``amsgrad`` group steps wholly by torch's Adam (none of its tensors in
    the extension's call, the other optimiser's still there), and a step with a closure returns
    the closure's loss: the values of torch's Adam either way."""

    def make(cls):
        torch.manual_seed(3)
        a = [torch.randn(s).requires_grad_() for s in SHAPES[:3]]
        b = [torch.randn(s).requires_grad_() for s in SHAPES[3:]]
        return a, cls([{"params": a[:1], "lr": 1e-2}, {"params": a[1:], "lr": 2e-2, "amsgrad": True}], lr=0.0), \
            b, cls(b, lr=3e-3)

    ta, topt_a, tb, topt_b = make(torch.optim.Adam)
    oa, oopt_a, ob, oopt_b = make(Adam)
    calls = spy_on_adam_step(monkeypatch)
    for it in range(4):
        gen = torch.Generator().manual_seed(it)
        grads = [torch.randn(p.shape, generator=gen) for p in ta + tb]
        for ps in (ta + tb, oa + ob):
            for p, g in zip(ps, grads):
                p.grad = g.clone()
        topt_a.step()
        topt_b.step()
        step_together([oopt_a, oopt_b])
    assert calls == [len(ob)] * 4  # the amsgrad optimiser never in the one loop
    for p, q in zip(ta + tb, oa + ob):
        assert torch.allclose(p, q, rtol=1e-5, atol=1e-6), float((p - q).abs().max())
    assert "max_exp_avg_sq" in oopt_a.state[oa[1]]

    def closure(ps):
        def f():
            for p in ps:
                p.grad = torch.full_like(p, 0.5)
            return torch.tensor(7.0)
        return f

    assert float(topt_b.step(closure(tb))) == 7.0 and float(oopt_b.step(closure(ob))) == 7.0
    for p, q in zip(tb, ob):
        assert torch.allclose(p, q, rtol=1e-5, atol=1e-6)
