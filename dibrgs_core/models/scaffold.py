"""Anchor-based neural Gaussians (Scaffold-GS) with the paper's IBR feature fusion.

Each anchor ``v`` (position ``x_v``, 32-d feature ``f_s``, 6-d log scaling ``l_v``
and ``k`` learned offsets ``O``) spawns ``k`` neural Gaussians per view:

* centres ``x_v + O * exp(l_v[:3])``;
* opacity, covariance and colour from three MLPs fed with the fused feature,
  the unit viewing direction (anchor - camera centre) and the camera distance:
  each is Linear(feat+3+1, feat)-ReLU-Linear(feat, k*out). Opacity uses Tanh and
  only Gaussians with opacity > 0 are rasterized; the covariance head gives
  3 scale logits (scale = exp(l_v[3:]) * sigmoid) and a quaternion (normalised,
  w x y z); colour uses Sigmoid.
* IBR fusion (paper Sec. "Adaptive Feature Fusion"): ``f = f_s + g * E_ref(f_v)``
  with ``g = E_mod(f_v) = sigmoid(Linear(f_v))``, its bias initialised to -5 so the
  reference feature enters gently.

Fusion, the decoders' input and the three MLPs run in :mod:`.decoder` (one C++ node on the
rasterizer's fast path).

Distances fed to the MLPs are divided by ``dist_scale`` (the mean camera-to-scene
distance at initialisation) so the decoders see O(1) inputs whatever the scene's
units; Scaffold-GS feeds raw distances on scenes a few units across. The near plane
of frustum culling and rasterization is ``NEAR_FRACTION`` of that distance, and
``paper_unit`` (scene units per paper unit, below) lets training express the volume
regulariser in the paper's units.

Anchor voxel (documented rule): the paper's anchor grid is 0.03 in LEVIR-NVS units.
Like the geometry stage (``init.py``), we convert paper units to scene units with
``scale = median training-camera distance to the look-at point / 115`` (LEVIR-NVS
cameras are about 115 units from the scene), so ``voxel = 0.03 * scale``. That is
much finer than the dense cloud's 1.0-unit downsampling voxel, so in the paper
every fused point becomes an anchor. A preset may cap the initial anchor count;
the voxel then doubles until the cloud fits (reported). The grid goes through the
cloud's lowest corner (``grid_origin``, kept with the model), so a scene gets the same
anchors wherever its coordinates put it.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Sequence

import numpy as np
import torch
from torch import nn

from ..camera.frame import central_camera
from ..camera.pinhole import Camera
from ..geometry.pointcloud import grid_origin, voxelize
from ..render import fast, uses_fast
from .base import CameraTensors, Gaussians
from .config import ModelConfig
from .decoder import decode as decode_heads, fuse
from .spawn import activate_scaling, spawn, take_rows, true_indices
from .visible import decode_visible

log = logging.getLogger("dibrgs.neural_gaussians")

# Parameter tensors with one row per anchor (the growth strategy resizes them).
ANCHOR_PARAMS = ("anchor", "offset", "anchor_feat", "scaling")
# Near plane as a fraction of the camera-to-scene distance (the rasterizer's former 0.01 m
# at the generated scenes' 210 m is 5e-5; anything nearer a camera than this is a floater).
NEAR_FRACTION = 1e-4


def _mlp(in_dim: int, hidden: int, out_dim: int, act: nn.Module | None) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim)]
    if act is not None:
        layers.append(act)
    return nn.Sequential(*layers)


def anchor_voxel_size(points: np.ndarray, cfg: ModelConfig, scale: float,
                      origin: np.ndarray | None = None) -> tuple[float, str]:
    """The anchor voxel (scene units) for ``points`` and a sentence explaining it.

    ``scale`` is scene units per paper unit (see the module docstring); ``origin``: the grid's
    (default :func:`~dibrgs_core.geometry.pointcloud.grid_origin` of ``points``).
    """
    origin = grid_origin(points) if origin is None else origin
    voxel = cfg.anchor_voxel * scale
    why = f"{cfg.anchor_voxel} paper units x {scale:.4g} scene units per paper unit = {voxel:.4g}"
    if cfg.max_init_anchors:
        if not cfg.anchor_voxel_growth > 1.0:
            raise ValueError(f"anchor_voxel_growth must be above 1, got {cfg.anchor_voxel_growth}")
        n = len(voxelize(points, voxel, origin))
        steps = 0
        while n > cfg.max_init_anchors:
            voxel *= cfg.anchor_voxel_growth
            steps += 1
            n = len(voxelize(points, voxel, origin))
        if steps:
            grown = "doubled" if cfg.anchor_voxel_growth == 2.0 else f"grown by {cfg.anchor_voxel_growth:.4g}"
            why += f"; {grown} {steps}x to {voxel:.4g} to fit the budget of {cfg.max_init_anchors} anchors"
    return voxel, why


@dataclass
class Decoded:
    """Neural Gaussians decoded for one camera (activated values, rasterizer-ready).

    ``anchor_visible`` (N,) marks the anchors inside the frustum and ``anchor_index``
    (M,) int64 is their positions, increasing; ``neural_opacity`` (M*k,) the raw Tanh
    opacities of those anchors' Gaussians and ``selected`` (M*k,) the ones kept
    (opacity > 0), i.e. the rows of ``means`` etc.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    anchor_visible: torch.Tensor
    anchor_index: torch.Tensor
    neural_opacity: torch.Tensor
    selected: torch.Tensor


