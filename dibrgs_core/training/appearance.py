"""Per-training-view colour transforms: one photo's exposure must not become geometry.

Real photographs of one flight differ in exposure, white balance and vignetting. A model
fitted to them as they are explains a brighter photo with brighter (or extra) Gaussians,
which then show in every new view. Each training view ``v`` therefore gets a colour
transform applied to the *rendered* image before the loss on that view::

    out = img @ A_v.T + b_v,   A_v = I + D_v - mean_u D_u,   b_v = e_v - mean_u e_u

with learned ``D_v`` (3x3) and ``e_v`` (3), initialised to zero (identity transform), and
``median`` the entry-wise median over the views (the mean of the middle two for an even
count). Centring fixes the gauge (a transform common to all views is the model's colours):
the median view's colour response is the model's own, and renders of new views (curve,
evaluation, ``dibrgs render``) use the identity. The model file holds no transform. The
median, not the mean: with one photo over-exposed by 50 % among three, mean centring made
the model 17 % too bright for every new view (held-out PSNR 1.5 dB below no transforms at
all, ``tests/training/test_appearance.py``); the median keeps the typical exposure. A penalty
``weight * (|A_v - I|^2 + |b_v|^2)`` on the iteration's view keeps them near the identity.

Pseudo views (warped from the training photos, nearest source first, so their pixels
carry mostly the nearest training photo's colours) use the transform of the training
view nearest to the pseudo camera; a camera that is exactly a training camera uses its
own. With one training view the transform would only trade places with the model's
colours, so ``auto`` applies it from two views on.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from ..camera.pinhole import Camera
from ..common.report import Report
from ..models.base import CameraTensors
from .config import ColourConfig


class ColourTransforms(nn.Module):
    """Centred per-view colour affines of ``cameras`` (the training views, in order)."""

    def __init__(self, cameras: Sequence[Camera]) -> None:
        super().__init__()
        n = len(cameras)
        self.delta = nn.Parameter(torch.zeros(n, 3, 3))
        self.shift = nn.Parameter(torch.zeros(n, 3))
        self.register_buffer("centers", torch.tensor(np.array([c.center for c in cameras]), dtype=torch.float64),
                             persistent=False)
        self.w2cs = [torch.tensor(c.w2c, dtype=torch.float32) for c in cameras]
        self.names = [c.name or str(i) for i, c in enumerate(cameras)]

    def __len__(self) -> int:
        return int(self.delta.shape[0])

    def view_of(self, cam: CameraTensors) -> int:
        """The training view whose transform applies to ``cam``: its own for a training camera,
        else the nearest training camera (by centre)."""
        for i, w in enumerate(self.w2cs):
            if torch.equal(w, cam.w2c):
                return i
        c = torch.as_tensor(cam.cam.center, dtype=torch.float64)
        return int(torch.argmin((self.centers - c).norm(dim=1)))

    def affine(self, v: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(A_v (3,3), b_v (3,))`` of view ``v``, centred on the views' median."""
        A = torch.eye(3) + self.delta[v] - torch.quantile(self.delta, 0.5, dim=0)
        b = self.shift[v] - torch.quantile(self.shift, 0.5, dim=0)
        return A, b

    def apply(self, img: torch.Tensor, cam: CameraTensors) -> tuple[torch.Tensor, torch.Tensor]:
        """``(img @ A.T + b, penalty |A - I|^2 + |b|^2)`` for the view ``cam`` belongs to."""
        A, b = self.affine(self.view_of(cam))
        out = img @ A.T + b
        return out, ((A - torch.eye(3)) ** 2).sum() + (b ** 2).sum()

    @torch.no_grad()
    def summary(self) -> dict[str, Any]:
        """Per view: the transform's matrix and offset, rounded, for the report."""
        out = {}
        for v, name in enumerate(self.names):
            A, b = self.affine(v)
            out[name] = {"matrix": [[round(float(x), 4) for x in row] for row in A],
                         "offset": [round(float(x), 4) for x in b]}
        return out


def build_colour_transforms(cfg: ColourConfig, cameras: Sequence[Camera], report: Report
                            ) -> ColourTransforms | None:
    """The transforms of the training ``cameras`` when they apply (the decision is recorded)."""
    n = len(cameras)
    if cfg.mode == "off":
        report.decide("train", "colour_transforms", False, "switched off (colour.mode = off)")
        return None
    if n < 2:
        report.decide("train", "colour_transforms", False,
                      "one training view: its colour transform could not be told from the model's colours")
        return None
    report.decide("train", "colour_transforms", True,
                  f"a 3x3 colour matrix and offset for each of the {n} training views, the median "
                  "view's being the identity (exposure and white-balance differences between photos stay out of the scene); "
                  "new views render with the identity, pseudo views with their nearest training view's")
    return ColourTransforms(cameras)
