"""Reference rasterizer: tile binning and alpha compositing in plain torch.

Runs on any device, is differentiable by autograd, and keeps memory bounded
by processing tiles in chunks under activation checkpointing. It is the
oracle for the fast C++ path and implements exactly the same rules:

* 16x16 pixel tiles. A visible Gaussian is binned to the tiles of its 3-sigma
  square ``floor((m - r) / 16) .. ceil((m + r) / 16)`` (gsplat's rule) - it
  never contributes outside those tiles. Tiles are additionally skipped when
  they cannot contain a pixel with ``alpha >= 1/255`` (the bounding box of
  the ellipse ``q <= 2 ln(255 o)``, inflated by what float32 rounding of q
  may reach, more for thin Gaussians);
  this cull never changes a result, it only saves work.
* Per pixel, Gaussians in increasing depth (ties by index). With
  ``d = mean2d - (pixel + 0.5)`` and ``power = -0.5 (a dx^2 + c dy^2) - b dx dy``:
  skip when ``power > 0``; ``alpha = min(0.99, opacity * exp(power))``; skip
  when ``alpha < 1/255``; stop (without this Gaussian) when
  ``T * (1 - alpha) < 1e-4``; else add ``alpha T feature`` and ``T *= 1 - alpha``.
"""
from __future__ import annotations


import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1.0e-4
# Elements of a (tiles, 256, K) chunk tensor, and the longest segment of a
# tile's list composited at once; together they bound the reference's memory.
_CHUNK_ELEMS = 1 << 22
_SEGMENT = 2048


def tile_rects(
    means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, width: int, height: int
) -> Tensor:
    """Per-Gaussian tile rectangle ``(x0, x1, y0, y1)`` (N, 4) int64, end-exclusive.

    The 3-sigma tile square intersected with the tiles that may hold a pixel
    with ``alpha >= 1/255``; empty (x1 <= x0 or y1 <= y0) for culled Gaussians.
    """
    tx, ty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    m = means2d.detach().to(torch.float64)
    con = conics.detach().to(torch.float64)
    op = opacities.detach().to(torch.float64)
    r = radii.to(torch.float64)
    # Half-extents of {q <= t}: sqrt(t * Sigma_xx), Sigma = conic^-1, for the
    # level t = 2 ln(255 o), inflated so float32 rounding of q stays inside: 1 %
    # + 0.01, and about 4 eps cond q more for a thin Gaussian (its terms cancel;
    # cond <= (a + c)^2 / det); past twice the level, or not positive definite,
    # no cull (the C++ binning's rule).
    a, b, c = con.unbind(1)
    det = a * c - b * b
    grow = 8.0 * torch.finfo(torch.float32).eps * (a + c) ** 2 / det
    t = (2.0 * torch.log(torch.clamp(op * 255.0, min=1e-300)) * 1.01 + 0.01) * (1.0 + grow)
    t = torch.where((det > 0) & (grow <= 1.0), t, torch.full_like(t, float("inf")))
    t = torch.where(op * 255.0 >= 1.0, t, torch.full_like(t, -1.0))
    det = torch.where(det > 0, det, torch.ones_like(det))
    tpos = torch.clamp(t, min=0.0)
    # nan (an infinite level times a zero or negative variance): no bound but the radius's
    ex = torch.nan_to_num(torch.sqrt(tpos * c / det) * (1.0 + 1e-9) + 0.01, nan=float("inf"))
    ey = torch.nan_to_num(torch.sqrt(tpos * a / det) * (1.0 + 1e-9) + 0.01, nan=float("inf"))
    x0 = torch.maximum(torch.floor((m[:, 0] - r) / TILE), torch.floor((m[:, 0] - ex) / TILE))
    x1 = torch.minimum(torch.ceil((m[:, 0] + r) / TILE), torch.floor((m[:, 0] + ex) / TILE) + 1)
    y0 = torch.maximum(torch.floor((m[:, 1] - r) / TILE), torch.floor((m[:, 1] - ey) / TILE))
    y1 = torch.minimum(torch.ceil((m[:, 1] + r) / TILE), torch.floor((m[:, 1] + ey) / TILE) + 1)
    x0 = x0.clamp(0, tx)
    x1 = x1.clamp(0, tx)
    y0 = y0.clamp(0, ty)
    y1 = y1.clamp(0, ty)
    dead = (radii <= 0) | (t < 0) | ~torch.isfinite(m).all(-1)
    x1 = torch.where(dead, x0, x1)
    return torch.stack([x0, x1, y0, y1], dim=-1).to(torch.int64)


