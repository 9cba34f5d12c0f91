"""Vanilla 3D Gaussian Splatting (Kerbl et al. 2023): the baseline, on the same rasterizer.

Facts taken from graphdeco-inria/gaussian-splatting (read, not copied):

* initialisation from SfM points: colours as the SH DC term ((rgb - 0.5) / C0),
  log scale of the RMS distance to the 3 nearest points, opacity 0.1 (logit),
  identity rotation;
* spherical harmonics up to degree 3, the active degree growing by one every
  1,000 of 30,000 iterations; colour = max(SH(dir) + 0.5, 0);
* learning rates: position 1.6e-4 -> 1.6e-6 x scene extent (exponential decay),
  SH DC 2.5e-3, SH rest 2.5e-3 / 20, opacity 0.025, scaling 5e-3, rotation 1e-3;
* densification every 100 its from 500 to 15,000: Gaussians whose mean NDC
  gradient >= 2e-4 are cloned (max scale <= 1% of the extent) or split in two
  (larger; samples from the Gaussian, scales / 1.6); pruning of opacity < 0.005
  and, after the first opacity reset, of Gaussians larger than 20 px on screen or
  10% of the extent; opacity reset to at most 0.01 every 3,000 its.

Schedules are fractions of training as everywhere else (``GS3DConfig``). A
preset may cap the number of Gaussians (``max_gaussians``) so a CPU run stays
bounded; densification then stops adding (reported in the log).
"""
from __future__ import annotations

import logging
import math

import numpy as np
import torch
from torch import nn

from ..training.config import GS3DConfig
from ..strategy.anchor import _swap_param, cat_rows, keep_rows

log = logging.getLogger("dibrgs.gs3d")

GAUSS_PARAMS = ("means", "sh_dc", "sh_rest", "opacity", "log_scales", "quats")

# Real spherical-harmonics basis constants (degree 0-3).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
       0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / _C0


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour from SH coefficients ``sh`` (N, 16, 3) for unit directions ``dirs`` (N, 3)."""
    res = _C0 * sh[:, 0]
    if degree < 1:
        return res
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    res = res - _C1 * y * sh[:, 1] + _C1 * z * sh[:, 2] - _C1 * x * sh[:, 3]
    if degree < 2:
        return res
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    res = (res + _C2[0] * xy * sh[:, 4] + _C2[1] * yz * sh[:, 5]
           + _C2[2] * (2.0 * zz - xx - yy) * sh[:, 6] + _C2[3] * xz * sh[:, 7]
           + _C2[4] * (xx - yy) * sh[:, 8])
    if degree < 3:
        return res
    return (res + _C3[0] * y * (3 * xx - yy) * sh[:, 9] + _C3[1] * xy * z * sh[:, 10]
            + _C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
            + _C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
            + _C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + _C3[5] * z * (xx - yy) * sh[:, 14]
            + _C3[6] * x * (xx - 3 * yy) * sh[:, 15])


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N,4) wxyz (any norm) -> (N,3,3)."""
    q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=1).view(-1, 3, 3)


