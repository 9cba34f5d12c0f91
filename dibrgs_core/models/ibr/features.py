"""IBR reference features for neural Gaussian anchors (paper: "IBR Feature Extraction").

Each training image goes once through a frozen encoder; a learnable projection
``P`` maps the encoder outputs to ``C_r`` channels and fuses them into one
reference map per view of size ``(H//2, W//2)``. An anchor's IBR feature is the
bilinear sample of that map at its projection, averaged over the training views
where it lies in front of the camera and inside the image.

Encoders (``IBRFeatures(encoder=...)``):

* ``"dino"``: DINO-pretrained ResNet-50 (outputs of ``layer1``..``layer4``,
  strides 4..32) and ViT-B/8 (patch tokens at stride 8 and the CLS token),
  written in plain torch with the parameter names of the official checkpoints
  ``dino_resnet50_pretrain.pth`` (torchvision ``resnet50`` names) and
  ``dino_vitbase8_pretrain.pth`` (DINO ``vision_transformer.py`` names). ``P``
  is a 1x1 convolution per ResNet stage, bilinearly upsampled, plus a linear
  map of the patch tokens, repeated to pixels ("broadcast"), plus a linear map
  of the CLS token added everywhere.
* ``"pyramid"``: a weight-free pyramid of the image and its Sobel gradients at
  1/2, 1/4, 1/8 and 1/16 resolution (6 channels per level: RGB, gx, gy,
  |grad|); ``P`` is a 1x1 convolution per level, bilinearly upsampled.
* ``"none"``: no IBR feature; :func:`build_ibr` returns ``None``.

Pixel convention (as :mod:`dibrgs_core.camera.pinhole`): pixel ``(i, j)`` covers
``[i, i+1] x [j, j+1]``, so full-resolution coordinate ``u`` maps to the
normalised grid coordinate ``2 u / W - 1`` of ``grid_sample(align_corners=False)``
for a map of any size that covers the whole image.

Only ``P`` is stored in ``state_dict``; the frozen encoder outputs are
recomputed from the images when the object is rebuilt (resume).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ...camera.pinhole import Camera
from ...common.errors import InputError
from ...common.modes import IbrEncoder, choices
from .pyramid import image_pyramid
from .resnet import dino_resnet50
from .vit import dino_vitb8
from .weights import load_backbone_weights

log = logging.getLogger("dibrgs.ibr_features")

#: Encoders that can be built (``auto`` picks one of them).
ENCODERS = tuple(e for e in choices(IbrEncoder) if e != "auto")
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# ---------------------------------------------------------------------------
# The module used by the trainer
# ---------------------------------------------------------------------------
class IBRFeatures(nn.Module):
    """Per-anchor IBR features from the training images (see the module docstring).

    Args:
        encoder: ``"dino"`` or ``"pyramid"`` (use :func:`build_ibr` for ``"none"``).
        images: (V,3,H,W) training images in [0,1].
        cameras: the V training cameras (their width/height must be W/H).
        c_r: reference feature channels (paper: 32).
        dino_resnet, dino_vit: local paths of ``dino_resnet50_pretrain.pth``
            and ``dino_vitbase8_pretrain.pth`` (both required for ``"dino"``).
        resnet, vit: already-loaded backbones to use instead of the paths
            (tests build small ones).

    The frozen encoder runs once here, without gradients; only the projection
    ``P`` (:meth:`projection_parameters`) is trainable and saved in
    ``state_dict``.
    """

    def __init__(self, encoder: str, images: torch.Tensor, cameras: Sequence[Camera], c_r: int = 32,
                 dino_resnet: str | Path | None = None, dino_vit: str | Path | None = None, *,
                 resnet: nn.Module | None = None, vit: nn.Module | None = None):
        super().__init__()
        if encoder not in ("dino", "pyramid"):
            raise ValueError(f"IBRFeatures encoder must be 'dino' or 'pyramid', got {encoder!r}")
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"images must be (V,3,H,W), got {tuple(images.shape)}")
        V, _, H, W = images.shape
        if len(cameras) != V:
            raise ValueError(f"{V} images but {len(cameras)} cameras")
        for c in cameras:
            if (c.width, c.height) != (W, H):
                raise ValueError(f"camera {c.name!r} is {c.width}x{c.height}, images are {W}x{H}")
        self.encoder = encoder
        self.c_r = int(c_r)
        self.width, self.height = int(W), int(H)
        self.map_size = (max(1, H // 2), max(1, W // 2))
        images = images.detach().float().clamp(0.0, 1.0)
        self.register_buffer("K", torch.tensor(np.stack([c.K for c in cameras]), dtype=torch.float32),
                             persistent=False)
        self.register_buffer("w2c", torch.tensor(np.stack([c.w2c for c in cameras]), dtype=torch.float32),
                             persistent=False)

        self._levels: list[str] = []
        if encoder == "pyramid":
            feats = image_pyramid(images)
            self.proj = nn.ModuleDict({f"level{i}": nn.Conv2d(f.shape[1], self.c_r, 1)
                                       for i, f in enumerate(feats)})
            for i, f in enumerate(feats):
                self._add_feature(f"level{i}", f)
        else:
            resnet, vit = self._backbones(dino_resnet, dino_vit, resnet, vit)
            stages, cls, tokens = self._run_dino(images, resnet, vit)
            proj: dict[str, nn.Module] = {f"stage{i + 1}": nn.Conv2d(f.shape[1], self.c_r, 1)
                                          for i, f in enumerate(stages)}
            proj["vit_tokens"] = nn.Linear(tokens.shape[1], self.c_r)
            proj["vit_cls"] = nn.Linear(cls.shape[1], self.c_r)
            self.proj = nn.ModuleDict(proj)
            for i, f in enumerate(stages):
                self._add_feature(f"stage{i + 1}", f)
            self._add_feature("vit_tokens", tokens)
            self.register_buffer("feat_vit_cls", cls, persistent=False)
        self._cache: tuple[tuple, torch.Tensor] | None = None

    # -- construction helpers ----------------------------------------------
    def _add_feature(self, name: str, f: torch.Tensor) -> None:
        self.register_buffer(f"feat_{name}", f.contiguous(), persistent=False)
        self._levels.append(name)

    @staticmethod
    def _backbones(resnet_path, vit_path, resnet, vit) -> tuple[nn.Module, nn.Module]:
        if resnet is None:
            if resnet_path is None:
                raise InputError(None, "IBR encoder 'dino' needs the DINO ResNet-50 weights "
                                       "(dino_resnet50_pretrain.pth)")
            resnet = dino_resnet50()
            load_backbone_weights(resnet, resnet_path, "DINO ResNet-50")
        if vit is None:
            if vit_path is None:
                raise InputError(None, "IBR encoder 'dino' needs the DINO ViT-B/8 weights "
                                       "(dino_vitbase8_pretrain.pth)")
            vit = dino_vitb8()
            load_backbone_weights(vit, vit_path, "DINO ViT-B/8")
        return resnet.eval(), vit.eval()

    @staticmethod
    @torch.no_grad()
    def _run_dino(images: torch.Tensor, resnet: nn.Module, vit: nn.Module
                  ) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
        mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        x = (images - mean) / std
        H, W = x.shape[-2:]
        p = getattr(vit, "patch", 8)
        # The ViT needs multiples of the patch size; resizing keeps the image
        # extent, so token (a, b) still covers the same fraction of the image.
        Hp, Wp = max(p, round(H / p) * p), max(p, round(W / p) * p)
        stages: list[list[torch.Tensor]] = [[], [], [], []]
        cls_l, tok_l = [], []
        for v in range(x.shape[0]):  # one view at a time bounds the memory
            xv = x[v:v + 1]
            for i, f in enumerate(resnet(xv)):
                stages[i].append(f)
            xv = xv if (Hp, Wp) == (H, W) else F.interpolate(xv, size=(Hp, Wp), mode="bilinear",
                                                              align_corners=False)
            c, t = vit(xv)
            cls_l.append(c)
            tok_l.append(t)
            log.info("DINO features: view %d/%d", v + 1, x.shape[0])
        return [torch.cat(s) for s in stages], torch.cat(cls_l), torch.cat(tok_l)

    # -- public API ----------------------------------------------------------
    def projection_parameters(self) -> list[nn.Parameter]:
        """The trainable projection ``P`` (paper: AdamW, lr 1e-4, frozen after 2/3 of training)."""
        return list(self.proj.parameters())

    def feature_maps(self) -> torch.Tensor:
        """Fused reference maps ``F_v`` (V, C_r, H//2, W//2) through the current ``P``.

        ``P`` is applied at each level's own resolution (a 1x1 convolution is a
        per-pixel linear map), then ResNet/pyramid levels are upsampled
        bilinearly, ViT tokens repeated (nearest) and the CLS projection added
        everywhere. Cached while no gradient can flow into ``P`` (frozen or
        under ``torch.no_grad``); the cache key holds the parameters' versions,
        so loading or changing weights invalidates it.
        """
        params = self.projection_parameters()
        needs_grad = torch.is_grad_enabled() and any(p.requires_grad for p in params)
        key = tuple(p._version for p in params) + tuple(p.data_ptr() for p in params)
        if not needs_grad and self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        out = None
        for name in self._levels:
            f = getattr(self, f"feat_{name}").permute(0, 2, 3, 1)  # channels last
            m = self.proj[name]
            y = F.linear(f, m.weight.reshape(m.weight.shape[0], -1), m.bias).permute(0, 3, 1, 2)
            if name == "vit_tokens":
                y = F.interpolate(y, size=self.map_size, mode="nearest")  # repeat each token over its patch
            else:
                y = F.interpolate(y, size=self.map_size, mode="bilinear", align_corners=False)
            out = y if out is None else out + y
        if self.encoder == "dino":
            out = out + self.proj["vit_cls"](self.feat_vit_cls)[:, :, None, None]
        if needs_grad:
            self._cache = None
        else:
            out = out.detach()
            self._cache = (key, out)
        return out

    def forward(self, anchors: torch.Tensor) -> torch.Tensor:
        """IBR feature (N, C_r) of anchors (N,3) in world coordinates.

        Bilinear ``grid_sample`` (align_corners=False, border) of
        :meth:`feature_maps` at each anchor's projection, averaged over the
        views where it is in front (z > 0) and inside the image; anchors seen
        by no view get zeros. Anchor positions receive no gradient from here
        (the features serve appearance, not geometry).
        """
        maps = self.feature_maps()
        X = anchors.detach().to(device=maps.device, dtype=maps.dtype)
        if X.shape[0] == 0:
            return maps.new_zeros((0, self.c_r))
        R, t = self.w2c[:, :3, :3], self.w2c[:, :3, 3]
        Xc = torch.einsum("vij,nj->vni", R, X) + t[:, None, :]  # (V,N,3)
        z = Xc[..., 2]
        front = z > 1e-6
        zs = torch.where(front, z, torch.ones_like(z))
        pix = torch.einsum("vij,vnj->vni", self.K, Xc / zs[..., None])
        u, v = pix[..., 0], pix[..., 1]
        ok = front & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        grid = torch.stack([2.0 * u / self.width - 1.0, 2.0 * v / self.height - 1.0], dim=-1)
        grid = torch.where(ok[..., None], grid, torch.zeros_like(grid))  # no NaN/Inf into grid_sample
        s = F.grid_sample(maps, grid[:, None], mode="bilinear", padding_mode="border",
                          align_corners=False)[:, :, 0]  # (V,C,N)
        w = ok.to(maps.dtype)
        total = (s * w[:, None]).sum(0)  # (C,N)
        return (total / w.sum(0).clamp(min=1.0)).T


def resolve_encoder(requested: str, dino_paths: tuple[str | Path | None, str | Path | None]
                    ) -> tuple[str, str]:
    """Pick the IBR encoder: returns ``(name in ENCODERS, reason for the report)``.

    ``dino_paths`` is ``(resnet50 checkpoint, vitb8 checkpoint)``, each possibly
    None. ``"auto"`` gives ``"dino"`` when both are given, else ``"pyramid"``.
    Asking for ``"dino"`` without both files raises :class:`InputError`.
    """
    resnet_p, vit_p = dino_paths
    have = resnet_p is not None and vit_p is not None
    if requested in ("dino", "auto") and have:
        for p in (resnet_p, vit_p):
            if not Path(p).is_file():
                raise InputError(p, "DINO weights not found")
        why = "requested" if requested == "dino" else "auto: DINO ResNet-50 and ViT-B/8 weights given"
        return "dino", why
    if requested == "dino":
        raise InputError(None, "IBR encoder 'dino' needs both DINO weight files: ResNet-50 "
                               "(dino_resnet50_pretrain.pth) and ViT-B/8 (dino_vitbase8_pretrain.pth)")
    if requested == "auto":
        return "pyramid", ("auto: no DINO weights given (both ResNet-50 and ViT-B/8 are needed), "
                           "using the weight-free image/gradient pyramid")
    if requested in ("pyramid", "none"):
        return requested, "requested"
    raise InputError(None, f"unknown IBR encoder {requested!r}; choose auto, dino, pyramid or none")


def build_ibr(name: str, images: torch.Tensor, cameras: Sequence[Camera], c_r: int = 32,
              dino_resnet: str | Path | None = None, dino_vit: str | Path | None = None
              ) -> IBRFeatures | None:
    """IBRFeatures for ``name`` in {"dino", "pyramid"}; None for ``"none"``."""
    if name == "none":
        return None
    return IBRFeatures(name, images, cameras, c_r=c_r, dino_resnet=dino_resnet, dino_vit=dino_vit)
