"""Adam whose step updates every parameter tensor in one parallel C++ loop.

torch's CPU Adam runs about ten operators per parameter tensor, one tensor after another. A
Scaffold model's optimiser holds nineteen tensors of 10 to 84,000 elements (about 200,000 in
all), so a step was about 1.1 ms of dispatch on one thread and longer on two (docs/benchmarks.md,
"Adam in one loop"). :class:`Adam` keeps torch's optimiser - its arguments, parameter groups,
state (``step``, ``exp_avg``, ``exp_avg_sq``), ``state_dict`` and checkpoints - and only replaces
the arithmetic of a step with ``adam_step`` of the rasterizer's extension (``render/csrc/adam.h``:
the same formula in float32, all chunks of all tensors one parallel loop) whenever the
rasterizer's C++ path is in use and every tensor is a plain contiguous float32 CPU tensor.
Anything else (the reference path, ``amsgrad``, ``maximize``, a tensor learning rate, another
dtype) takes torch's own step. Values agree with torch's to float32 rounding
(``tests/training/test_optim.py``). :func:`step_together` steps several such optimisers (a
method's model and its IBR projection) in one call of the extension.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Callable

import torch
from torch.optim import optimizer as _torch_optimizer

from ..render import fast, uses_fast


# Group options torch's step handles and the one loop does not.
_TORCH_ONLY = ("amsgrad", "maximize", "differentiable", "capturable", "fused")


class Adam(torch.optim.Adam):
    """:class:`torch.optim.Adam` (``decoupled_weight_decay=True`` is AdamW) with a one-loop step."""

    @torch.no_grad()
    def step(self, closure: Callable[[], Any] | None = None) -> Any:
        if closure is not None:
            return super().step(closure)
        for opt in _one_loop([self]):
            torch.optim.Adam.step(opt)
        return None


class _Tensors:
    """What one ``adam_step`` call takes, gathered from one or more optimisers."""

    def __init__(self) -> None:
        self.params: list[torch.Tensor] = []
        self.grads: list[torch.Tensor] = []
        self.exp_avgs: list[torch.Tensor] = []
        self.exp_avg_sqs: list[torch.Tensor] = []
        self.steps: list[torch.Tensor] = []
        self.hyper: list[float] = []  # six a tensor: lr, beta1, beta2, eps, weight decay, decoupled 0/1

    def add(self, opt: Adam) -> bool:
        """Appends ``opt``'s tensors that have a gradient; False, appending nothing, when a group
        needs torch's own step. A lean loop (a step of a small model is mostly this): the tensors'
        types and layouts are checked by the extension."""
        n = len(self.params)
        state = opt.state
        for group in opt.param_groups:
            if any(group[k] for k in _TORCH_ONLY) or torch.is_tensor(group["lr"]):
                self._truncate(n)
                return False
            beta1, beta2 = group["betas"]
            row = (group["lr"], float(beta1), float(beta2), group["eps"], group["weight_decay"],
                   float(bool(group.get("decoupled_weight_decay", False))))
            ps = [p for p in group["params"] if p.grad is not None]
            sts = [state.get(p) for p in ps]
            if not all(sts):  # torch's own lazy state initialisation, for the whole group
                opt._init_group(group, [], [], [], [], [], [])
                sts = [state[p] for p in ps]
            self.params += ps
            self.grads += [p.grad for p in ps]
            self.exp_avgs += [st["exp_avg"] for st in sts]
            self.exp_avg_sqs += [st["exp_avg_sq"] for st in sts]
            self.steps += [st["step"] for st in sts]
            self.hyper += row * len(ps)
        return True

    def _truncate(self, n: int) -> None:
        for lst in (self.params, self.grads, self.exp_avgs, self.exp_avg_sqs, self.steps):
            del lst[n:]
        del self.hyper[6 * n:]


def _one_loop(optimizers: Sequence[Adam]) -> list[Adam]:
    """Steps ``optimizers`` in one call of the extension where it applies; returns those left
    for torch's own step (a group option it lacks, the reference path, a tensor it declines)."""
    batch, taken, left = _Tensors(), [], []
    for opt in optimizers:
        (taken if batch.add(opt) else left).append(opt)
    if not batch.params:
        return left
    if not uses_fast(None, batch.params[0]):
        return left + taken
    if not fast.extension().adam_step(batch.params, batch.grads, batch.exp_avgs, batch.exp_avg_sqs, batch.steps,
                                      batch.hyper):
        return left + taken
    return left


@torch.no_grad()
def step_together(optimizers: Sequence[torch.optim.Optimizer]) -> None:
    """``opt.step()`` of each of ``optimizers``, the :class:`Adam` ones in one call of the
    extension (each call and the Python around it cost about as much as a small model's
    arithmetic). An optimiser of another class, or one with step hooks (its own or global),
    takes its own ``step()``, hooks included."""
    global_hooks = bool(_torch_optimizer._global_optimizer_pre_hooks or _torch_optimizer._global_optimizer_post_hooks)
    plain = [o for o in optimizers if isinstance(o, Adam) and not global_hooks
             and not o._optimizer_step_pre_hooks and not o._optimizer_step_post_hooks]
    for opt in optimizers:
        if not any(opt is o for o in plain):
            opt.step()
    for opt in _one_loop(plain):
        torch.optim.Adam.step(opt)