class NeuralGaussians(nn.Module):
    """Scaffold-GS anchors + decoders + IBR fusion (E_ref, E_mod); a :class:`~.base.GaussianModel`.

    The anchor tensors are ``nn.Parameter`` attributes named in ``ANCHOR_PARAMS``;
    the growth strategy replaces them when anchors are added or pruned. The IBR
    features come from :meth:`set_ibr` (a live feature module while training,
    the frozen per-anchor features of a trained model).
    """

    kind: ClassVar[str] = "dibrgs"

    def __init__(self, anchors: torch.Tensor, voxel_size: float, dist_scale: float,
                 cfg: ModelConfig, use_ibr: bool, paper_unit: float | None = None,
                 grid_origin: Sequence[float] | None = None) -> None:
        """``paper_unit``: scene units per paper unit (None: ``voxel_size / cfg.anchor_voxel``,
        which model files written before it was stored imply). ``grid_origin``: (3,) a point of
        the anchor grid, world units (None: (0, 0, 0), the grid of model files written before it
        was stored); the initial anchors are its voxel centres and growth adds those of coarser
        grids through the same point."""
        super().__init__()
        n = anchors.shape[0]
        k, fd = cfg.n_offsets, cfg.feat_dim
        self.cfg = cfg
        self.n_offsets = k
        self.feat_dim = fd
        self.voxel_size = float(voxel_size)
        self.dist_scale = float(dist_scale)
        self.paper_unit = float(paper_unit) if paper_unit else self.voxel_size / cfg.anchor_voxel
        self.grid_origin = tuple(float(v) for v in (grid_origin if grid_origin is not None else (0.0, 0.0, 0.0)))
        self.use_ibr = bool(use_ibr)
        self.anchor = nn.Parameter(anchors.float().clone())
        self.offset = nn.Parameter(torch.zeros(n, k, 3))
        self.anchor_feat = nn.Parameter(torch.zeros(n, fd))
        self.scaling = nn.Parameter(init_log_scaling(anchors.float()).repeat(1, 6))
        self.mlp_opacity = _mlp(fd + 4, fd, k, nn.Tanh())
        self.mlp_cov = _mlp(fd + 4, fd, 7 * k, None)
        self.mlp_color = _mlp(fd + 4, fd, 3 * k, nn.Sigmoid())
        if self.use_ibr:
            c = cfg.ibr_channels
            self.e_ref = nn.Linear(c, fd)
            self.e_mod = nn.Linear(c, fd)
            with torch.no_grad():
                self.e_mod.weight.mul_(0.01)
                self.e_mod.bias.fill_(cfg.gate_bias_init)
        # visibility mask (N,) -> IBR features (M, C_r) of the visible anchors, or None
        self._ibr: Callable[[torch.Tensor], torch.Tensor] | None = None

    def set_ibr(self, source: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | torch.Tensor | None
                ) -> None:
        """Where IBR features come from: a module mapping every anchor position (N,3)
        (detached) and a mask (N,) to the features (M, C_r) of the masked anchors (it may
        cache per anchor), or a tensor (N, C_r) of per-anchor features (indexed by the
        mask), or None."""
        if source is None:
            self._ibr = None
        elif isinstance(source, torch.Tensor):
            self._ibr = lambda vis: source[vis]
        else:
            self._ibr = lambda vis: source(fast.ready(self.anchor, self.anchor.dtype, detach=True), vis)

    @property
    def num_anchors(self) -> int:
        return int(self.anchor.shape[0])

    @property
    def near(self) -> float:
        """Near plane (scene units) of culling and rasterization."""
        return NEAR_FRACTION * self.dist_scale

    # -- per-anchor helpers ----------------------------------------------------
    def anchor_scaling(self) -> torch.Tensor:
        """(N,6) activated anchor scaling (the decode activates the visible anchors' rows itself)."""
        return activate_scaling(self.scaling)

    def fused_features(self, idx: torch.Tensor, ibr_feats: torch.Tensor | None) -> torch.Tensor:
        """``f_s + g * E_ref(f_v)`` for anchors ``idx`` (ibr_feats: (len(idx), C_r) or None)."""
        return fuse(take_rows([self.anchor_feat], idx)[0], ibr_feats, self._fusion())

    def _fusion(self) -> tuple[nn.Linear, nn.Linear] | None:
        """(E_ref, E_mod), or None without IBR fusion."""
        return (self.e_ref, self.e_mod) if self.use_ibr else None

    def visible_anchors(self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int,
                        near: float | None = None) -> torch.Tensor:
        """(N,) bool: anchors whose Gaussians can reach the image (frustum culling).

        An anchor is kept when it is in front of the camera and its projection,
        grown by the largest extent its Gaussians can reach (3 sigma plus the
        offset span), overlaps the image. One C++ pass (``render/csrc/spawn.h``
        ``visible``) when the rasterizer's C++ path is in use, else torch.
        """
        near = self.near if near is None else near
        if uses_fast(None, self.anchor):
            # The extension reads the values (no autograd below its calls): nothing to detach.
            return fast.extension().anchor_visibility(self.anchor, self.offset, self.scaling, K, w2c, int(width),
                                                      int(height), float(near))
        with torch.no_grad():
            x = self.anchor @ w2c[:3, :3].T + w2c[:3, 3]
            z = x[:, 2]
            s = self.anchor_scaling()
            reach = (self.offset.abs().amax(dim=(1, 2)) * s[:, :3].amax(dim=1)
                     + 3.0 * s[:, 3:].amax(dim=1))
            zs = z.clamp_min(near)
            u = K[0, 0] * x[:, 0] / zs + K[0, 2]
            v = K[1, 1] * x[:, 1] / zs + K[1, 2]
            r = K[0, 0].abs() * reach / zs
            inside = (u + r > 0) & (u - r < width) & (v + r > 0) & (v - r < height)
            return (z > near) & inside & torch.isfinite(u) & torch.isfinite(v)

    # -- decoding ----------------------------------------------------------------
    def decode(self, K: torch.Tensor, w2c: torch.Tensor, cam_center: torch.Tensor, width: int,
               height: int, ibr_feats: torch.Tensor | None = None,
               visible: torch.Tensor | None = None) -> Decoded:
        """Decode the neural Gaussians of the anchors visible from one camera.

        Args:
            K, w2c: intrinsics (pixels) and world-to-camera matrix, float32 tensors.
            cam_center: (3,) camera centre in world units.
            ibr_feats: (M,C_r) IBR features of the *visible* anchors (in index
                order), or None.
            visible: precomputed frustum mask (N,); computed when None.
        """
        if visible is None:
            visible = self.visible_anchors(K, w2c, width, height)
        idx = true_indices(visible)
        heads = (self.mlp_opacity, self.mlp_cov, self.mlp_color)
        # One autograd node on the C++ path (models/visible.py), else the three steps.
        fused = decode_visible(self.anchor, self.anchor_feat, self.scaling, self.offset, idx, ibr_feats,
                               cam_center, self.dist_scale, self._fusion(), heads)
        if fused is None:
            anchor, feat, log_s, offset = take_rows((self.anchor, self.anchor_feat, self.scaling, self.offset), idx)
            opacity, cov, color = decode_heads(feat, ibr_feats, anchor, cam_center, self.dist_scale, self._fusion(),
                                               heads)
            # The opacities in full feed the strategy's statistics, outside the loss's graph.
            fused = spawn(opacity, color, cov, anchor, log_s, offset), opacity.reshape(-1)
        g, neural_opacity = fused
        return Decoded(means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, colors=g.colors,
                       anchor_visible=visible, anchor_index=idx, neural_opacity=neural_opacity,
                       selected=g.selected)

    # -- the model protocol ------------------------------------------------------
    def gaussians(self, cam: CameraTensors) -> Gaussians:
        """Neural Gaussians of the anchors ``cam`` sees (``aux``: the :class:`Decoded`)."""
        W, H = cam.cam.width, cam.cam.height
        vis = self.visible_anchors(cam.K, cam.w2c, W, H)
        feats = None if self._ibr is None else self._ibr(vis)
        d = self.decode(cam.K, cam.w2c, cam.center, W, H, ibr_feats=feats, visible=vis)
        return Gaussians(d.means, d.quats, d.scales, d.opacities, d.colors, aux=d)

    @torch.no_grad()
    def export_gaussians(self, cams: Sequence[Camera]) -> dict[str, torch.Tensor]:
        """Every anchor's Gaussians decoded from the central training camera, frustum culling off."""
        c = CameraTensors.of(central_camera(cams))
        vis = torch.ones(self.num_anchors, dtype=torch.bool)
        feats = None if self._ibr is None else self._ibr(vis)
        d = self.decode(c.K, c.w2c, c.center, c.cam.width, c.cam.height, ibr_feats=feats, visible=vis)
        return Gaussians(d.means, d.quats, d.scales, d.opacities, d.colors).as_dict()

    def sizes(self) -> dict[str, int]:
        return {"anchors": self.num_anchors, "gaussians": self.num_anchors * self.n_offsets}

    def state(self) -> dict[str, Any]:
        return {"model": self.state_dict(),
                "model_meta": {"voxel_size": self.voxel_size, "dist_scale": self.dist_scale,
                               "use_ibr": self.use_ibr, "paper_unit": self.paper_unit,
                               "grid_origin": list(self.grid_origin)}}

    @classmethod
    def from_state(cls, st: dict[str, Any], cfg: ModelConfig) -> "NeuralGaussians":
        """A model with the shapes and values of :meth:`state`'s output."""
        sd, meta = st["model"], st["model_meta"]
        model = cls(torch.zeros(sd["anchor"].shape[0], 3), meta["voxel_size"], meta["dist_scale"], cfg,
                    meta["use_ibr"], meta.get("paper_unit"), meta.get("grid_origin"))
        model.load_state_dict(sd)
        return model

    def mlp_parameters(self) -> dict[str, list[nn.Parameter]]:
        """Decoder parameter groups by optimiser name."""
        groups = {"mlp_opacity": list(self.mlp_opacity.parameters()),
                  "mlp_cov": list(self.mlp_cov.parameters()),
                  "mlp_color": list(self.mlp_color.parameters())}
        if self.use_ibr:
            groups["ibr_fusion"] = list(self.e_ref.parameters()) + list(self.e_mod.parameters())
        return groups


