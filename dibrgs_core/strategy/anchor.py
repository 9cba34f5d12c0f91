"""Scaffold-GS anchor growing and pruning with the paper's height-constrained growth.

Statistics (every iteration inside the growth window, as Scaffold-GS's
``training_statis``):

* per neural Gaussian: accumulated norm of its screen-space mean gradient and a
  visit count, for Gaussians that were rasterized with a positive radius. Our
  rasterizer's ``means2d`` are in pixels, 3DGS's in NDC (pixel = (ndc+1) W/2), so
  gradients are scaled by (W/2, H/2) to make the 3DGS / Scaffold-GS threshold
  2e-4 mean the same thing;
* per anchor: accumulated Tanh opacity (negatives as 0) and a visit count.

Growth (``adjust``, every ``densify_every`` of training between ``densify_from``
and ``densify_until``), Scaffold-GS ``anchor_growing``: three levels i = 0, 1, 2
with cells of 16, 4, 1 voxels (update_init_factor // update_hierachy_factor**i)
and gradient thresholds tau * 2**i; a Gaussian is a candidate when its averaged
gradient passes the level's threshold, it was seen in more than half of
``success_threshold`` x interval iterations, and it survives a random pick with
probability 1 - 0.5**(i+1). Candidates are snapped to the level's cell; cells
already holding an anchor are dropped; new anchors get the max-pooled feature of
their candidates, zero offsets and log scaling = log(cell). Unlike Scaffold-GS,
the finer levels run even when a coarser one added nothing (there they are skipped),
because the height veto below would otherwise switch off all growth in a scene
where the coarsest level is vetoed.

Height constraint (paper Sec. "Height-constrained Anchor Growth"): at the coarsest
level only, candidate Gaussians above the height map's relaxed bound are dropped.

A configured ``max_anchors`` ceiling keeps a random subset of the new cells when
growth would exceed it (CPU presets only; the paper has none).

Pruning: anchors visited more than ``success_threshold`` x interval times whose
accumulated opacity is under ``min_opacity`` per visit are removed (Scaffold-GS
prunes in the same call). Scaffold-GS also clamps log scales to 0.05 there, a
constant in world units; we leave it out so the behaviour does not depend on the
scene's units.

Optimiser state stays consistent: new rows get zero Adam moments, removed rows
lose theirs (``cat_rows`` / ``keep_rows``).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from ..models.scaffold import ANCHOR_PARAMS, Decoded, NeuralGaussians
from ..models.spawn import true_indices
from ..training.config import GrowthConfig
from .base import Strategy
from .ops import cat_rows, keep_rows
from .stats import add_grad_norms

log = logging.getLogger("dibrgs.strategy")


class HeightBound(Protocol):
    def allows(self, points: Any) -> Any: ...



@dataclass
class AdjustResult:
    added: int
    vetoed: int
    pruned: int


def _new_cells(cand: torch.Tensor, existing: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The distinct cells of ``cand`` ((n, 3) int64 grid coordinates) in lexicographic order, each
    row's cell among them, and which of them no row of ``existing`` occupies.

    torch's row-wise ``unique(dim=0)`` took about 6 ms a call for a few thousand cells (three
    calls a level, three levels a growth step: most of a step's 40 ms); the rows packed into one
    int64 key each (the same order) make them one-dimensional, unless the cells span more than
    62 bits (a stray point far out), where the rows are compared as rows."""
    both = torch.cat([cand, existing])
    lo, hi = both.min(0).values.tolist(), both.max(0).values.tolist()
    span = [h - l + 1 for h, l in zip(hi, lo)]  # Python integers: exact at any coordinates
    if span[0] * span[1] * span[2] < 2 ** 62:
        sy, sz = span[1], span[2]

        def key(c: torch.Tensor) -> torch.Tensor:
            return ((c[:, 0] - lo[0]) * sy + (c[:, 1] - lo[1])) * sz + (c[:, 2] - lo[2])

        keys, inv = torch.unique(key(cand), return_inverse=True)
        first = torch.full((len(keys),), len(cand), dtype=torch.int64).scatter_reduce_(
            0, inv, torch.arange(len(cand)), reduce="amin")
        return cand[first], inv, ~torch.isin(keys, key(existing))
    cells, inv = torch.unique(cand, dim=0, return_inverse=True)
    uniq = torch.unique(existing, dim=0)
    _, binv, counts = torch.unique(torch.cat([uniq, cells]), dim=0, return_inverse=True, return_counts=True)
    return cells, inv, counts[binv[len(uniq):]] == 1