def bin_gaussians(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Tile lists: ``(offsets (num_tiles + 1,), gauss_ids (num_isect,))`` int64.

    Gaussians of tile ``t`` are ``gauss_ids[offsets[t]:offsets[t + 1]]`` in
    increasing depth (ties broken by index).
    """
    dev = means2d.device
    tx, ty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    rect = tile_rects(means2d, conics, opacities, radii, width, height)
    w = (rect[:, 1] - rect[:, 0]).clamp(min=0)
    h = (rect[:, 3] - rect[:, 2]).clamp(min=0)
    cnt = w * h
    live = torch.nonzero(cnt > 0).squeeze(1)
    order = live[torch.argsort(depths.detach()[live], stable=True)]
    cnt_o = cnt[order]
    total = int(cnt_o.sum())
    gid = torch.repeat_interleave(order, cnt_o)
    start = torch.repeat_interleave(torch.cumsum(cnt_o, 0) - cnt_o, cnt_o)
    local = torch.arange(total, device=dev) - start
    wg = w[gid]
    tile = (rect[gid, 2] + local // wg) * tx + rect[gid, 0] + local % wg
    tile_sorted, perm = torch.sort(tile, stable=True)
    gid = gid[perm]
    counts = torch.bincount(tile_sorted, minlength=tx * ty)
    offsets = torch.zeros(tx * ty + 1, dtype=torch.int64, device=dev)
    offsets[1:] = torch.cumsum(counts, 0)
    return offsets, gid


def _composite_segment(
    ids: Tensor,
    valid: Tensor,
    pix: Tensor,
    t_in: Tensor,
    done_in: Tensor,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite one depth-ordered segment of Gaussians over a chunk of tiles.

    ids/valid: (T, K) Gaussians of each tile; pix: (T, P, 2) pixel centres;
    t_in: (T, P) transmittance and done_in: (T, P) early-stop flags carried
    from the previous segments. Returns (features (T, P, C), t_out, done_out).
    """
    m = means2d[ids]  # (T, K, 2)
    con = conics[ids]
    dx = m[:, None, :, 0] - pix[:, :, None, 0]  # (T, P, K)
    dy = m[:, None, :, 1] - pix[:, :, None, 1]
    power = -0.5 * (con[:, None, :, 0] * dx * dx + con[:, None, :, 2] * dy * dy) - con[:, None, :, 1] * dx * dy
    alpha = torch.clamp(opacities[ids][:, None, :] * torch.exp(power), max=ALPHA_MAX)
    ok = valid[:, None, :] & (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
    cp = torch.cumprod(1.0 - alpha, dim=-1)
    t_incl = t_in[..., None] * cp
    # The Gaussians kept are a prefix: T only decreases, and the first one that
    # would take it under T_MIN stops the pixel for good.
    keep = (t_incl >= T_MIN) & ~done_in[..., None]
    t_excl = t_in[..., None] * torch.cat([torch.ones_like(cp[..., :1]), cp[..., :-1]], dim=-1)
    wgt = torch.where(keep, alpha * t_excl, torch.zeros_like(alpha))
    out = torch.einsum("tpk,tkc->tpc", wgt, feats[ids])
    t_out = torch.where(keep, t_incl, t_in[..., None]).amin(-1)
    done_out = done_in | (t_incl[..., -1] < T_MIN)
    return out, t_out, done_out


def composite_reference(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
) -> Tensor:
    """Alpha-composite features (N, C) front to back -> (H, W, C), autograd-differentiable.

    No background is added; the caller composites one through an all-ones
    feature channel (whose output is the accumulated alpha ``1 - T``).
    Tiles are processed in chunks and each tile's list in segments of at most
    ``_SEGMENT`` Gaussians (stopping once every pixel of the chunk is done),
    each segment under activation checkpointing, so memory stays bounded.
    """
    dev, dt = feats.device, feats.dtype
    C = feats.shape[1]
    tx, ty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    offsets, gids = bin_gaussians(means2d, conics, opacities, depths, radii, width, height)
    counts = offsets[1:] - offsets[:-1]
    P = TILE * TILE
    lin = torch.arange(P, device=dev)
    loc = torch.stack([(lin % TILE).to(dt), (lin // TILE).to(dt)], dim=-1) + 0.5  # (P, 2)
    out = torch.zeros(ty * tx, P, C, device=dev, dtype=dt)
    nonempty = torch.nonzero(counts > 0).squeeze(1).tolist()
    cnt_list = counts.tolist()
    off_list = offsets.tolist()
    need_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (means2d, conics, opacities, feats))
    i = 0
    chunks = []
    while i < len(nonempty):
        j, kmax = i, 0
        while j < len(nonempty):
            k2 = max(kmax, cnt_list[nonempty[j]])
            if j > i and (j - i + 1) * P * min(k2, _SEGMENT) > _CHUNK_ELEMS:
                break
            kmax = k2
            j += 1
        tiles = nonempty[i:j]
        ids = torch.zeros(len(tiles), kmax, dtype=torch.int64, device=dev)
        valid = torch.zeros(len(tiles), kmax, dtype=torch.bool, device=dev)
        for r, t in enumerate(tiles):
            n = cnt_list[t]
            ids[r, :n] = gids[off_list[t] : off_list[t] + n]
            valid[r, :n] = True
        tt = torch.tensor(tiles, device=dev)
        org = torch.stack([(tt % tx).to(dt), (tt // tx).to(dt)], dim=-1) * TILE  # (T, 2)
        pix = org[:, None, :] + loc[None]
        t_cur = torch.ones(len(tiles), P, device=dev, dtype=dt)
        # Pixels of partial tiles outside the image start done.
        done = (pix[..., 0] > width) | (pix[..., 1] > height)
        acc = torch.zeros(len(tiles), P, C, device=dev, dtype=dt)
        for k0 in range(0, kmax, _SEGMENT):
            if bool(done.all()):
                break
            seg = (ids[:, k0 : k0 + _SEGMENT], valid[:, k0 : k0 + _SEGMENT], pix, t_cur, done)
            if need_grad:
                res, t_cur, done = checkpoint(
                    _composite_segment, *seg, means2d, conics, opacities, feats, use_reentrant=False
                )
            else:
                res, t_cur, done = _composite_segment(*seg, means2d, conics, opacities, feats)
            acc = acc + res
        chunks.append((tt, acc))
        i = j
    if chunks:
        tt = torch.cat([c[0] for c in chunks])
        res = torch.cat([c[1] for c in chunks])
        out = out.index_put((tt,), res)
    img = out.reshape(ty, tx, TILE, TILE, C).permute(0, 2, 1, 3, 4).reshape(ty * TILE, tx * TILE, C)
    return img[:height, :width]
