"""Semi-global aggregation of a plane-sweep cost volume along image paths (Hirschmueller 2008),
in torch: penalties ``p1`` for a one-plane step and ``p2`` for a larger jump between neighbours."""
from __future__ import annotations


def semi_global(cost, p1: float, p2: float, paths: int = 4):
    """Semi-global aggregation of a (D,H,W) plane-sweep cost along ``paths`` (4 or 8) image directions.

    Each path adds, per pixel and plane, the cost plus the cheapest way to arrive from the
    previous pixel on the path: the same plane for free, a neighbouring plane for ``p1``, any
    plane for ``p2`` (costs are 1 - NCC, in [0, 2]). With height planes "the same plane" means
    the same height, so flat roofs and ground are favoured and height jumps at walls stay
    possible. The per-path minimum is subtracted at every step, so values stay bounded.
    Returns the sum over the paths (D,H,W).
    """
    import torch

    if paths not in (4, 8):
        raise ValueError(f"semi_global: paths must be 4 or 8, got {paths}")
    D, H, W = cost.shape
    total = torch.zeros_like(cost)
    inf = torch.tensor(float("inf"))

    def run(c):  # c: (D, N, L), aggregate along the last axis, all N lines at once
        out = torch.empty_like(c)
        prev = c[:, :, 0]
        out[:, :, 0] = prev
        pad = inf.expand(1, c.shape[1])
        for x in range(1, c.shape[2]):
            m = prev.min(0).values
            step = torch.minimum(torch.cat([pad, prev[:-1]]), torch.cat([prev[1:], pad])) + p1
            best = torch.minimum(torch.minimum(prev, step), (m + p2)[None])
            prev = c[:, :, x] + best - m[None]
            out[:, :, x] = prev
        return out

    # Horizontal and vertical paths, both ways.
    total += run(cost)
    total += run(cost.flip(2)).flip(2)
    total += run(cost.transpose(1, 2)).transpose(1, 2)
    total += run(cost.transpose(1, 2).flip(2)).flip(2).transpose(1, 2)
    if paths == 8:
        # Diagonals: shear the volume so that diagonals become rows, aggregate, shear back.
        for flip in (False, True):
            c = cost.flip(2) if flip else cost
            sheared, idx = _shear(c)
            for rev in (False, True):
                a = run(sheared.flip(2)).flip(2) if rev else run(sheared)
                back = _unshear(a, idx, H, W)
                total += back.flip(2) if flip else back
    return total


def _shear(c):
    """(D,H,W) -> (D, H+W-1, min(H,W)-ish) lines along the main diagonals, padded with the max cost."""
    import torch

    D, H, W = c.shape
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    diag = (xs - ys + H - 1).reshape(-1)  # which diagonal
    pos = torch.minimum(ys, xs).reshape(-1)  # position along it
    L = min(H, W)
    out = torch.full((D, H + W - 1, L), 2.0, dtype=c.dtype)
    out[:, diag, pos] = c.reshape(D, -1)
    return out, (diag, pos)


def _unshear(a, idx, H: int, W: int):
    diag, pos = idx
    return a[:, diag, pos].reshape(a.shape[0], H, W)
