"""Differentiable 3D Gaussian rasterizer (3DGS maths, gsplat-style API).

``rasterize`` projects Gaussians and alpha-composites them in 16x16 tiles,
either with the plain-torch reference path (:func:`projection.project_gaussians`
and :mod:`reference`, autograd, any device) or with the C++ CPU path
(:mod:`fast`, compiled on first use, hand-written backward). Both implement
the same rules and agree to 1e-5.

Backend choice: ``backend="auto"`` (the default) uses the C++ path for CPU
tensors and the reference for others; ``"fast"`` insists on the C++ path;
``"reference"`` never compiles anything. A failed C++ build is an error
(:class:`fast.BuildError`, saying how to fix it), never a silent switch to
the ~100x slower reference. The process-wide default is
:func:`set_backend`'s, else ``$DIBRGS_RASTERIZER``, else ``"auto"``.

Conventions: ``viewmat`` is world-to-camera with OpenCV axes (x right, y down,
z forward); ``K`` is in pixels with pixel centres at +0.5 (``cx = W / 2`` is a
centred camera); quaternions are ``(w, x, y, z)`` and normalised inside;
scales are world-unit standard deviations; opacities are in [0, 1].
"""
from __future__ import annotations

import logging
import os
from typing import Any, Literal, get_args

import torch
from torch import Tensor

from .vml import init_vml
from . import fast
from .depth import expected_depth
from .projection import Projected, project_gaussians, quat_to_rotmat
from .reference import composite_reference

__all__ = [
    "ENV_BACKEND",
    "Backend",
    "Projected",
    "RenderMode",
    "composite",
    "get_backend",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
    "set_backend",
    "uses_fast",
]

log = logging.getLogger("dibrgs.render")

# Before any operator runs on two threads: the same values in every process (vml.py).
init_vml()

Backend = Literal["auto", "fast", "reference"]
_BACKENDS = get_args(Backend)
#: What :func:`rasterize` composites: the features and, with ``"+ED"``, the alpha and the
#: expected depth (gsplat's names).
RenderMode = Literal["RGB", "RGB+ED"]
_RENDER_MODES = get_args(RenderMode)
ENV_BACKEND = "DIBRGS_RASTERIZER"
_backend: Backend | None = None


def _check(backend: str, where: str) -> Backend:
    if backend not in _BACKENDS:
        raise ValueError(f"{where}: unknown rasterizer backend {backend!r} (expected auto, fast or reference)")
    return backend  # type: ignore[return-value]


def set_backend(backend: Backend | None) -> None:
    """Process-wide default backend of :func:`rasterize` and :func:`composite`; None restores
    ``$DIBRGS_RASTERIZER`` / ``"auto"``. A CLI ``--rasterizer`` option maps onto this."""
    global _backend
    _backend = None if backend is None else _check(backend, "set_backend")


def get_backend() -> Backend:
    """The default backend: :func:`set_backend`'s, else ``$DIBRGS_RASTERIZER``, else ``"auto"``."""
    if _backend is not None:
        return _backend
    env = os.environ.get(ENV_BACKEND, "").strip()
    return _check(env, f"${ENV_BACKEND}") if env else "auto"


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    backend: Backend | None = None,
) -> Tensor:
    """Front-to-back alpha compositing of screen-space Gaussians -> (H, W, C).

    ``backend``: ``"auto"`` (C++ on CPU tensors, the reference on others),
    ``"fast"`` (C++, CPU only) or ``"reference"``; None is :func:`get_backend`.
    """
    if uses_fast(backend, feats):
        C = feats.shape[1]
        return fast.composite_fast(means2d, conics, opacities, feats, depths, radii, width, height, (C,))[0]
    return composite_reference(means2d, conics, opacities, feats, depths, radii, width, height)


