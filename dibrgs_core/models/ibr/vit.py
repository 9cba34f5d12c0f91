"""ViT-B/8 in plain torch with the parameter names of DINO's ``vision_transformer.py``, for
``dino_vitbase8_pretrain.pth``: the CLS token and the patch tokens at stride 8."""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


class _PatchEmbed(nn.Module):
    def __init__(self, patch: int, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=patch, stride=patch)


class _Attention(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, dim * 3, bias=True)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, N, C = x.shape
        q, k, v = self.qkv(x).reshape(B, N, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(q, k, v)  # softmax(q k^T / sqrt(d)) v
        return self.proj(y.transpose(1, 2).reshape(B, N, C))


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class _Block(nn.Module):
    def __init__(self, dim: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = _Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = _Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class ViTFeatures(nn.Module):
    """Vision transformer returning (CLS token (B, dim), patch tokens (B, dim, H/p, W/p)).

    ``patch=8, dim=768, depth=12, heads=12`` is ViT-B/8; position embeddings are
    stored for a 224x224 input (as in the checkpoint) and bicubically resized
    to the token grid of the actual input. Input height and width must be
    multiples of ``patch``.
    """

    def __init__(self, patch: int = 8, dim: int = 768, depth: int = 12, heads: int = 12,
                 mlp_ratio: float = 4.0, img_size: int = 224):
        super().__init__()
        self.patch = patch
        self.patch_embed = _PatchEmbed(patch, dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, (img_size // patch) ** 2 + 1, dim))
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.trunc_normal_(self.cls_token, std=0.02)
        self.blocks = nn.ModuleList([_Block(dim, heads, mlp_ratio) for _ in range(depth)])
        self.norm = nn.LayerNorm(dim, eps=1e-6)

    def _pos(self, h: int, w: int) -> torch.Tensor:
        pe = self.pos_embed
        n = pe.shape[1] - 1
        g = int(round(n ** 0.5))
        if g * g == n and (h, w) == (g, g):
            return pe
        grid = pe[:, 1:].reshape(1, g, g, -1).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
        return torch.cat([pe[:, :1], grid.flatten(2).transpose(1, 2)], dim=1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, _, H, W = x.shape
        if H % self.patch or W % self.patch:
            raise ValueError(f"ViT input {H}x{W} is not a multiple of the patch size {self.patch}")
        t = self.patch_embed.proj(x)
        h, w = t.shape[-2:]
        t = torch.cat([self.cls_token.expand(B, -1, -1), t.flatten(2).transpose(1, 2)], dim=1)
        t = t + self._pos(h, w)
        for blk in self.blocks:
            t = blk(t)
        t = self.norm(t)
        return t[:, 0], t[:, 1:].transpose(1, 2).reshape(B, -1, h, w)


def dino_vitb8() -> ViTFeatures:
    """Full-size ViT-B/8 (random weights until loaded)."""
    return ViTFeatures(patch=8, dim=768, depth=12, heads=12)
