"""Vanilla 3DGS densification (Kerbl et al. 2023): clone, split and prune with opacity resets.

Facts from graphdeco-inria/gaussian-splatting (read, not copied): every 100 its
from 500 to 15,000 of 30,000, Gaussians whose mean NDC gradient >= 2e-4 are
cloned (max scale <= 1% of the extent) or split in two (larger; samples from
the Gaussian, scales / 1.6); pruning of opacity < 0.005 and, after the first
opacity reset, of Gaussians larger than 20 px on screen or 10% of the extent;
opacity reset to at most 0.01 every 3,000 its (resets stop with densification,
so the last is at 12,000, 60 % of training before the end). Schedules are
fractions of training (``GS3DConfig``), except that resets are at least
``min_reset_every`` iterations apart (3DGS's own 3,000): opacities need a number
of iterations, not a share of the run, to recover from a reset, so short runs
(under 6,000 iterations) never reset; a 2,000-iteration run that reset every
10 % of training, or once at 25 %, ended lower held out. A preset may cap the
number of Gaussians (``max_gaussians``), densification then stops adding.
"""
from __future__ import annotations

import logging
import math
from typing import Any

import torch

from ..models.gs3d import GAUSS_PARAMS, Gaussians3D
from ..render.projection import quat_to_rotmat
from ..training.config import GS3DConfig
from .base import Strategy
from .ops import cat_rows, keep_rows, swap_param
from .stats import add_grad_norms

log = logging.getLogger("dibrgs.gs3d")


class DensifyStrategy(Strategy):
    """3DGS clone / split / prune with opacity reset."""

    def __init__(self, model: Gaussians3D, cfg: GS3DConfig, iterations: int, extent: float) -> None:
        self.cfg = cfg
        self.extent = float(extent)
        self.start = max(1, round(cfg.densify_from * iterations))
        self.until = max(1, round(cfg.densify_until * iterations))
        self.every = max(cfg.min_every, round(cfg.densify_every * iterations))
        self.reset_every = max(1, cfg.min_reset_every, round(cfg.opacity_reset_every * iterations))
        self._reset_stats(model.num_gaussians)

    @property
    def resets(self) -> list[int]:
        """The iterations at which opacities are reset (inside the densification window)."""
        return list(range(self.reset_every, self.until, self.reset_every))

    def _reset_stats(self, n: int) -> None:
        self.grad_accum = torch.zeros(n)
        self.denom = torch.zeros(n)
        self.max_radii = torch.zeros(n)

    @torch.no_grad()
    def update(self, means2d_grad: torch.Tensor | None, radii: torch.Tensor, width: int, height: int) -> None:
        # The radii are >= 0 and 0 where unseen: the running maximum needs no mask.
        r = radii.reshape(-1)
        torch.maximum(self.max_radii, r.to(self.max_radii.dtype), out=self.max_radii)
        if means2d_grad is not None:
            add_grad_norms(self.grad_accum, self.denom, means2d_grad, r > 0, width, height)

    def step_post_backward(self, model: Gaussians3D, optimizer: torch.optim.Optimizer, step: int,
                           info: dict[str, Any] | None) -> dict[str, int]:
        """Statistics of this view, then densification and opacity reset when due (before ``until``)."""
        if not self.collects(step):  # the window in which step_pre_backward keeps the gradient
            return {}
        if info is not None:
            self.update(info["means2d"].grad, info["radii"], info["width"], info["height"])
        if step > self.start and step % self.every == 0:
            self.densify_and_prune(step, model, optimizer)
        if step % self.reset_every == 0:
            self._reset_opacity(model, optimizer)
        return {}

    @torch.no_grad()
    def densify_and_prune(self, it: int, model: Gaussians3D, optimizer: torch.optim.Optimizer) -> None:
        cfg = self.cfg
        grads = torch.nan_to_num(self.grad_accum / self.denom, nan=0.0)
        n = model.num_gaussians
        room = None if cfg.max_gaussians is None else max(cfg.max_gaussians - n, 0)
        big = grads >= cfg.grad_threshold
        scales = torch.exp(model.log_scales)
        small = scales.max(dim=1).values <= cfg.percent_dense * self.extent
        clone = big & small
        split = big & ~small
        if room is not None:
            # Keep the strongest gradients within the budget (a split adds one net Gaussian).
            order = torch.argsort(grads, descending=True)
            want = (clone | split)[order]
            allowed = torch.cumsum(want.long(), 0) <= room
            ok = torch.zeros(n, dtype=torch.bool)
            ok[order[want & allowed]] = True
            clone &= ok
            split &= ok
        ext = {name: getattr(model, name).detach()[clone] for name in GAUSS_PARAMS}
        # Split: two samples from the Gaussian, scales / (0.8 * 2).
        ns = int(split.sum())
        if ns:
            s = scales[split].repeat(2, 1)
            samples = torch.randn(2 * ns, 3) * s
            R = quat_to_rotmat(model.quats.detach()[split]).repeat(2, 1, 1)
            new_means = (R @ samples[..., None]).squeeze(-1) + model.means.detach()[split].repeat(2, 1)
            new_scales = torch.log(s / 1.6)
            for name in GAUSS_PARAMS:
                rep = getattr(model, name).detach()[split].repeat(2, *([1] * (getattr(model, name).dim() - 1)))
                if name == "means":
                    rep = new_means
                elif name == "log_scales":
                    rep = new_scales
                ext[name] = torch.cat([ext[name], rep], 0)
        cat_rows(optimizer, model, ext)
        total = model.num_gaussians
        prune = torch.sigmoid(model.opacity.detach()) < cfg.min_opacity
        prune[:n] |= split  # the split originals
        if it > self.reset_every:
            radii = torch.cat([self.max_radii, torch.zeros(total - n)])
            prune |= radii > cfg.max_screen_size
            prune |= torch.exp(model.log_scales.detach()).max(dim=1).values > 0.1 * self.extent
        if prune.all():
            prune[torch.argmax(torch.sigmoid(model.opacity.detach()))] = False
        keep_rows(optimizer, model, GAUSS_PARAMS, ~prune)
        log.debug("densify @%d: +%d clone, +%d split, -%d pruned -> %d", it, int(clone.sum()), ns,
                  int(prune.sum()), model.num_gaussians)
        self._reset_stats(model.num_gaussians)

    @torch.no_grad()
    def _reset_opacity(self, model: Gaussians3D, optimizer: torch.optim.Optimizer) -> None:
        cap = math.log(0.01 / 0.99)
        new = torch.minimum(model.opacity.detach(), torch.full_like(model.opacity, cap))

        swap_param(optimizer, model, "opacity", new, torch.zeros_like)

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "denom": self.denom, "max_radii": self.max_radii}

    def load_state_dict(self, d: dict) -> None:
        for key, val in d.items():
            setattr(self, key, val.clone())
