"""Progressive DIBR warping of training photos into a pseudo view with a given depth, and the
colour disagreement between sources that marks a wrong depth.

Every target pixel is back-projected with its depth and projected once into each source
(:func:`sample_sources`); a source fills only pixels that are still empty and that it sees
(occlusion test against its own depth map of the same cloud), nearest source first
(:func:`fill_progressive`). OpenCV cameras, z-depth in world units, images in [0, 1].
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from scipy import ndimage

from ..camera.pinhole import Camera
from .pseudo_depth import zbuffer_depth

EMPTY = -1  #: ``filled_by`` value of pixels nothing could fill
PADDED = -2  #: ``filled_by`` value of padded pixels
RTOL = 0.02  #: relative depth tolerance of the occlusion test (:func:`sample_sources`)


@dataclass
class SourceSamples:
    """One source view seen from the target's pixels at one depth hypothesis (all (H*W,) rows).

    Attributes:
        colour: float32 (N,3) bilinear colour at the projection, coordinates clamped to the
            image (the padding colour where the projection falls outside).
        front: the back-projected point is in front of the source camera.
        inside: ... and projects inside the source image.
        visible: ... and holds data there and passes the occlusion test against the source depth.
    """

    colour: np.ndarray
    front: np.ndarray
    inside: np.ndarray
    visible: np.ndarray


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colour (N,3) of (h,w,3) ``img`` at pixel coordinates ``uv`` (centres at +0.5),
    coordinates clamped to the outer pixel centres."""
    h, w = img.shape[:2]
    t = torch.from_numpy(np.ascontiguousarray(img[..., :3], dtype=np.float32)).permute(2, 0, 1)[None]
    g = torch.from_numpy(np.stack([uv[:, 0] * (2.0 / w) - 1.0, uv[:, 1] * (2.0 / h) - 1.0], -1)
                         .astype(np.float32))[None, None]
    out = torch.nn.functional.grid_sample(t, g, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T.numpy()


class Projector:
    """The target's pixels ``p`` projected into each source as ``a_s + d B_s p`` (homogeneous
    source pixels for depth ``d``): ``a_s = K_s (R_s C_t + t_s)``, ``B_s = K_s R_s R_t^T K_t^-1``
    (the paper's ``K_i T_{j->i} D_j K_j^-1 p_j``). Built once a view, so each depth hypothesis
    costs one multiply-add per pixel and source."""

    def __init__(self, target: Camera, sources: Sequence[tuple]):
        j, i = np.meshgrid(np.arange(target.height) + 0.5, np.arange(target.width) + 0.5, indexing="ij")
        self.px, self.py = i.ravel(), j.ravel()
        self.target = target
        to_world = target.R.T @ np.linalg.inv(target.K)  # pixel -> world direction (camera-z 1)
        self.a = [s[0].K @ (s[0].R @ target.center + s[0].t) for s in sources]
        # Elementwise rather than (3,3) @ (3,N): no BLAS threads for a few multiply-adds.
        self.B = [self._apply(s[0].K @ s[0].R @ to_world) for s in sources]
        self.to_world = to_world

    def _apply(self, M: np.ndarray) -> list[np.ndarray]:
        return [M[k, 0] * self.px + M[k, 1] * self.py + M[k, 2] for k in range(3)]

    def sample(self, depth: np.ndarray, sources: Sequence[tuple], rtol: float) -> list[SourceSamples]:
        depth = np.asarray(depth, dtype=np.float64).ravel()
        has_d = np.isfinite(depth) & (depth > 0)
        d = np.where(has_d, depth, 1.0)
        out = []
        for src, a, B in zip(sources, self.a, self.B):
            cam_s, im_s = src[0], np.asarray(src[1])
            d_s = src[2] if len(src) > 2 and src[2] is not None else None
            if d_s is None:
                X = self.target.center + d[:, None] * np.stack(self._apply(self.to_world), 1)
                sp = float(np.median(depth[has_d])) / max(self.target.fx, 1e-12) if has_d.any() else 0.0
                d_s = zbuffer_depth(X[has_d], cam_s, spacing=sp)
            d_s = np.asarray(d_s, dtype=np.float64)
            hs, ws = im_s.shape[:2]
            h0, h1, z = (a[k] + d * B[k] for k in range(3))
            front = has_d & (z > 1e-12 * np.maximum(np.maximum(np.abs(h0), np.abs(h1)), np.abs(z)))
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.where(front, h0 / z, 0.0)
                v = np.where(front, h1 / z, 0.0)
            front &= np.isfinite(u) & np.isfinite(v)
            inside = front & (u >= 0) & (u < ws) & (v >= 0) & (v < hs)
            ds = d_s[np.clip(v, 0, hs - 1).astype(np.int64), np.clip(u, 0, ws - 1).astype(np.int64)]
            colour = _sample(im_s, np.stack([u, v], -1))
            # NaN: the source holds no data there; like an occluded pixel, padded from its neighbours
            visible = inside & np.isfinite(colour).all(axis=1) & (ds > 0) & (z <= ds * (1.0 + rtol))
            out.append(SourceSamples(np.nan_to_num(colour), front, inside, visible))
        return out


def sample_sources(target: Camera, depth: np.ndarray, sources: Sequence[tuple], rtol: float = RTOL
                   ) -> list[SourceSamples]:
    """Project the target's pixels, back-projected at ``depth`` (H,W; 0 = none), once into each source.

    ``sources`` are ``(camera, image (h,w,3))`` or ``(camera, image, depth (h,w))`` tuples (an image
    is NaN where it holds no data: a pixel drawn from there is not visible in it). The
    source depth (0 = unknown) is used for the occlusion test: a pixel is visible in a source
    when its depth there is at most ``source_depth * (1 + rtol)``; without it, one is
    z-buffered from the target's own back-projected pixels.
    """
    return Projector(target, sources).sample(depth, sources, rtol)


def source_order(target: Camera, sources: Sequence[tuple]) -> np.ndarray:
    """Indices of ``sources`` from the nearest camera centre to the target's to the farthest."""
    return np.argsort([np.linalg.norm(s[0].center - target.center) for s in sources], kind="stable")


def fill_progressive(samples: Sequence[SourceSamples], order: Sequence[int], shape: tuple[int, int]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill the target from per-source samples, sources in ``order`` (nearest first).

    Returns ``(image (H,W,3) float32, valid (H,W) bool, filled_by (H,W) int32)``.
    ``filled_by`` holds the index of the source that filled a valid pixel,
    :data:`PADDED` for padded pixels and :data:`EMPTY` for pixels left black (only when
    nothing can be padded). Padding: pixels outside every source's image take the clamped
    colour of the nearest source they are in front of ("warping with padding"); occluded
    pixels and pixels without depth take the colour of the nearest filled pixel.
    """
    H, W = shape
    img = np.zeros((H * W, 3), np.float32)
    valid = np.zeros(H * W, bool)
    filled_by = np.full(H * W, EMPTY, np.int32)
    if not len(samples):
        return img.reshape(H, W, 3), valid.reshape(H, W), filled_by.reshape(H, W)
    seen_inside = np.zeros(H * W, bool)
    padded_from = np.full(H * W, -1, np.int64)
    for k in order:
        s = samples[k]
        new = s.visible & ~valid
        img[new] = s.colour[new]
        valid |= new
        filled_by[new] = k
        seen_inside |= s.inside
        padded_from[(padded_from < 0) & s.front] = k
    out = ~valid & ~seen_inside & (padded_from >= 0)
    for k in np.unique(padded_from[out]):
        m = out & (padded_from == k)
        img[m] = samples[k].colour[m]
        filled_by[m] = PADDED
    done = filled_by != EMPTY
    if done.any() and not done.all():
        ii = ndimage.distance_transform_edt(~done.reshape(H, W), return_distances=False, return_indices=True)
        near = (ii[0] * W + ii[1]).ravel()
        rest = ~done
        img[rest] = img[near[rest]]
        filled_by[rest] = PADDED
    return img.reshape(H, W, 3), valid.reshape(H, W), filled_by.reshape(H, W)


def disagreement(samples: Sequence[SourceSamples], shape: tuple[int, int], min_common: int = 64
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(count (H,W) int32, spread (H,W) float32)``: how many sources see each pixel, and the
    largest mean absolute RGB difference between two of them (0 where fewer than two do).

    With the right depth, sources agree up to shading and exposure; a wrong depth samples
    different surfaces in different views. Photographs differ in exposure, so each pair is
    compared after a gain per channel (the median of the colour ratios over the pixels both
    see, when at least ``min_common`` do; clamped to [0.5, 2]) - exposure is not a depth
    error. (The ratio of the median colours is no estimate: on a generated city, whose views
    share one exposure, it strays to 1.2 where the median ratio stays within 4 % of 1.)
    """
    n = shape[0] * shape[1]
    count = np.zeros(n, np.int32)
    spread = np.zeros(n, np.float32)
    for a in range(len(samples)):
        count += samples[a].visible
        for b in range(a + 1, len(samples)):
            seen = samples[a].visible & samples[b].visible
            both = np.flatnonzero(seen)
            if not len(both):
                continue
            ca, cb = samples[a].colour, samples[b].colour
            gain = np.ones(3, np.float32)
            if len(both) >= min_common:
                some = both[::max(1, len(both) // 4096)]  # a few thousand ratios pin the median down
                gain = np.clip(np.median((cb[some] + 0.02) / (ca[some] + 0.02), 0), 0.5, 2.0).astype(np.float32)
            # Over every pixel, kept where both see it: cheaper than gathering those pixels first.
            np.maximum(spread, np.abs(ca * gain - cb).mean(-1), out=spread, where=seen)
    return count.reshape(shape), spread.reshape(shape)


def warp_progressive(target: Camera, depth: np.ndarray, sources: Sequence[tuple], rtol: float = RTOL
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Synthesise the target view from source images, nearest source first: :func:`sample_sources`
    then :func:`fill_progressive` (see both for the arguments and the result)."""
    shape = (target.height, target.width)
    if not sources:
        return fill_progressive([], [], shape)
    return fill_progressive(sample_sources(target, depth, sources, rtol), source_order(target, sources), shape)


def source_disagreement(target: Camera, depth: np.ndarray, sources: Sequence[tuple]
                        ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`disagreement` of the sources warped into ``target`` at ``depth``."""
    return disagreement(sample_sources(target, depth, sources), (target.height, target.width))


def merge_samples(a: Sequence[SourceSamples], b: Sequence[SourceSamples], take: np.ndarray) -> list[SourceSamples]:
    """Per pixel, ``b``'s samples where ``take`` (H*W,) else ``a``'s."""
    def pick(x, y):
        return np.where(take[:, None] if x.ndim == 2 else take, y, x)

    return [SourceSamples(pick(x.colour, y.colour), pick(x.front, y.front), pick(x.inside, y.inside),
                          pick(x.visible, y.visible)) for x, y in zip(a, b)]
