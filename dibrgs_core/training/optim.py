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
(``tests/training/test_optim.py``).
"""
from __future__ import annotations

from typing import Any, Callable

import torch

from ..render import uses_fast


# Group options torch's step handles and the one loop does not.
_TORCH_ONLY = ("amsgrad", "maximize", "differentiable", "capturable", "fused")


class Adam(torch.optim.Adam):
    """:class:`torch.optim.Adam` (``decoupled_weight_decay=True`` is AdamW) with a one-loop step."""

    @torch.no_grad()
    def step(self, closure: Callable[[], Any] | None = None) -> Any:
        if closure is not None:
            return super().step(closure)
        params: list[torch.Tensor] = []
        grads: list[torch.Tensor] = []
        exp_avgs: list[torch.Tensor] = []
        exp_avg_sqs: list[torch.Tensor] = []
        steps: list[torch.Tensor] = []
        hyper: list[tuple[float, ...]] = []
        state = self.state
        # A lean gather (a step of a small model is mostly this loop): the tensors' types and
        # layouts are checked by the extension, which changes nothing and returns False when one
        # is not plain float32 CPU data.
        for group in self.param_groups:
            if any(group[k] for k in _TORCH_ONLY) or torch.is_tensor(group["lr"]):
                return super().step()
            beta1, beta2 = group["betas"]
            row = (group["lr"], float(beta1), float(beta2), group["eps"], group["weight_decay"],
                   float(bool(group.get("decoupled_weight_decay", False))))
            for p in group["params"]:
                g = p.grad
                if g is None:
                    continue
                st = state.get(p)
                if not st:  # torch's own lazy state initialisation, for the whole group
                    self._init_group(group, [], [], [], [], [], [])
                    st = state[p]
                params.append(p)
                grads.append(g)
                exp_avgs.append(st["exp_avg"])
                exp_avg_sqs.append(st["exp_avg_sq"])
                steps.append(st["step"])
                hyper.append(row)
        if not params:
            return None
        if not uses_fast(None, params[0]):
            return super().step()
        from ..render.fast import extension

        if not extension().adam_step(params, grads, exp_avgs, exp_avg_sqs, steps,
                                     torch.tensor(hyper, dtype=torch.float64)):
            return super().step()
        return None