def uses_fast(backend: Backend | None, like: Tensor) -> bool:
    """Whether ``backend`` resolves to the C++ path for tensors like ``like`` (building it if
    needed: a failed build raises :class:`fast.BuildError`)."""
    # Called by every stage of a training step (about ten times): kept cheap.
    backend = get_backend() if backend is None else _check(backend, "rasterizer")
    if backend == "reference":
        return False
    if not like.is_cpu:
        if backend == "fast":
            raise ValueError("the fast backend runs on CPU tensors only")
        return False
    fast.extension()
    return True


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    backend: Backend | None = None,
    render_mode: RenderMode = "RGB+ED",
) -> tuple[Tensor, Tensor | None, Tensor | None, dict[str, Any]]:
    """Render N 3D Gaussians with one pinhole camera.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) rotations ``(w, x, y, z)``; normalised inside, a zero
            quaternion is the identity.
        scales: (N, 3) standard deviations in world units (not log).
        opacities: (N,) in [0, 1].
        colors: (N, C) per-Gaussian features, any C >= 1 (RGB or features).
        viewmat: (4, 4) world-to-camera, OpenCV axes.
        K: (3, 3) intrinsics in pixels, pixel centres at +0.5.
        width, height: image size in pixels.
        background: optional (C,) colour blended as ``image + T * background``
            where ``T = 1 - alpha`` is the final transmittance.
        near, far: camera-z clipping planes (world units), ``near > 0``.
        backend: ``"auto"``, ``"fast"`` or ``"reference"``; None is
            :func:`get_backend`. The fast path projects in C++ too, unless
            ``viewmat`` or ``K`` requires grad (then the torch projection
            carries their gradients).
        render_mode: ``"RGB+ED"`` composites each Gaussian's depth and a one
            beside its features, for the alpha and the expected depth;
            ``"RGB"`` the features alone (what a photometric loss reads; two
            channels of five fewer made a training step 5-6 % faster at 256x256
            and 8-9 % at 512x512) and returns None for both (the alpha is still
            composited, not returned, when a background is blended).

    Returns:
        ``(image (H, W, C), alpha (H, W, 1), depth (H, W, 1), meta)``.
        ``depth`` is the *normalised* expected camera z,
        ``sum_i w_i z_i / alpha`` (0 where ``alpha == 0``); multiply by
        ``alpha`` for the accumulated form. ``alpha`` and ``depth`` are None
        with ``render_mode="RGB"``. ``meta`` holds ``"radii"`` (N,)
        int32 pixels, ``"visible"`` (N,) bool, ``"means2d"`` (N, 2) (call its
        ``retain_grad()`` before backward to read its ``.grad``),
        ``"depths"`` (N,) and ``"conics"`` (N, 3).
    """
    N = means.shape[0]
    if means.shape != (N, 3) or quats.shape != (N, 4) or scales.shape != (N, 3):
        raise ValueError(
            f"shape mismatch: means {tuple(means.shape)}, quats {tuple(quats.shape)}, scales {tuple(scales.shape)}"
        )
    if opacities.shape != (N,) or colors.dim() != 2 or colors.shape[0] != N:
        raise ValueError(f"shape mismatch: opacities {tuple(opacities.shape)}, colors {tuple(colors.shape)}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if render_mode not in _RENDER_MODES:
        raise ValueError(f"rasterize: unknown render_mode {render_mode!r} (expected RGB or RGB+ED)")
    C = colors.shape[1]
    use_fast = uses_fast(backend, colors)
    if use_fast and not (viewmat.requires_grad or K.requires_grad):
        proj = fast.project_fast(means, quats, scales, viewmat, K, width, height, near, far)
    else:
        proj = project_gaussians(means, quats, scales, viewmat, K, width, height, near, far)
    # The (C,) values read as a list, not a reduction: one operator of dispatch a step for a black background.
    blend = background is not None and (background.requires_grad or any(
        (background if background.dim() == 1 else background.reshape(-1)).tolist()))
    if render_mode == "RGB" and not blend:
        image = composite(proj.means2d, proj.conics, opacities, colors, proj.depths, proj.radii, width, height, backend)
        alpha = depth_acc = None
    elif use_fast:
        # The compositing's features are the colours, each Gaussian's depth and a one (for the
        # expected depth and alpha), read in place: a concatenated copy and its ones were about half a
        # millisecond of a 256x256 step on the calling thread.
        image, depth_acc, alpha = fast.composite_fast(
            proj.means2d, proj.conics, opacities, colors, proj.depths, proj.radii, width, height, (C, 1, 1),
            depth_alpha=True)
    else:
        feats = torch.cat([colors, proj.depths[:, None], torch.ones_like(proj.depths)[:, None]], dim=1)
        out = composite_reference(proj.means2d, proj.conics, opacities, feats, proj.depths, proj.radii, width, height)
        image, depth_acc, alpha = out[..., :C], out[..., C : C + 1], out[..., C + 1 : C + 2]
    if blend:
        # (H,W,1) @ (1,C): the gradient to alpha is then a matmul, not a slow reduction over the
        # few channels (about 1 ms of a 256x256 step); a fixed black background adds nothing.
        image = image + (1.0 - alpha) @ background.to(image).reshape(1, -1)
    if render_mode == "RGB":
        alpha = depth = None
    else:
        depth = expected_depth(depth_acc, alpha, use_fast)
    meta = {
        "radii": proj.radii,
        "visible": proj.visible,
        "means2d": proj.means2d,
        "depths": proj.depths,
        "conics": proj.conics,
    }
    return image, alpha, depth, meta
