"""How each method optimises its model: optimisers and learning-rate schedules, the regulariser,
the densification strategy, and what the model file keeps beside the model.

The trainer sees one :class:`TrainingMethod`; which one is built (and how the model is
initialised from the scene) is decided in :mod:`.setup`.
"""
from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from typing import Any

import torch

from ..common.report import Report
from ..models.base import CameraTensors
from ..models.gs3d import Gaussians3D
from ..models.scaffold import NeuralGaussians
from ..strategy.anchor import AnchorStrategy, HeightBound
from ..strategy.base import Strategy
from ..strategy.densify import DensifyStrategy
from .appearance import ColourTransforms
from .config import GS3DConfig, TrainConfig, expon_lr
from .losses import mean_volume
from .optim import Adam, step_together

log = logging.getLogger("dibrgs.train")


class TrainingFailed(RuntimeError):
    """Training cannot continue (e.g. every anchor was pruned); the message says why."""


class TrainingMethod(ABC):
    """A model with its optimiser(s), schedule and densification strategy, and optionally the
    training views' colour transforms (:mod:`.appearance`, their own Adam)."""

    model: Any
    optimizer: torch.optim.Optimizer
    strategy: Strategy

    def __init__(self, cfg: TrainConfig, colour: ColourTransforms | None = None) -> None:
        self.cfg = cfg
        self.colour = colour
        self.colour_optimizer = (Adam(colour.parameters(), lr=cfg.colour.lr[0])
                                 if colour is not None else None)

    @abstractmethod
    def set_lr(self, it: int) -> None:
        """Learning rates of iteration ``it``."""

    def regulariser(self, info: dict[str, Any] | None, weight: float = 1.0) -> torch.Tensor:
        """The method's regularisation term for this view times ``weight`` (0 by default)."""
        return torch.zeros(())

    def as_photographed(self, img: torch.Tensor, cam: CameraTensors) -> tuple[torch.Tensor, torch.Tensor]:
        """The render ``img`` of ``cam`` through its training view's colour transform, and the
        weighted penalty of that transform (the render and 0 without transforms)."""
        if self.colour is None:
            return img, torch.zeros(())
        out, penalty = self.colour.apply(img, cam)
        return out, self.cfg.colour.weight * penalty

    def parameters(self) -> list[torch.Tensor]:
        # From the optimisers' groups: the colour module's own walk (nn.Module.parameters) cost
        # about 10 us, three times a step.
        opts = [self.optimizer] + ([self.colour_optimizer] if self.colour_optimizer is not None else [])
        return [p for o in opts for g in o.param_groups for p in g["params"]]

    def zero_grad(self) -> None:
        """Every optimised tensor's gradient to None (the optimisers' ``zero_grad(set_to_none=True)``,
        without their profiler scopes: one loop for all of them)."""
        for p in self.parameters():
            p.grad = None

    def step(self, it: int) -> None:
        """The optimisers' step of iteration ``it``, together (:func:`.optim.step_together`)."""
        step_together(self.stepping(it))

    def stepping(self, it: int) -> list[torch.optim.Optimizer]:
        """The optimisers that step at iteration ``it``: the model's, and the colour transforms'
        from their start (their learning rate of ``it`` set here)."""
        opts = [self.optimizer]
        if self.colour_optimizer is not None and it >= self.cfg.it(self.cfg.colour.start):
            for g in self.colour_optimizer.param_groups:
                g["lr"] = expon_lr(it, self.cfg.iterations, *self.cfg.colour.lr)
            opts.append(self.colour_optimizer)
        return opts

    def after_step(self, it: int, changes: dict[str, int], report: Report) -> None:
        """After the strategy's post-backward hook (``changes``: what it did this step)."""

    def report_colour(self, it: int, report: Report) -> None:
        """At the last iteration, the learned colour transforms into the report."""
        if self.colour is not None and it == self.cfg.iterations:
            report.values["colour_transforms"] = self.colour.summary()

    def state(self) -> dict[str, Any]:
        st = {"model": self.model.state(), "optimizer": self.optimizer.state_dict(),
              "strategy": self.strategy.state_dict()}
        if self.colour is not None:
            st["colour"] = {"params": self.colour.state_dict(), "optimizer": self.colour_optimizer.state_dict()}
        return st

    def load(self, st: dict[str, Any]) -> None:
        """Optimiser and strategy state from :meth:`state` (the model is rebuilt by the setup)."""
        self.optimizer.load_state_dict(st["optimizer"])
        self.strategy.load_state_dict(st["strategy"])
        if self.colour is not None and st.get("colour") is not None:
            self.colour.load_state_dict(st["colour"]["params"])
            self.colour_optimizer.load_state_dict(st["colour"]["optimizer"])

    def model_file_extras(self) -> dict[str, Any]:
        """What the trained model file keeps beside ``model.state()``."""
        return {}


