"""Which training views see each pixel of a held-out view, and the error split by that count.

Sparse-view errors concentrate where few training views see the surface: a pixel
no training view sees can only be guessed, one seen by a single view has colour
but no parallax to place it. Splitting held-out PSNR by this count tells which
part of a method (geometry, pseudo views, regularisation) a change helped.

The count needs the held-out view's true z-depth (generated scenes have it):
each held-out pixel is lifted to a world point and projected into every
training view; the view sees it when the point lands inside the image, in front
of the camera, and no more than ``rel_tol`` (relative) behind that view's own
true depth at the (nearest) pixel, i.e. it is not occluded.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..camera.pinhole import Camera

#: Groups :class:`SplitError` reports: (name, min count, max count or None).
GROUPS: tuple[tuple[str, int, int | None], ...] = (("unseen", 0, 0), ("one", 1, 1), ("two_plus", 2, None))


def visibility_count(cam: Camera, depth: np.ndarray, sources: Sequence[tuple],
                     rel_tol: float = 0.01) -> np.ndarray:
    """How many of ``sources`` see each pixel of ``cam``.

    Args:
        cam: the target camera (OpenCV axes, world-to-camera extrinsics).
        depth: (H, W) z-depth of the target in world units; 0 or non-finite = no surface.
        sources: (camera, (H', W') z-depth) of each training view, or (camera, depth, valid):
            ``valid`` (H', W') bool, the pixels where the view's photo holds data (None: all);
            a view does not see what lands on a pixel without data.
        rel_tol: a projected point counts as visible when its depth in the source is at
            most ``(1 + rel_tol)`` times the source's depth at that pixel.

    Returns:
        (H, W) int32 counts; -1 where the target has no surface (``depth`` invalid).
    """
    depth = np.asarray(depth, np.float64)
    if depth.shape != (cam.height, cam.width):
        raise ValueError(f"depth of {cam.name!r} is {depth.shape}, camera is {cam.height}x{cam.width}")
    ok = np.isfinite(depth) & (depth > 0)
    X = cam.backproject(np.where(ok, depth, 1.0))
    count = np.zeros(X.shape[0], np.int32)
    for scam, sdepth, *rest in sources:
        sdepth = np.asarray(sdepth, np.float64)
        valid = rest[0] if rest else None
        uv, z = scam.project(X)
        H, W = sdepth.shape
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        xs = np.clip(np.nan_to_num(uv[:, 0]).astype(np.int64), 0, W - 1)
        ys = np.clip(np.nan_to_num(uv[:, 1]).astype(np.int64), 0, H - 1)
        d = sdepth[ys, xs]
        # A source without depth at that pixel (sky, background) cannot occlude it.
        free = ~(np.isfinite(d) & (d > 0))
        if valid is not None:
            inside &= np.asarray(valid, bool)[ys, xs]
        with np.errstate(invalid="ignore"):
            count += inside & (free | (z <= d * (1.0 + rel_tol)))
    count = count.reshape(cam.height, cam.width)
    count[~ok] = -1
    return count


@dataclass
class SplitError:
    """Squared-error sums of one or more images split by visibility group.

    ``sse[g]`` sums the per-pixel mean-over-channels squared error and ``n[g]`` counts
    the pixels of group ``g`` (see :data:`GROUPS`); ``"all"`` covers every pixel.
    """

    sse: dict[str, float]
    n: dict[str, int]

    @staticmethod
    def empty() -> "SplitError":
        names = ["all"] + [g[0] for g in GROUPS]
        return SplitError({k: 0.0 for k in names}, {k: 0 for k in names})

    def add(self, render: np.ndarray, gt: np.ndarray, count: np.ndarray) -> float:
        """Accumulate one view: images (H, W, 3) in [0, 1], ``count`` from :func:`visibility_count`.
        Returns the view's own PSNR over all its pixels (the whole-image figure of ``dibrgs eval``)."""
        se = ((np.asarray(render, np.float64) - np.asarray(gt, np.float64)[..., :3]) ** 2).mean(-1)
        total = float(se.sum())
        self.sse["all"] += total
        self.n["all"] += se.size
        for name, lo, hi in GROUPS:
            m = (count >= lo) if hi is None else ((count >= lo) & (count <= hi))
            self.sse[name] += float(se[m].sum())
            self.n[name] += int(m.sum())
        return _pooled_psnr(total, se.size)

    def psnr(self) -> dict[str, float | None]:
        """PSNR (dB, peak 1) of each group over all accumulated pixels; None for an empty group."""
        return {k: _pooled_psnr(s, self.n[k]) for k, s in self.sse.items()}

    def seen_psnr(self) -> float | None:
        """PSNR of the pooled squared error over the pixels one or more sources see (None when
        there are none): the figure a sparse-view method is judged by where it had photos."""
        return _pooled_psnr(self.sse["one"] + self.sse["two_plus"], self.n["one"] + self.n["two_plus"])

    def fractions(self) -> dict[str, float]:
        """Share of pixels in each group (the ``all`` total is 1)."""
        tot = max(self.n["all"], 1)
        return {k: v / tot for k, v in self.n.items()}


def _pooled_psnr(sse: float, n: int) -> float | None:
    """PSNR (dB, peak 1) of ``sse`` summed over ``n`` pixels; None for none."""
    return None if n == 0 else float(-10.0 * np.log10(max(sse / n, 1e-20)))
