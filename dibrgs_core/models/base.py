"""What every Gaussian model offers, and the one function that renders any of them.

A model turns a camera into rasterizer-ready Gaussians (:meth:`GaussianModel.gaussians`);
:func:`render_model` rasterizes them. Training, evaluation, rendering and export all go
through these two, so they never ask which kind of model they hold.

Conventions: cameras are OpenCV (x right, y down, z forward) with ``w2c`` world-to-camera
and ``K`` in pixels (:class:`~dibrgs_core.camera.pinhole.Camera`); Gaussians are world
means, unit ``(w, x, y, z)`` quaternions, world-unit standard deviations, opacities and
RGB colours in [0, 1].
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, Sequence

import torch

from ..camera.pinhole import Camera
from ..render import RenderMode, rasterize


@dataclass
class CameraTensors:
    """A camera as float32 tensors: ``K`` (3,3) pixels, ``w2c`` (4,4), ``center`` (3,) world."""

    cam: Camera
    K: torch.Tensor
    w2c: torch.Tensor
    center: torch.Tensor

    @staticmethod
    def of(cam: Camera) -> "CameraTensors":
        return CameraTensors(cam, torch.tensor(cam.K, dtype=torch.float32),
                             torch.tensor(cam.w2c, dtype=torch.float32),
                             torch.tensor(cam.center, dtype=torch.float32))


@dataclass
class Gaussians:
    """Activated Gaussians for one camera; ``aux`` is what the model's strategy needs from the
    view (Scaffold: the per-anchor visibility and raw opacities), None otherwise."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    aux: Any = None

    def as_dict(self) -> dict[str, torch.Tensor]:
        return {"means": self.means, "quats": self.quats, "scales": self.scales,
                "opacities": self.opacities, "colors": self.colors}


class GaussianModel(Protocol):
    """The protocol of :class:`~.scaffold.NeuralGaussians` and :class:`~.gs3d.Gaussians3D`.

    ``kind`` names the method ("dibrgs", "3dgs"); :mod:`.factory` maps it back to the class.
    """

    kind: ClassVar[str]
    #: Near clipping plane in scene units (a fixed fraction of a length of the scene, so it
    #: does not depend on the scene's units).
    near: float

    def gaussians(self, cam: CameraTensors) -> Gaussians:
        """The Gaussians this model shows ``cam`` (differentiable)."""

    def export_gaussians(self, cams: Sequence[Camera]) -> dict[str, torch.Tensor]:
        """Every Gaussian, view-independent, for a 3DGS PLY (``cams``: the training cameras)."""

    def sizes(self) -> dict[str, int]:
        """``{"anchors": ..., "gaussians": ...}``."""

    def state(self) -> dict[str, Any]:
        """Everything :meth:`from_state` needs: ``{"model": state_dict, ...shape metadata}``."""


def render_model(model: GaussianModel, cam: CameraTensors, background: torch.Tensor,
                 render_mode: RenderMode = "RGB+ED"
                 ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, dict[str, Any] | None]:
    """Render ``model`` from ``cam``: ``(image (H,W,3), alpha (H,W,1), depth (H,W,1), info)``.

    ``info`` is the rasterizer's meta plus ``width``, ``height``, the model's ``aux`` and the
    ``gaussians`` themselves; None when the model shows this camera no Gaussian (the image
    is then the background, alpha and depth 0). ``render_mode`` as :func:`rasterize`'s:
    ``"RGB"`` (a training step) returns None for alpha and depth.
    """
    W, H = cam.cam.width, cam.cam.height
    g = model.gaussians(cam)
    if g.means.shape[0] == 0:
        zero = None if render_mode == "RGB" else torch.zeros(H, W, 1)
        return background.expand(H, W, 3).clone(), zero, zero, None
    img, alpha, depth, meta = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors,
                                        cam.w2c, cam.K, W, H, background=background, near=model.near,
                                        render_mode=render_mode)
    return img, alpha, depth, {**meta, "width": W, "height": H, "aux": g.aux, "gaussians": g}
