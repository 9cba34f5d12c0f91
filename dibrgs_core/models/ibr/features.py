"""IBR reference features for neural Gaussian anchors (paper: "IBR Feature Extraction").

Each training image goes once through a frozen encoder; a learnable projection
``P`` maps the encoder outputs to ``C_r`` channels and fuses them into one
reference map per view of size ``(H//2, W//2)``, half its own image's (photos may differ in
size; views of one size share their feature tensors). An anchor's IBR feature is the
bilinear sample of that map at its projection, averaged over the training views
where it lies in front of the camera and inside the image, on a pixel that holds data. Training never builds
the maps: ``P`` is affine and the upsampling, sampling and averaging are blends
with weights summing to 1, so each anchor's raw encoder features are sampled once
(:mod:`.sampling`) and ``P`` is one small matmul an iteration (:meth:`IBRFeatures.forward`).

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
from .projection import project_rows
from .pyramid import image_pyramid
from .resnet import dino_resnet50
from .sampling import upsampled_taps
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
        images: the V training images in [0,1], each (3,H,W) of its camera's size (a (V,3,H,W)
            tensor when they share one).
        cameras: the V training cameras.
        c_r: reference feature channels (paper: 32).
        dino_resnet, dino_vit: local paths of ``dino_resnet50_pretrain.pth``
            and ``dino_vitbase8_pretrain.pth`` (both required for ``"dino"``).
        resnet, vit: already-loaded backbones to use instead of the paths
            (tests build small ones).

    The frozen encoder runs once here, without gradients; only the projection
    ``P`` (:meth:`projection_parameters`) is trainable and saved in
    ``state_dict``.
    """

    def __init__(self, encoder: str, images: torch.Tensor | Sequence[torch.Tensor], cameras: Sequence[Camera],
                 c_r: int = 32, dino_resnet: str | Path | None = None, dino_vit: str | Path | None = None, *,
                 resnet: nn.Module | None = None, vit: nn.Module | None = None,
                 valid: Sequence[np.ndarray | None] | None = None):
        super().__init__()
        if encoder not in ("dino", "pyramid"):
            raise ValueError(f"IBRFeatures encoder must be 'dino' or 'pyramid', got {encoder!r}")
        images = list(images)
        for im in images:
            if im.dim() != 3 or im.shape[0] != 3:
                raise ValueError(f"each image must be (3,H,W), got {tuple(im.shape)}")
        V = len(images)
        if len(cameras) != V:
            raise ValueError(f"{V} images but {len(cameras)} cameras")
        for c, im in zip(cameras, images):
            if (c.width, c.height) != (im.shape[2], im.shape[1]):
                raise ValueError(f"camera {c.name!r} is {c.width}x{c.height}, its image {im.shape[2]}x{im.shape[1]}")
        self.encoder = encoder
        self.c_r = int(c_r)
        # per view, bool (H, W) pixels with data or None: a view does not see what lands elsewhere
        self._valid = [None if m is None else torch.as_tensor(np.asarray(m, bool)) for m in (valid or [None] * V)]
        # Views of one size share their feature tensors (a group); the groups keep the
        # views' order within them.
        by_size: dict[tuple[int, int], list[int]] = {}
        for i, c in enumerate(cameras):
            by_size.setdefault((int(c.width), int(c.height)), []).append(i)
        self._groups = [(torch.tensor(ix), (max(1, H // 2), max(1, W // 2))) for (W, H), ix in by_size.items()]
        self.register_buffer("size", torch.tensor([[c.width, c.height] for c in cameras], dtype=torch.float32),
                             persistent=False)
        self.register_buffer("K", torch.tensor(np.stack([c.K for c in cameras]), dtype=torch.float32),
                             persistent=False)
        self.register_buffer("w2c", torch.tensor(np.stack([c.w2c for c in cameras]), dtype=torch.float32),
                             persistent=False)

        self._levels: list[str] = []
        self._raw_dim = 0
        batches = [torch.stack([images[i] for i in ix.tolist()]).detach().float().clamp(0.0, 1.0)
                   for ix, _ in self._groups]
        if encoder == "pyramid":
            feats = [image_pyramid(b) for b in batches]  # per group, per level
            names = [f"level{i}" for i in range(len(feats[0]))]
        else:
            resnet, vit = self._backbones(dino_resnet, dino_vit, resnet, vit)
            feats, cls = [], torch.zeros(V, 0)
            for (ix, _), b in zip(self._groups, batches):
                stages, c, tokens = self._run_dino(b, resnet, vit)
                feats.append(stages + [tokens])
                cls = c.new_zeros(V, c.shape[1]) if cls.shape[1] == 0 else cls
                cls[ix] = c
            names = [f"stage{i + 1}" for i in range(len(feats[0]) - 1)] + ["vit_tokens"]
            self.register_buffer("feat_vit_cls", cls, persistent=False)
        proj: dict[str, nn.Module] = {}
        for k, name in enumerate(names):
            ch = feats[0][k].shape[1]
            proj[name] = nn.Linear(ch, self.c_r) if name == "vit_tokens" else nn.Conv2d(ch, self.c_r, 1)
            self._add_feature(name, [f[k] for f in feats])
        if encoder == "dino":
            proj["vit_cls"] = nn.Linear(cls.shape[1], self.c_r)
        self.proj = nn.ModuleDict(proj)
        self._p_cache: tuple[nn.ModuleDict, list[nn.Module], tuple[nn.Parameter, ...]] | None = None  # see _p
        # anchor_rows cache: (position bits (N,3) int32, rows (N,D+1), view weights (N,V))
        self._rows: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self._rows_generation = 0
        # The anchor tensor those rows were read from and its version counter then (kept
        # referenced, so that its memory cannot be reused by another tensor meanwhile).
        self._rows_of: tuple[torch.Tensor, int] | None = None
        self._projected: tuple[tuple, torch.Tensor] | None = None

    # -- construction helpers ----------------------------------------------
    def _add_feature(self, name: str, per_group: list[torch.Tensor]) -> None:
        # channels-last memory: (V*h*w, C) rows for the per-anchor gathers are a view
        for g, f in enumerate(per_group):
            self.register_buffer(f"feat_{name}_{g}", f.contiguous(memory_format=torch.channels_last),
                                 persistent=False)
        self._levels.append(name)
        self._raw_dim += per_group[0].shape[1]

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
        return list(self._p()[2])

    def _p(self) -> tuple[nn.ModuleDict, list[nn.Module], tuple[nn.Parameter, ...]]:
        """``proj``, its layers of ``_levels`` in order and its parameters, read once for the ModuleDict
        in place (another assigned is read anew): a walk of it cost 45 us of every training step."""
        proj = self.proj
        if self._p_cache is None or self._p_cache[0] is not proj:
            self._p_cache = (proj, [proj[n] for n in self._levels], tuple(proj.parameters()))
        return self._p_cache

    def feature_maps(self) -> list[torch.Tensor]:
        """Fused reference maps ``F_v`` through the current ``P``: per view a (C_r, H//2, W//2)
        map of its own size.

        ``P`` is applied at each level's own resolution (a 1x1 convolution is a
        per-pixel linear map), then ResNet/pyramid levels are upsampled
        bilinearly, ViT tokens repeated (nearest) and the CLS projection added
        everywhere. :meth:`forward` gives what bilinear sampling of these maps
        gives, without building them; this is its definition (tests, inspection).
        """
        maps: list[torch.Tensor | None] = [None] * self.K.shape[0]
        for g, (ix, map_size) in enumerate(self._groups):
            out = None
            for name in self._levels:
                f = getattr(self, f"feat_{name}_{g}").permute(0, 2, 3, 1)  # channels last
                m = self.proj[name]
                y = F.linear(f, m.weight.reshape(m.weight.shape[0], -1), m.bias).permute(0, 3, 1, 2)
                mode = "nearest" if name == "vit_tokens" else "bilinear"  # a token repeated over its patch
                y = F.interpolate(y, size=map_size, mode=mode, **({} if mode == "nearest" else
                                                                  {"align_corners": False}))
                out = y if out is None else out + y
            if self.encoder == "dino":
                out = out + self.proj["vit_cls"](self.feat_vit_cls[ix])[:, :, None, None]
            for k, i in enumerate(ix.tolist()):
                maps[i] = out[k]
        return maps

    def forward(self, anchors: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """IBR features (M, C_r) of ``anchors[mask]`` ((N,3) world coordinates; all when
        ``mask`` is None).

        Equal (to float rounding) to bilinear ``grid_sample`` (align_corners=False, border)
        of :meth:`feature_maps` at each anchor's projection, averaged over the views where
        it is in front (z > 0) and inside the image; anchors seen by no view get zeros.
        Computed the other way round: ``P`` is affine and the upsampling, the sampling and
        the view average are blends whose weights sum to 1, so the anchor's raw encoder
        features are sampled and averaged once (:meth:`anchor_rows`, cached per anchor
        position) and ``P`` is one matmul per call. Anchor positions receive no gradient
        from here (the features serve appearance, not geometry).
        """
        rows, omega = self.anchor_rows(anchors)
        params = self._p()[2]
        if torch.is_grad_enabled() and any(p.requires_grad for p in params):
            return self._project(rows, omega, mask)
        # No gradient can reach P (frozen, or evaluation): project every anchor once and
        # keep it while neither P (its versions) nor the anchors change.
        key = (self._rows_generation,) + tuple((p._version, p.data_ptr()) for p in params)
        if self._projected is None or self._projected[0] != key:
            with torch.no_grad():
                self._projected = (key, self._project(rows, omega))
        out = self._projected[1]
        return out if mask is None else out[mask]

    def anchor_rows(self, anchors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw encoder features, view-averaged, of each anchor (N, D+1) (last column: 1 if
        any view sees it, else 0) and its view weights (N, V) (1/count where seen, else 0).

        Cached for the last anchor tensor by the bits of its positions; when anchors are
        added, pruned or reordered, rows of positions already cached are carried over
        and only new positions are sampled. The tensor cached last, unchanged since (same
        memory, layout and version counter, which every in-place write bumps), is a hit
        without comparing its bits (a comparison of the whole tensor each training step).
        """
        seen = self._rows_of  # set with self._rows, never without
        if (seen is not None and anchors.data_ptr() == seen[0].data_ptr() and anchors._version == seen[1]
                and anchors.shape == seen[0].shape and anchors.stride() == seen[0].stride()
                and anchors.dtype == seen[0].dtype):
            return self._rows[1], self._rows[2]
        X = anchors.detach().to(dtype=torch.float32, device=self.K.device).contiguous()
        bits = X.view(torch.int32)
        c = self._rows
        if c is not None and c[0].shape == bits.shape and torch.equal(c[0], bits):
            self._rows_of = (anchors.detach(), anchors._version)
            return c[1], c[2]
        n, V = X.shape[0], self.K.shape[0]
        rows = X.new_zeros((n, self._raw_dim + 1))
        omega = X.new_zeros((n, V))
        todo = torch.ones(n, dtype=torch.bool)
        if c is not None and c[0].shape[0] and n:
            _, inv = torch.unique(torch.cat([c[0], bits]), dim=0, return_inverse=True)
            slot = torch.full((int(inv.max()) + 1,), -1, dtype=torch.long)
            slot[inv[:c[0].shape[0]]] = torch.arange(c[0].shape[0])
            src = slot[inv[c[0].shape[0]:]]
            todo = src < 0
            rows[~todo], omega[~todo] = c[1][src[~todo]], c[2][src[~todo]]
        if todo.any():
            rows[todo], omega[todo] = self._sample_rows(X[todo])
        self._rows = (bits.clone(), rows, omega)
        self._rows_of = (anchors.detach(), anchors._version)
        self._rows_generation += 1
        return rows, omega

    # -- the factorised path -------------------------------------------------------
    @torch.no_grad()
    def _sample_rows(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`anchor_rows` of positions ``X`` (M,3), computed.

        Element-wise arithmetic only (no matmul, whose blocking depends on M), so a row is
        bit-identical whichever anchors it is computed with: a resumed run, which samples
        every anchor at once, matches one that sampled them as they appeared.
        """
        R, t, K = self.w2c[:, None, :3, :3], self.w2c[:, None, :3, 3], self.K[:, None]
        x, y, zz = X[:, 0], X[:, 1], X[:, 2]
        xc, yc, z = (R[..., i, 0] * x + R[..., i, 1] * y + R[..., i, 2] * zz + t[..., i] for i in range(3))
        front = z > 1e-6
        zs = torch.where(front, z, torch.ones_like(z))
        xn, yn = xc / zs, yc / zs
        u = K[..., 0, 0] * xn + K[..., 0, 1] * yn + K[..., 0, 2]
        v = K[..., 1, 0] * xn + K[..., 1, 1] * yn + K[..., 1, 2]
        W, H = self.size[:, 0, None], self.size[:, 1, None]  # (V,1) each view's own size
        ok = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        for i, m in enumerate(self._valid):
            if m is not None:  # the view holds no data there: it does not see the anchor
                ok[i] &= m[v[i].clamp(0, m.shape[0] - 1).long(), u[i].clamp(0, m.shape[1] - 1).long()]
        grid = torch.stack([2.0 * u / W - 1.0, 2.0 * v / H - 1.0], dim=-1)
        grid = torch.where(ok[..., None], grid, torch.zeros_like(grid))  # no NaN/Inf into the taps
        w = ok.float()
        omega = (w / w.sum(0).clamp(min=1.0)).T.contiguous()  # (M,V)
        cols = []
        for name in self._levels:
            mode = "nearest" if name == "vit_tokens" else "bilinear"
            col = None
            for g, (ix, map_size) in enumerate(self._groups):
                f = getattr(self, f"feat_{name}_{g}")  # (Vg,C,h,w), channels-last memory
                Vg, C, h, wd = f.shape
                idx, wt = upsampled_taps(grid[ix], (h, wd), map_size, mode)  # (Vg,M,16)
                idx = idx + (torch.arange(Vg) * (h * wd))[:, None, None]
                wt = wt * omega.T[ix, :, None]
                flat = f.permute(0, 2, 3, 1).reshape(Vg * h * wd, C)  # a view: no copy
                part = F.embedding_bag(idx.permute(1, 0, 2).reshape(X.shape[0], -1), flat,
                                       per_sample_weights=wt.permute(1, 0, 2).reshape(X.shape[0], -1), mode="sum")
                col = part if col is None else col + part
            cols.append(col)
        cols.append((omega.sum(1, keepdim=True) > 0).float())
        return torch.cat(cols, 1), omega

    def _project(self, rows: torch.Tensor, omega: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """``P`` applied to :meth:`anchor_rows` (those ``mask`` selects): one matmul (weights of
        every level side by side, their biases summed on the "seen" column) plus, for DINO, the
        CLS term (``omega``: the rows' view weights, read only then)."""
        levels = self._p()[1]
        out = project_rows(rows, [m.weight for m in levels], [m.bias for m in levels], mask)
        if self.encoder == "dino":
            out = out + (omega if mask is None else omega[mask]) @ self.proj["vit_cls"](self.feat_vit_cls)
        return out


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
              dino_resnet: str | Path | None = None, dino_vit: str | Path | None = None,
              valid: Sequence[np.ndarray | None] | None = None) -> IBRFeatures | None:
    """IBRFeatures for ``name`` in {"dino", "pyramid"}; None for ``"none"``."""
    if name == "none":
        return None
    return IBRFeatures(name, images, cameras, c_r=c_r, dino_resnet=dino_resnet, dino_vit=dino_vit, valid=valid)
