"""LPIPS (Zhang et al. 2018) in plain torch, from local weights only.

Weights the user gives (``--lpips FILE``): a state dict in the official ``lpips``
package layout (``net.slice{1..5}.*`` backbone + ``lin{0..4}.model.1.weight`` 1x1
heads, as ``lpips.LPIPS(net=...).state_dict()``), or only the heads (the package's
``weights/v0.1/{vgg,alex}.pth``) together with ``--lpips-backbone`` (the torchvision
``vgg16`` / ``alexnet`` state dict, ``features.*`` keys). Nothing is downloaded.
"""
from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from ..common.errors import InputError


_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]


# torchvision feature indices that end each LPIPS slice (after the ReLU).
_VGG_SLICES = [(0, 4), (4, 9), (9, 16), (16, 23), (23, 30)]


_VGG_CH = [64, 128, 256, 512, 512]


_ALEX_SLICES = [(0, 2), (2, 5), (5, 8), (8, 10), (10, 12)]


_ALEX_CH = [64, 192, 384, 256, 256]


#: The shortest image side each backbone's five slices have features for: AlexNet's stride-4
#: convolution and two 3x3 poolings leave nothing of 30 pixels, VGG's four 2x2 poolings nothing of 15.
MIN_SIDE = {"alex": 31, "vgg": 16}


def _vgg_features() -> nn.Sequential:
    layers: list[nn.Module] = []
    c = 3
    for v in _VGG_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=False)]
            c = v
    return nn.Sequential(*layers)


def _alex_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU())


class _Lin(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(c, 1, 1, bias=False))


class LPIPS(nn.Module):
    """LPIPS (Zhang et al. 2018) with the ``lpips`` package's module names.

    ``net.slice{k}`` hold the backbone layers under their torchvision indices,
    ``lin{k}.model.1`` the learned 1x1 heads, ``scaling_layer`` the input
    normalisation. Inputs are (H,W,3) images in [0,1].
    """

    def __init__(self, net: str = "vgg") -> None:
        super().__init__()
        if net not in ("vgg", "alex"):
            raise ValueError(f"LPIPS net must be 'vgg' or 'alex', got {net!r}")
        feats = _vgg_features() if net == "vgg" else _alex_features()
        slices, chans = (_VGG_SLICES, _VGG_CH) if net == "vgg" else (_ALEX_SLICES, _ALEX_CH)
        self.net = nn.Module()
        for k, (a, b) in enumerate(slices, 1):
            s = nn.Sequential()
            for i in range(a, b):
                s.add_module(str(i), feats[i])
            setattr(self.net, f"slice{k}", s)
        self.n_slices = len(slices)
        self.net_name, self.min_side = net, MIN_SIDE[net]
        for k, c in enumerate(chans):
            setattr(self, f"lin{k}", _Lin(c))
        self.scaling_layer = nn.Module()
        self.scaling_layer.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.scaling_layer.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.eval()

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        def prep(x: torch.Tensor) -> torch.Tensor:
            x = x.permute(2, 0, 1)[None].float() * 2.0 - 1.0
            return (x - self.scaling_layer.shift) / self.scaling_layer.scale

        xa, xb = prep(a), prep(b)
        total = torch.zeros(())
        for k in range(self.n_slices):
            s = getattr(self.net, f"slice{k + 1}")
            xa, xb = s(xa), s(xb)
            na = xa / (xa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = xb / (xb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = getattr(self, f"lin{k}").model[1]((na - nb) ** 2)
            total = total + d.mean()
        return total


def load_lpips(weights: str | Path, backbone: str | Path | None = None, net: str | None = None) -> LPIPS:
    """LPIPS from local files (see the module docstring). ``InputError`` names a bad file."""
    weights = Path(weights)
    if not weights.is_file():
        raise InputError(weights, "LPIPS weights not found")
    try:
        sd = torch.load(weights, map_location="cpu", weights_only=True)
    except Exception as e:
        raise InputError(weights, f"not a torch state dict ({e})") from None
    if not isinstance(sd, dict) or "lin0.model.1.weight" not in sd:
        raise InputError(weights, "expected LPIPS weights with keys like 'lin0.model.1.weight' "
                                  "(the lpips package layout)")
    if net is None:
        net = "vgg" if sd["lin0.model.1.weight"].shape[1] == 64 and sd["lin1.model.1.weight"].shape[1] == 128 \
            else "alex"
    model = LPIPS(net)
    full = {k: v for k, v in sd.items() if k.startswith(("lin", "net.", "scaling_layer."))}
    if not any(k.startswith("net.") for k in full):
        if backbone is None:
            raise InputError(weights, "these LPIPS weights hold only the linear heads; give the "
                                      f"torchvision {net} backbone with --lpips-backbone")
        bb = Path(backbone)
        if not bb.is_file():
            raise InputError(bb, "LPIPS backbone weights not found")
        try:
            bsd = torch.load(bb, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises many types for corrupt files
            raise InputError(bb, f"not a torch state dict ({e})") from None
        slices = _VGG_SLICES if net == "vgg" else _ALEX_SLICES
        for k, (a, b) in enumerate(slices, 1):
            for i in range(a, b):
                for p in ("weight", "bias"):
                    key = f"features.{i}.{p}"
                    if key in bsd:
                        full[f"net.slice{k}.{i}.{p}"] = bsd[key]
    full.setdefault("scaling_layer.shift", model.scaling_layer.shift)
    full.setdefault("scaling_layer.scale", model.scaling_layer.scale)
    missing, unexpected = model.load_state_dict(full, strict=False)
    if missing:
        raise InputError(weights, f"LPIPS weights are missing {len(missing)} tensors, e.g. {missing[:3]}")
    return model
