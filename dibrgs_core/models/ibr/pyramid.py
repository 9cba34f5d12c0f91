"""The weight-free IBR encoder: an image and Sobel-gradient pyramid."""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F

PYRAMID_SCALES = (2, 4, 8, 16)


def image_pyramid(images: torch.Tensor, scales: Sequence[int] = PYRAMID_SCALES) -> list[torch.Tensor]:
    """(V,3,H,W) in [0,1] -> per scale s a (V,6,max(1,H//s),max(1,W//s)) map: RGB, gx, gy, |grad|.

    Gradients are Sobel derivatives of the grey image at that level (per
    level-pixel, divided by 8 so a unit step gives 0.5).
    """
    sob = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=images.dtype) / 8.0
    kern = torch.stack([sob, sob.T])[:, None].to(images.device)
    out = []
    H, W = images.shape[-2:]
    for s in scales:
        lvl = F.adaptive_avg_pool2d(images, (max(1, H // s), max(1, W // s)))
        grey = lvl.mean(1, keepdim=True)
        g = F.conv2d(F.pad(grey, (1, 1, 1, 1), mode="replicate"), kern)
        mag = torch.sqrt((g ** 2).sum(1, keepdim=True) + 1e-12)
        out.append(torch.cat([lvl, g, mag], dim=1))
    return out