def init_log_scaling(points: torch.Tensor) -> torch.Tensor:
    """(N,1) log of the RMS distance to the 3 nearest neighbours (3DGS / Scaffold-GS init)."""
    from scipy.spatial import cKDTree

    p = points.detach().cpu().double().numpy()
    if len(p) < 2:
        return torch.full((len(p), 1), math.log(1e-2), dtype=torch.float32)
    kq = min(4, len(p))
    d, _ = cKDTree(p).query(p, k=kq)
    d2 = np.mean(d[:, 1:] ** 2, axis=1)
    # Coincident points get a scale of 1e-3 x the median spacing (not a fixed length: units vary).
    pos = d2[d2 > 0]
    floor = 1e-3 * float(np.sqrt(np.median(pos))) if len(pos) else 1e-7
    d2 = np.clip(d2, floor ** 2, None)
    return torch.from_numpy(np.log(np.sqrt(d2))).float()[:, None]


def build_model(points: np.ndarray, cam_centers: np.ndarray, cfg: ModelConfig, use_ibr: bool,
                scale: float) -> tuple[NeuralGaussians, str]:
    """Anchors on a voxel grid over ``points`` (N,3); returns the model and the voxel rule used.

    ``scale``: scene units per paper unit (see the module docstring).
    """
    pts = np.asarray(points, np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise ValueError("the initial point cloud is empty; cannot place anchors")
    origin = grid_origin(pts)
    voxel, why = anchor_voxel_size(pts, cfg, scale, origin)
    anchors = torch.from_numpy(voxelize(pts, voxel, origin))
    centre = np.median(pts, axis=0)
    dist_scale = float(np.mean(np.linalg.norm(np.asarray(cam_centers) - centre, axis=1)))
    model = NeuralGaussians(anchors, voxel, max(dist_scale, 1e-6), cfg, use_ibr, paper_unit=scale,
                            grid_origin=origin)
    log.info("anchors: %d from %d points (voxel %s)", model.num_anchors, len(pts), why)
    return model, why
