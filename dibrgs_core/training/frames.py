"""Supervised frames: a camera as tensors, its target image and an optional per-pixel loss weight
(a scene view's pixels without data weigh 0; a pseudo view's padding less than its warped pixels).

Images are (H, W, 3) float32 in [0, 1]; a resolution scale resizes image and camera together
(area-averaged down, bilinear up; the camera with :meth:`Camera.scaled`, pixel-centre exact).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..models.base import CameraTensors


def resize_image(img: np.ndarray, scale: float) -> np.ndarray:
    """Area-resize an (H,W,C) float image by ``scale`` (no-op at 1)."""
    if scale == 1.0:
        return np.asarray(img, np.float32)
    t = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)[None]
    H, W = img.shape[:2]
    out = torch.nn.functional.interpolate(t, size=(max(1, round(H * scale)), max(1, round(W * scale))),
                                          mode="area" if scale < 1 else "bilinear")
    return out[0].permute(1, 2, 0).numpy()


@dataclass
class Frame:
    """A supervised view: camera, target image (H,W,3) and optional per-pixel loss weight (H,W) in [0,1]."""

    cam: CameraTensors
    image: torch.Tensor
    mask: torch.Tensor | None = None


def views_to_frames(views: list[Any], scale: float) -> list[Frame]:
    """Frames of scene views (:class:`~dibrgs_core.data.scene.View`) at ``scale`` x their resolution;
    a view with pixels that hold no data gets a 0/1 mask: 1 where every photo pixel a frame pixel
    is drawn from holds data (its colour is not mixed with the fill)."""
    out = []
    for v in views:
        cam = v.camera.scaled(scale) if scale != 1.0 else v.camera
        image, valid = v.pixels()
        img = resize_image(np.clip(np.nan_to_num(image), 0.0, 1.0), scale)
        mask = None
        if valid is not None:
            mask = torch.from_numpy((resize_image(valid[..., None].astype(np.float32), scale)[..., 0] > 1 - 1e-4)
                                    .astype(np.float32))
        out.append(Frame(CameraTensors.of(cam), torch.from_numpy(np.ascontiguousarray(img[..., :3])), mask))
    return out


def has_data(frame: Frame) -> bool:
    """Whether a scene view's frame has a pixel of data to score (a photo may have none)."""
    return frame.mask is None or bool((frame.mask > 0.5).any())


def frame_valid(frame: Frame) -> np.ndarray | None:
    """The pixels of a scene view's frame that hold data (bool (H, W)), None when all do."""
    return None if frame.mask is None else frame.mask.numpy() > 0.5
