"""Optimiser surgery shared by the densification strategies: replace, append or drop rows of a
model's parameters and keep the Adam moments aligned with them."""
from __future__ import annotations

from typing import Callable

import torch
from torch import nn


def swap_param(optimizer: torch.optim.Optimizer, module: nn.Module, name: str, new: torch.Tensor,
                state_fn: Callable[[torch.Tensor], torch.Tensor]) -> None:
    """Replace parameter ``name`` of ``module`` (and its optimiser group) by ``new``.

    ``state_fn`` maps each per-row optimiser moment to the new row layout.
    """
    trainable = getattr(module, name).requires_grad
    param = nn.Parameter(new.detach().contiguous(), requires_grad=trainable)
    for group in optimizer.param_groups:
        if group.get("name") != name:
            continue
        old = group["params"][0]
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key] = state_fn(state[key])
            optimizer.state[param] = state
        group["params"][0] = param
    setattr(module, name, param)


def cat_rows(optimizer: torch.optim.Optimizer, module: nn.Module, ext: dict[str, torch.Tensor]) -> None:
    """Append rows ``ext[name]`` to each named parameter; new rows get zero moments."""
    for name, rows in ext.items():
        old = getattr(module, name)
        rows = rows.to(old.dtype)
        swap_param(optimizer, module, name, torch.cat([old.detach(), rows], 0),
                    lambda s, r=rows: torch.cat([s, torch.zeros_like(r)], 0))


def keep_rows(optimizer: torch.optim.Optimizer, module: nn.Module, names: tuple[str, ...],
              keep: torch.Tensor) -> None:
    """Keep only rows where ``keep`` (bool) is True in each named parameter and its moments."""
    for name in names:
        old = getattr(module, name)
        swap_param(optimizer, module, name, old.detach()[keep], lambda s: s[keep])