class ScaffoldTraining(TrainingMethod):
    """Neural Gaussians + IBR features + anchor growth with the height veto (the paper's method).

    Learning rates are Scaffold-GS's with their exponential decays; the IBR projection P
    has its own AdamW and is frozen after ``lr.projection_freeze`` of training. Anchor
    positions are not optimised (Scaffold-GS: lr 0). Regulariser: the mean volume
    ``prod(scales)`` of the rasterized neural Gaussians, in the paper's units (scales
    divided by the model's ``paper_unit``, scene units per LEVIR-NVS unit), so that it
    weighs the same whatever the scene's units (unnormalised, a scene in units 10x
    larger had a regulariser 1,000x stronger and trained 4 dB worse).
    """

    def __init__(self, model: NeuralGaussians, cfg: TrainConfig, ibr: Any | None,
                 height_map: HeightBound | None, colour: ColourTransforms | None = None) -> None:
        super().__init__(cfg, colour)
        self.model = model
        self.ibr = ibr
        model.set_ibr(ibr)
        self.strategy = AnchorStrategy(model, cfg.growth, cfg.iterations, height_map)
        lr = cfg.lr
        groups = [
            {"params": [model.offset], "lr": lr.offset[0], "name": "offset"},
            {"params": [model.anchor_feat], "lr": lr.anchor_feat, "name": "anchor_feat"},
            {"params": [model.scaling], "lr": lr.scaling, "name": "scaling"},
        ]
        for name, params in model.mlp_parameters().items():
            groups.append({"params": params, "lr": getattr(lr, name)[0], "name": name})
        model.anchor.requires_grad_(False)
        self.optimizer = Adam(groups, lr=0.0, eps=1e-15)
        self.p_params = list(ibr.projection_parameters()) if ibr is not None else []
        # AdamW with torch's default decay (0.01).
        self.p_optimizer = (Adam(self.p_params, lr=lr.projection, weight_decay=0.01, decoupled_weight_decay=True)
                            if self.p_params else None)
        self.p_freeze_at = cfg.it(lr.projection_freeze)

    def set_lr(self, it: int) -> None:
        for g in self.optimizer.param_groups:
            sched = getattr(self.cfg.lr, g["name"])
            if isinstance(sched, tuple):
                g["lr"] = expon_lr(it, self.cfg.iterations, *sched)

    def regulariser(self, info: dict[str, Any] | None, weight: float = 1.0) -> torch.Tensor:
        if info is None:
            return torch.zeros(())
        return mean_volume(info["gaussians"].scales, self.model.paper_unit, weight)

    def parameters(self) -> list[torch.Tensor]:
        return super().parameters() + self.p_params

    def stepping(self, it: int) -> list[torch.optim.Optimizer]:
        """The base's optimisers and, until it freezes, the IBR projection's."""
        opts = super().stepping(it)
        if self.p_optimizer is not None and it <= self.p_freeze_at:
            opts.append(self.p_optimizer)
        return opts

    def step(self, it: int) -> None:
        super().step(it)
        if self.p_optimizer is not None and it == self.p_freeze_at:
            for p in self.p_params:
                p.requires_grad_(False)
            log.info("IBR projection P frozen at iteration %d", it)

    def after_step(self, it: int, changes: dict[str, int], report: Report) -> None:
        self.report_colour(it, report)
        if not changes:
            return
        growth = report.values.setdefault("growth", {"added": 0, "vetoed": 0, "pruned": 0})
        for k, v in changes.items():
            growth[k] += v
        growth["left_out_by_max_anchors"] = self.strategy.capped
        if self.model.num_anchors == 0:
            raise TrainingFailed(
                f"every anchor was pruned at iteration {it} (opacity stayed below "
                f"{self.cfg.growth.min_opacity} per visit); check the images and learning rates")

    def state(self) -> dict[str, Any]:
        return {**super().state(),
                "p_optimizer": None if self.p_optimizer is None else self.p_optimizer.state_dict(),
                "ibr": None if self.ibr is None else self.ibr.state_dict(),
                "p_frozen": bool(self.p_params) and not self.p_params[0].requires_grad}

    def load(self, st: dict[str, Any]) -> None:
        super().load(st)
        if self.p_optimizer is not None and st["p_optimizer"] is not None:
            self.p_optimizer.load_state_dict(st["p_optimizer"])
        if self.ibr is not None and st["ibr"] is not None:
            self.ibr.load_state_dict(st["ibr"])
        if st.get("p_frozen"):
            for p in self.p_params:
                p.requires_grad_(False)

    @torch.no_grad()
    def model_file_extras(self) -> dict[str, Any]:
        """The per-anchor IBR features, frozen, so rendering needs no encoder."""
        return {"ibr_feats": None if self.ibr is None else self.ibr(self.model.anchor.detach())}