class Gaussians3D(nn.Module):
    """Explicit Gaussians with SH colour (3DGS)."""

    def __init__(self, points: np.ndarray, colors: np.ndarray, sh_degree: int) -> None:
        """``points`` (N,3) world units, ``colors`` (N,3) RGB in [0,1]."""
        super().__init__()
        from .scaffold import init_log_scaling

        p = torch.as_tensor(np.asarray(points), dtype=torch.float32)
        c = torch.as_tensor(np.asarray(colors), dtype=torch.float32).clamp(0.0, 1.0)
        n = p.shape[0]
        self.sh_degree = int(sh_degree)
        self.active_sh_degree = 0
        nc = (self.sh_degree + 1) ** 2
        self.means = nn.Parameter(p.clone())
        self.sh_dc = nn.Parameter(rgb_to_sh(c)[:, None, :].clone())
        self.sh_rest = nn.Parameter(torch.zeros(n, nc - 1, 3))
        self.opacity = nn.Parameter(torch.full((n,), math.log(0.1 / 0.9)))
        self.log_scales = nn.Parameter(init_log_scaling(p).repeat(1, 3))
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        self.quats = nn.Parameter(quats)

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def activated(self, cam_center: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(means, quats wxyz unit, scales, opacities, colours) for one camera centre."""
        d = self.means - cam_center
        d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        sh = torch.cat([self.sh_dc, self.sh_rest], dim=1)
        rgb = (eval_sh(self.active_sh_degree, sh, d) + 0.5).clamp_min(0.0)
        q = self.quats / self.quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return (self.means, q, torch.exp(self.log_scales.clamp(-30.0, 20.0)),
                torch.sigmoid(self.opacity), rgb)


class DensifyStrategy:
    """3DGS clone / split / prune with opacity reset."""

    def __init__(self, model: Gaussians3D, cfg: GS3DConfig, iterations: int, extent: float) -> None:
        self.cfg = cfg
        self.extent = float(extent)
        self.start = max(1, round(cfg.densify_from * iterations))
        self.until = max(1, round(cfg.densify_until * iterations))
        self.every = max(cfg.min_every, round(cfg.densify_every * iterations))
        self.reset_every = max(1, round(cfg.opacity_reset_every * iterations))
        self.sh_every = max(1, round(cfg.sh_every * iterations))
        self._reset_stats(model.num_gaussians)

    def _reset_stats(self, n: int) -> None:
        self.grad_accum = torch.zeros(n)
        self.denom = torch.zeros(n)
        self.max_radii = torch.zeros(n)

    @torch.no_grad()
    def update(self, means2d_grad: torch.Tensor | None, radii: torch.Tensor, width: int, height: int) -> None:
        seen = radii.reshape(-1) > 0
        self.max_radii[seen] = torch.maximum(self.max_radii[seen], radii.reshape(-1)[seen].float())
        if means2d_grad is None:
            return
        g = means2d_grad.detach()[seen] * torch.tensor([width / 2.0, height / 2.0])
        self.grad_accum[seen] += torch.nan_to_num(g.norm(dim=1), nan=0.0, posinf=0.0)
        self.denom[seen] += 1

    def step(self, it: int, model: Gaussians3D, optimizer: torch.optim.Optimizer) -> None:
        """Run whatever the schedule asks for after iteration ``it``'s optimiser step."""
        if it % self.sh_every == 0 and model.active_sh_degree < model.sh_degree:
            model.active_sh_degree += 1
        if it < self.until:
            if it > self.start and it % self.every == 0:
                self._densify_and_prune(it, model, optimizer)
            if it % self.reset_every == 0:
                self._reset_opacity(model, optimizer)

    @torch.no_grad()
    def _densify_and_prune(self, it: int, model: Gaussians3D, optimizer: torch.optim.Optimizer) -> None:
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

        _swap_param(optimizer, model, "opacity", new, torch.zeros_like)

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "denom": self.denom, "max_radii": self.max_radii}

    def load_state_dict(self, d: dict) -> None:
        for key, val in d.items():
            setattr(self, key, val.clone())


def optimizer_for(model: Gaussians3D, cfg: GS3DConfig, extent: float) -> torch.optim.Adam:
    groups = [
        {"params": [model.means], "lr": cfg.position_lr[0] * extent, "name": "means"},
        {"params": [model.sh_dc], "lr": cfg.feature_lr, "name": "sh_dc"},
        {"params": [model.sh_rest], "lr": cfg.feature_lr / 20.0, "name": "sh_rest"},
        {"params": [model.opacity], "lr": cfg.opacity_lr, "name": "opacity"},
        {"params": [model.log_scales], "lr": cfg.scaling_lr, "name": "log_scales"},
        {"params": [model.quats], "lr": cfg.rotation_lr, "name": "quats"},
    ]
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15)
