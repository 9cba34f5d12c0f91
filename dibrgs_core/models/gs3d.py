"""Vanilla 3D Gaussian Splatting (Kerbl et al. 2023): the baseline's model, on the same rasterizer.

Facts taken from graphdeco-inria/gaussian-splatting (read, not copied):

* initialisation from SfM points: colours as the SH DC term ((rgb - 0.5) / C0),
  log scale of the RMS distance to the 3 nearest points, opacity 0.1 (logit),
  identity rotation;
* spherical harmonics up to degree 3 (the trainer raises the active degree);
  colour = max(SH(dir) + 0.5, 0).

Densification: :mod:`dibrgs_core.strategy.densify`; learning rates:
:mod:`dibrgs_core.training.methods`.

The near plane is a fraction of ``length``, the initial points' median distance from
their median (stored with the model), so it follows the scene's units.
"""
from __future__ import annotations

import math
from typing import Any, ClassVar, Sequence

import numpy as np
import torch
from torch import nn

from ..camera.pinhole import Camera
from .base import CameraTensors, Gaussians

GAUSS_PARAMS = ("means", "sh_dc", "sh_rest", "opacity", "log_scales", "quats")
NEAR_FRACTION = 1e-4  # near plane / ``length``

# Real spherical-harmonics basis constants (degree 0-3).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
       0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / _C0


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis (N, (degree+1)^2) at unit directions ``dirs`` (N, 3), 3DGS's sign convention."""
    x, y, z = dirs.unbind(1)
    cols = [torch.full_like(x, _C0)]
    if degree >= 1:
        cols += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        cols += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2.0 * zz - xx - yy), _C2[3] * xz, _C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [_C3[0] * y * (3 * xx - yy), _C3[1] * xy * z, _C3[2] * y * (4 * zz - xx - yy),
                 _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                 _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    return torch.stack(cols, 1)


def eval_sh_split(degree: int, sh_dc: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour (N, 3) from the DC coefficient ``sh_dc`` (N, 1, 3) and the higher ones ``sh_rest``
    (N, K-1, 3), K >= (degree+1)^2, at unit directions ``dirs`` (N, 3).

    One basis matrix times the coefficients (a batched matmul): the backward pass allocates
    one gradient of ``sh_rest``'s active part, not one full-size gradient per coefficient.
    """
    res = _C0 * sh_dc.squeeze(1)
    if degree < 1:
        return res
    nc = (degree + 1) ** 2
    return res + torch.einsum("nk,nkc->nc", sh_basis(degree, dirs)[:, 1:], sh_rest[:, :nc - 1])


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour from SH coefficients ``sh`` (N, 16, 3) for unit directions ``dirs`` (N, 3)."""
    return eval_sh_split(degree, sh[:, :1], sh[:, 1:], dirs)


class Gaussians3D(nn.Module):
    """Explicit Gaussians with SH colour (3DGS); a :class:`~.base.GaussianModel`."""

    kind: ClassVar[str] = "3dgs"

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
        self.length = scene_length(p)

    @property
    def near(self) -> float:
        """Near plane (scene units) of rasterization."""
        return NEAR_FRACTION * self.length

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def activated(self, cam_center: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(means, quats wxyz unit, scales, opacities, colours) for one camera centre."""
        d = self.means - cam_center
        d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        rgb = (eval_sh_split(self.active_sh_degree, self.sh_dc, self.sh_rest, d) + 0.5).clamp_min(0.0)
        q = self.quats / self.quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return (self.means, q, torch.exp(self.log_scales.clamp(-30.0, 20.0)),
                torch.sigmoid(self.opacity), rgb)

    # -- the model protocol ------------------------------------------------------
    def gaussians(self, cam: CameraTensors) -> Gaussians:
        return Gaussians(*self.activated(cam.center))

    @torch.no_grad()
    def export_gaussians(self, cams: Sequence[Camera]) -> dict[str, torch.Tensor]:
        """Every Gaussian with its SH coefficients (view-independent)."""
        center = torch.tensor(np.mean([c.center for c in cams], 0), dtype=torch.float32)
        means, quats, scales, opac, _ = self.activated(center)
        g = {"means": means, "quats": quats, "scales": scales, "opacities": opac,
             "sh_dc": self.sh_dc[:, 0], "sh_rest": self.sh_rest}
        return {k: v.detach() for k, v in g.items()}  # parameters themselves would carry requires_grad

    def sizes(self) -> dict[str, int]:
        return {"anchors": 0, "gaussians": self.num_gaussians}

    def state(self) -> dict[str, Any]:
        return {"model": self.state_dict(), "active_sh_degree": self.active_sh_degree, "length": self.length}

    @classmethod
    def from_state(cls, st: dict[str, Any], cfg: Any = None) -> "Gaussians3D":
        """A model with the shapes and values of :meth:`state`'s output (``cfg`` is not needed:
        the SH degree follows from the coefficients' shape)."""
        sd = st["model"]
        sh_degree = math.isqrt(sd["sh_rest"].shape[1] + 1) - 1
        model = cls(np.zeros((sd["means"].shape[0], 3)), np.zeros((sd["means"].shape[0], 3)), sh_degree)
        for name, t in sd.items():
            setattr(model, name, nn.Parameter(t.clone()))
        model.active_sh_degree = int(st["active_sh_degree"])
        model.length = float(st["length"]) if "length" in st else scene_length(model.means.detach())
        return model


def scene_length(points: torch.Tensor) -> float:
    """The median distance of ``points`` (N,3) from their median: the scene's size in its units
    (1 when the points give none)."""
    if points.shape[0] == 0:
        return 1.0
    d = float((points - points.median(dim=0).values).norm(dim=1).median())
    return d if math.isfinite(d) and d > 0 else 1.0