def gs3d_optimizer(model: Gaussians3D, cfg: GS3DConfig, extent: float) -> Adam:
    """3DGS's Adam groups (position learning rate scaled by the scene extent)."""
    groups = [
        {"params": [model.means], "lr": cfg.position_lr[0] * extent, "name": "means"},
        {"params": [model.sh_dc], "lr": cfg.feature_lr, "name": "sh_dc"},
        {"params": [model.sh_rest], "lr": cfg.feature_lr / 20.0, "name": "sh_rest"},
        {"params": [model.opacity], "lr": cfg.opacity_lr, "name": "opacity"},
        {"params": [model.log_scales], "lr": cfg.scaling_lr, "name": "log_scales"},
        {"params": [model.quats], "lr": cfg.rotation_lr, "name": "quats"},
    ]
    return Adam(groups, lr=0.0, eps=1e-15)


class GS3DTraining(TrainingMethod):
    """Vanilla 3DGS: position learning rate 1.6e-4 -> 1.6e-6 x extent, the SH degree rising by one
    every ``sh_every`` of training, clone/split/prune with opacity resets (at least
    ``min_reset_every`` iterations apart); no regulariser."""

    def __init__(self, model: Gaussians3D, cfg: TrainConfig, extent: float,
                 colour: ColourTransforms | None = None) -> None:
        super().__init__(cfg, colour)
        self.model = model
        self.extent = extent
        self.optimizer = gs3d_optimizer(model, cfg.gs3d, extent)
        self.strategy = DensifyStrategy(model, cfg.gs3d, cfg.iterations, extent)
        self.sh_every = max(1, round(cfg.gs3d.sh_every * cfg.iterations))

    def set_lr(self, it: int) -> None:
        init, final = self.cfg.gs3d.position_lr
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = expon_lr(it, self.cfg.iterations, init * self.extent, final * self.extent)

    def after_step(self, it: int, changes: dict[str, int], report: Report) -> None:
        if "opacity_resets" not in report.values:
            report.values["opacity_resets"] = self.strategy.resets
        self.report_colour(it, report)
        if it % self.sh_every == 0 and self.model.active_sh_degree < self.model.sh_degree:
            self.model.active_sh_degree += 1
