"""Image losses and metrics in torch: differentiable SSIM, the paper's photometric loss, PSNR;
and the neural Gaussians' volume regulariser (:func:`mean_volume`).

Image layout: **(H, W, C)** (channels last, as the rasterizer returns them) or
(H, W) for a single channel; values in [0, 1]. All functions return 0-d tensors
that stay finite for any finite input, including constant and all-black images
and masks without a single valid pixel.

SSIM follows Wang et al. (2004) with a Gaussian window (size 11, sigma 1.5),
C1 = 0.01^2, C2 = 0.03^2 for a data range of 1 and population (not sample)
covariances, i.e. ``skimage.metrics.structural_similarity(...,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)``.
Like scikit-image, the mean SSIM leaves out a border of ``window // 2`` pixels
so that no window reaches outside the image; the per-pixel map used by the
loss is defined everywhere by replicating the border.
"""
from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

from ..render import fast, uses_fast
from ..render.fast import ready
from ..render.ssim import photometric_fast, ssim_map_fast

_C1 = 0.01 ** 2
_C2 = 0.03 ** 2
_WINDOW, _SIGMA = 11, 1.5  # the loss's SSIM window (Wang et al.)


def _gauss_1d(window: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The normalised 1-D Gaussian window (cached, read only)."""
    return _gauss_cached(window, float(sigma), dtype, device, torch.is_inference_mode_enabled())


@functools.lru_cache(maxsize=16)
def _gauss_cached(window: int, sigma: float, dtype: torch.dtype, device: torch.device, inference: bool
                  ) -> torch.Tensor:
    r = window // 2
    x = torch.arange(-r, r + 1, dtype=dtype, device=device)
    g = torch.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return g / g.sum()


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of (1,C,H,W), borders replicated (output same size)."""
    C = x.shape[1]
    r = g.numel() // 2
    x = F.pad(x, (r, r, r, r), mode="replicate")
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    return F.conv2d(x, g.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


def ssim_map(pred: torch.Tensor, gt: torch.Tensor, window: int = _WINDOW, sigma: float = _SIGMA) -> torch.Tensor:
    """Per-pixel SSIM, shape (H, W, C). Differentiable with respect to both inputs.

    CPU tensors go through the C++ kernel (:func:`dibrgs_core.render.ssim.ssim_map_fast`, the
    same maths in one pass) when the rasterizer's backend resolves to it and ``gt`` needs no
    gradient; otherwise, and with ``--rasterizer reference``, the torch formulation below."""
    if pred.shape != gt.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ in shape")
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd size, got {window}")
    if pred.dim() not in (2, 3):
        raise ValueError(f"expected an (H,W) or (H,W,C) image, got shape {tuple(pred.shape)}")
    g = _gauss_1d(window, sigma, pred.dtype, pred.device)
    hwc = pred.shape if pred.dim() == 3 else pred.shape + (1,)
    p3, t3 = pred.reshape(hwc), gt.to(pred.dtype).reshape(hwc)
    if _kernel_applies(pred, gt):
        return ssim_map_fast(p3, t3, g).reshape(pred.shape)
    x, y = p3.permute(2, 0, 1)[None], t3.permute(2, 0, 1)[None]  # (1, C, H, W)
    # The five local means in one blur: fewer, larger operators (faster, and they use a second thread).
    mx, my, mxx, myy, mxy = _blur(torch.cat([x, y, x * x, y * y, x * y], 1), g).split(x.shape[1], 1)
    # Population variances; tiny negative values from cancellation are harmless
    # because C2 > 0 keeps the denominator positive.
    vx = mxx - mx * mx
    vy = myy - my * my
    cxy = mxy - mx * my
    num = (2 * mx * my + _C1) * (2 * cxy + _C2)
    den = (mx * mx + my * my + _C1) * (vx + vy + _C2)
    return (num / den)[0].permute(1, 2, 0).reshape(pred.shape)


def ssim(pred: torch.Tensor, gt: torch.Tensor, window: int = _WINDOW, sigma: float = _SIGMA,
         mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM of two (H,W,C) or (H,W) images in [0,1] (0-d tensor, differentiable).

    Matches scikit-image's Gaussian-weighted SSIM: the mean excludes a border of
    ``window // 2`` pixels when the image is large enough to have an interior. With ``mask``
    (H,W), the mean over the pixels it weights, ``pred`` taken as ``gt`` where it is 0 (so that
    windows reaching pixels without data compare only the pixels with it).
    """
    if mask is not None:
        m = _mask_hw1(mask, pred.shape[0], pred.shape[1], pred)
        s = ssim_map(_gt_where_unweighted(pred, gt, m), gt, window, sigma)
        w = (m if pred.dim() == 3 else m[..., 0]).expand_as(s)
        return (s * w).sum() / w.sum().clamp_min(1e-12)
    m = ssim_map(pred, gt, window, sigma)
    r = window // 2
    H, W = m.shape[0], m.shape[1]
    if H > 2 * r and W > 2 * r:
        # The interior's mean as a weighted sum: its backward is one product, where a slice's
        # is a zeroed image and two strided copies.
        w = _interior_weights(H, W, r, m.dim(), m.dtype, m.device, torch.is_inference_mode_enabled())
        return (m * w).sum() / (m.numel() // (H * W))
    return m.mean()


@functools.lru_cache(maxsize=8)
def _interior_weights(H: int, W: int, r: int, dim: int, dtype: torch.dtype, device: torch.device,
                      inference: bool) -> torch.Tensor:
    """(H, W[, 1]) weights: 1 / (number of interior pixels) on the pixels at least ``r`` from the
    border, 0 on the border. Cached (read only); ``inference`` keys it too, since a tensor made in
    inference mode cannot be saved for a later backward."""
    w = torch.zeros((H, W, 1)[:dim], dtype=dtype, device=device)
    w[r:H - r, r:W - r] = 1.0 / ((H - 2 * r) * (W - 2 * r))
    return w


def _kernel_applies(pred: torch.Tensor, gt: torch.Tensor) -> bool:
    """Whether the C++ SSIM / loss kernels take these images (else the torch formulation)."""
    return (pred.dtype in (torch.float32, torch.float64) and pred.numel() > 0 and not gt.requires_grad
            and uses_fast(None, pred))


@functools.lru_cache(maxsize=8)
def _plain_weights(H: int, W: int, C: int, r: int, dtype: torch.dtype, device: torch.device, inference: bool
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """(H, W, C) weights of the unmasked loss on the C++ path: L1's mean over every value, and
    D-SSIM's over the interior (:func:`ssim`), each summing to 1. Cached (read only), keyed by
    inference mode like :func:`_interior_weights`."""
    wl = torch.full((H, W, C), 1.0 / (H * W * C), dtype=dtype, device=device)
    if H > 2 * r and W > 2 * r:
        ws = (_interior_weights(H, W, r, 3, dtype, device, inference) / C).expand(H, W, C).contiguous()
    else:
        ws = wl
    return wl, ws


def _gt_where_unweighted(pred: torch.Tensor, gt: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """``pred`` (H,W[,C]) with ``gt`` where the weight ``m`` (H,W,1, :func:`_mask_hw1`) is 0: those pixels
    then take no part in a loss or score, SSIM's windows that reach them included."""
    return torch.where((m if pred.dim() == 3 else m[..., 0]) > 0, pred, gt.to(pred.dtype))


def _mask_hw1(mask: torch.Tensor, H: int, W: int, like: torch.Tensor) -> torch.Tensor:
    m = mask.to(dtype=like.dtype, device=like.device)
    if m.dim() == 3:
        m = m[..., :1]
    elif m.dim() == 2:
        m = m[..., None]
    if m.shape[:2] != (H, W):
        raise ValueError(f"mask shape {tuple(mask.shape)} does not match image {H}x{W}")
    return m


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lam: float = 0.2,
                     mask: torch.Tensor | None = None) -> torch.Tensor:
    """The paper's loss ``(1 - lam) * L1 + lam * (1 - SSIM)`` for (H,W,C) images.

    ``mask`` (H,W) or (H,W,1), bool or float weights in [0,1], restricts both
    terms to valid pixels (pseudo views with holes, photos without data in places): L1 is the
    weighted mean absolute error and the D-SSIM term the weighted mean of the SSIM map, ``pred``
    taken as ``gt`` where the weight is 0. A mask
    without any valid pixel gives a loss of exactly 0 whose gradients are 0.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ in shape")
    gt = gt if gt.dtype == pred.dtype else gt.to(pred.dtype)
    H, W = pred.shape[0], pred.shape[1]
    C = pred.shape[2] if pred.dim() == 3 else 1
    fast = pred.dim() in (2, 3) and _kernel_applies(pred, gt)

    def one_node(wl: torch.Tensor, ws: torch.Tensor) -> torch.Tensor:
        # The C++ path: L1 and D-SSIM with per-value weights in one autograd node.
        # A reshape to the same shape is still a view and an autograd node: only (H, W) images take one.
        p, g = (pred, gt) if pred.dim() == 3 else (pred.reshape(H, W, C), gt.reshape(H, W, C))
        return photometric_fast(p, g,
                                _gauss_1d(_WINDOW, _SIGMA, pred.dtype, pred.device), wl, ws, lam)

    if mask is None:
        if fast:
            return one_node(*_plain_weights(H, W, C, _WINDOW // 2, pred.dtype, pred.device,
                                            torch.is_inference_mode_enabled()))
        l1 = (pred - gt).abs().mean()
        return (1.0 - lam) * l1 + lam * (1.0 - ssim(pred, gt))
    m = _mask_hw1(mask, H, W, pred)
    wsum = m.sum()
    if float(wsum) <= 0.0:
        # Keep the graph (zero gradients) without dividing by zero.
        return (pred * 0.0).sum()
    if bool((m <= 0).any()):
        # SSIM windows reaching pixels without data compare the data only: none of their gradient
        # flows into what is rendered there
        pred = _gt_where_unweighted(pred, gt, m)
    if fast:
        # One contiguous weight tensor for both terms (expanded, each would be copied on its own).
        w = (m / (wsum * C)).detach().expand(H, W, C).contiguous()
        return one_node(w, w)
    diff = (pred - gt).abs()
    if diff.dim() == 2:
        diff = diff[..., None]
    l1 = (diff * m).sum() / (wsum * C)
    smap = ssim_map(pred, gt)
    if smap.dim() == 2:
        smap = smap[..., None]
    dssim = ((1.0 - smap) * m).sum() / (wsum * C)
    return (1.0 - lam) * l1 + lam * dssim


class _MeanVolume(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scales, unit, weight):  # type: ignore[override]
        ctx.save_for_backward(scales)
        ctx.unit, ctx.weight = unit, weight
        return fast.extension().volume_forward(scales, unit, weight)

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        (scales,) = ctx.saved_tensors
        return fast.extension().volume_backward(g, scales, ctx.unit, ctx.weight), None, None


def mean_volume(scales: torch.Tensor, unit: float, weight: float = 1.0) -> torch.Tensor:
    """``weight`` times the mean over Gaussians of their volume ``prod(scales / unit)`` ((N, 3)
    scales; ``unit`` the length that counts as 1, so that the term weighs the same in any scene's
    units); 0 without Gaussians. On the C++ path one autograd node, the weight included (torch's
    ``prod`` and its backward, which guards zeros with several passes, cost about 0.6 ms of a 22 ms
    step at 256x256, and a separate product with the weight is one more node); otherwise the same
    product in torch."""
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    if scales.dtype in (torch.float32, torch.float64) and uses_fast(None, scales):
        return _MeanVolume.apply(ready(scales, scales.dtype), float(unit), float(weight))
    s = scales / unit
    v = (s[:, 0] * s[:, 1] * s[:, 2]).mean()
    return v if weight == 1.0 else weight * v


def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for images in [0,1] (0-d tensor).

    The MSE is floored at 1e-10 so identical images give 100 dB, not Inf. With a
    ``mask`` (H,W) only valid pixels count; an empty mask gives 0 dB.
    """
    gt = gt.to(pred.dtype)
    se = (pred - gt) ** 2
    if mask is None:
        mse = se.mean()
    else:
        if se.dim() == 2:
            se = se[..., None]
        m = _mask_hw1(mask, pred.shape[0], pred.shape[1], pred)
        wsum = m.sum()
        if float(wsum) <= 0.0:
            return torch.zeros((), dtype=pred.dtype, device=pred.device)
        mse = (se * m).sum() / (wsum * se.shape[-1])
    return -10.0 * torch.log10(torch.clamp(mse, min=1e-10))


__all__ = ["ssim", "ssim_map", "photometric_loss", "mean_volume", "psnr"]
