"""The densification interface both methods use (gsplat style).

A training iteration calls, in this order::

    img, _alpha, _depth, info = models.base.render_model(model, camera, background, "RGB")
    strategy.step_pre_backward(model, optimizer, step, info)
    loss.backward()
    optimizer.step(); optimizer.zero_grad()
    strategy.step_post_backward(model, optimizer, step, info)

``info`` is the render's meta dict (screen-space ``means2d`` with its gradient,
``radii``, ``width``, ``height`` and the model's own ``aux``), or ``None`` when the
iteration took no step (non-finite loss or gradients, nothing rendered): a strategy
then gathers no statistics but still runs what its schedule asks for. As in gsplat's
trainer, the post-backward hook runs after the optimiser step, so new or removed
rows never see the step of the iteration that judged them.

Strategies hold their own statistics and persist them with ``state_dict`` /
``load_state_dict``; optimiser surgery goes through :mod:`.ops`.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import torch
from torch import nn


class Strategy(ABC):
    """Densification schedule and statistics of one model.

    Attributes:
        start, until, every: growth/densification runs every ``every`` iterations
            after ``start`` and before ``until`` (for the run's report).
    """

    start: int
    until: int
    every: int

    def collects(self, step: int) -> bool:
        """Whether ``step`` gathers statistics from the screen-space means' gradient."""
        return step < self.until

    def step_pre_backward(self, model: nn.Module, optimizer: torch.optim.Optimizer, step: int,
                          info: dict[str, Any] | None) -> None:
        """Before ``loss.backward()``: keep the gradient of the screen-space means when this step
        gathers statistics from it (keeping it costs a copy of it every step)."""
        if info is not None and self.collects(step) and info["means2d"].requires_grad:
            info["means2d"].retain_grad()

    @abstractmethod
    def step_post_backward(self, model: nn.Module, optimizer: torch.optim.Optimizer, step: int,
                           info: dict[str, Any] | None) -> dict[str, int]:
        """After the optimiser step: gather statistics from ``info`` and grow / prune.

        Returns counts of what changed at this step (empty when nothing ran).
        """

    @abstractmethod
    def state_dict(self) -> dict[str, torch.Tensor]:
        ...

    @abstractmethod
    def load_state_dict(self, d: dict[str, torch.Tensor]) -> None:
        ...