class AnchorStrategy(Strategy):
    """Accumulates growth statistics and grows / prunes anchors of a :class:`NeuralGaussians`."""

    def __init__(self, model: NeuralGaussians, cfg: GrowthConfig, iterations: int,
                 height_map: HeightBound | None = None) -> None:
        self.cfg = cfg
        self.height_map = height_map
        self.k = model.n_offsets
        n = model.num_anchors
        self.offset_grad = torch.zeros(n * self.k)
        self.offset_denom = torch.zeros(n * self.k)
        self.opacity_accum = torch.zeros(n)
        self.anchor_denom = torch.zeros(n)
        self.stat_start = max(1, round(cfg.stat_start * iterations))
        self.start = max(1, round(cfg.densify_from * iterations))
        self.until = max(1, round(cfg.densify_until * iterations))
        self.every = max(cfg.min_every, round(cfg.densify_every * iterations))
        self.capped = 0  # candidate anchors left out by ``max_anchors``

    # -- schedule ----------------------------------------------------------
    def collects(self, it: int) -> bool:
        return self.stat_start < it < self.until

    def adjusts(self, it: int) -> bool:
        return self.collects(it) and it > self.start and it % self.every == 0

    # -- the strategy hooks -------------------------------------------------------
    def step_post_backward(self, model: NeuralGaussians, optimizer: torch.optim.Optimizer, step: int,
                           info: dict[str, Any] | None) -> dict[str, int]:
        """Statistics of this view (inside the statistics window), then growth and pruning when due."""
        if info is not None and self.collects(step):
            self.update(info["aux"], info["means2d"].grad, info["visible"], info["width"], info["height"])
        if not self.adjusts(step):
            return {}
        r = self.adjust(model, optimizer)
        log.debug("anchors @%d: +%d (vetoed %d) -%d -> %d", step, r.added, r.vetoed, r.pruned, model.num_anchors)
        return {"added": r.added, "vetoed": r.vetoed, "pruned": r.pruned}

    # -- statistics ----------------------------------------------------------
    @torch.no_grad()
    def update(self, dec: Decoded, means2d_grad: torch.Tensor | None, visible: torch.Tensor,
               width: int, height: int) -> None:
        """Accumulate opacity and gradient statistics of one rendered view (``visible``: the
        rasterizer's (N,) mask of Gaussians with a positive radius, its meta's ``"visible"``)."""
        # Integer positions (the decoder's own) and index_add_, not boolean masks (each a nonzero
        # and a gather); the sums are the same, one addition a row.
        aidx = dec.anchor_index
        op = dec.neural_opacity.detach().clamp_min(0.0).view(-1, self.k).sum(1)
        self.opacity_accum.index_add_(0, aidx, op)
        self.anchor_denom.index_add_(0, aidx, torch.ones_like(op))
        if means2d_grad is not None:
            add_grad_norms(self.offset_grad, self.offset_denom, means2d_grad, visible, width, height,
                           aidx, dec.selected, self.k)

    # -- growth and pruning ----------------------------------------------------
    @torch.no_grad()
    def adjust(self, model: NeuralGaussians, optimizer: torch.optim.Optimizer) -> AdjustResult:
        cfg = self.cfg
        interval = self.every
        grads = torch.nan_to_num(self.offset_grad / self.offset_denom, nan=0.0, posinf=0.0)
        offset_mask = self.offset_denom > interval * cfg.success_threshold * 0.5
        n0 = model.num_anchors
        added, vetoed = self._grow(model, optimizer, grads, offset_mask)
        # Reset statistics of the Gaussians that were judged; pad for new anchors.
        self.offset_denom[offset_mask] = 0
        self.offset_grad[offset_mask] = 0
        pad = (model.num_anchors - n0) * self.k
        self.offset_denom = torch.cat([self.offset_denom, torch.zeros(pad)])
        self.offset_grad = torch.cat([self.offset_grad, torch.zeros(pad)])
        self.opacity_accum = torch.cat([self.opacity_accum, torch.zeros(model.num_anchors - n0)])
        self.anchor_denom = torch.cat([self.anchor_denom, torch.zeros(model.num_anchors - n0)])
        # Prune anchors that stayed (nearly) transparent.
        judged = self.anchor_denom > interval * cfg.success_threshold
        prune = (self.opacity_accum < cfg.min_opacity * self.anchor_denom) & judged
        self.opacity_accum[judged] = 0
        self.anchor_denom[judged] = 0
        keep = ~prune
        if prune.any():
            keep_rows(optimizer, model, ANCHOR_PARAMS, keep)
            self.offset_grad = self.offset_grad.view(-1, self.k)[keep].reshape(-1)
            self.offset_denom = self.offset_denom.view(-1, self.k)[keep].reshape(-1)
            self.opacity_accum = self.opacity_accum[keep]
            self.anchor_denom = self.anchor_denom[keep]
        return AdjustResult(added=added, vetoed=vetoed, pruned=int(prune.sum()))

    def _grow(self, model: NeuralGaussians, optimizer: torch.optim.Optimizer, grads: torch.Tensor,
              offset_mask: torch.Tensor) -> tuple[int, int]:
        cfg = self.cfg
        k = self.k
        init_len = model.num_anchors * k
        added = vetoed = 0
        # The grid of the initial anchors; float64 as the corner may lie far from the anchors.
        origin = torch.tensor(model.grid_origin, dtype=torch.float64)
        for i in range(cfg.update_depth):
            thr = cfg.grad_threshold * (cfg.update_hierarchy_factor // 2) ** i
            cand = (grads >= thr) & offset_mask
            cand &= torch.rand(cand.shape) > 0.5 ** (i + 1)
            extra = model.num_anchors * k - init_len
            if extra:
                cand = torch.cat([cand, torch.zeros(extra, dtype=torch.bool)])
            if not cand.any():
                continue
            scaling = model.anchor_scaling()
            all_xyz = (model.anchor[:, None, :] + model.offset * scaling[:, None, :3]).reshape(-1, 3)
            feats = model.anchor_feat.repeat_interleave(k, dim=0)
            sel_xyz, sel_feat = all_xyz[cand], feats[cand]
            if i == 0 and self.height_map is not None:
                ok = torch.as_tensor(self.height_map.allows(sel_xyz.numpy()), dtype=torch.bool)
                vetoed += int((~ok).sum())
                sel_xyz, sel_feat = sel_xyz[ok], sel_feat[ok]
            finite = torch.isfinite(sel_xyz).all(dim=1)
            sel_xyz, sel_feat = sel_xyz[finite], sel_feat[finite]
            if len(sel_xyz) == 0:
                continue
            size = model.voxel_size * (cfg.update_init_factor // cfg.update_hierarchy_factor ** i)
            cells, inv, new = _new_cells(torch.round((sel_xyz.double() - origin) / size).long(),
                                         torch.round((model.anchor.double() - origin) / size).long())
            if not new.any():
                continue
            pooled = torch.full((len(cells), sel_feat.shape[1]), -math.inf)
            pooled.scatter_reduce_(0, inv[:, None].expand_as(sel_feat), sel_feat, reduce="amax")
            new_idx = true_indices(new)
            if cfg.max_anchors is not None:
                room = max(cfg.max_anchors - model.num_anchors, 0)
                if len(new_idx) > room:
                    self.capped += len(new_idx) - room
                    new_idx = new_idx[torch.randperm(len(new_idx))[:room]].sort().values
            if len(new_idx) == 0:
                continue
            pos = (origin + cells[new_idx].double() * size).float()
            m = len(pos)
            cat_rows(optimizer, model, {
                "anchor": pos,
                "offset": torch.zeros(m, k, 3),
                "anchor_feat": pooled[new_idx],
                "scaling": torch.full((m, 6), math.log(size)),
            })
            added += m
        return added, vetoed

    # -- persistence -------------------------------------------------------------
    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"offset_grad": self.offset_grad, "offset_denom": self.offset_denom,
                "opacity_accum": self.opacity_accum, "anchor_denom": self.anchor_denom,
                "capped": torch.tensor(self.capped)}

    def load_state_dict(self, d: dict[str, torch.Tensor]) -> None:
        for key, val in d.items():
            setattr(self, key, int(val) if key == "capped" else val.clone())
