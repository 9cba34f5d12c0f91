"""Tests for dibrgs_core.training.losses against scikit-image and at numeric extremes."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from dibrgs_core.training.losses import photometric_loss, psnr, ssim

torch.set_num_threads(2)


def _sk_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=-1)


@pytest.mark.parametrize("shape", [(32, 40, 3), (24, 24, 1)])
def test_ssim_matches_skimage(shape):
    rng = np.random.default_rng(0)
    a = rng.random(shape)
    # b correlated with a so SSIM is far from both 0 and 1
    b = np.clip(0.7 * a + 0.3 * rng.random(shape), 0, 1)
    ref = _sk_ssim(a, b)
    got = float(ssim(torch.tensor(a), torch.tensor(b)))
    assert 0.2 < ref < 0.95
    assert abs(got - ref) < 1e-4
    # float32 as the trainer uses it
    got32 = float(ssim(torch.tensor(a, dtype=torch.float32), torch.tensor(b, dtype=torch.float32)))
    assert abs(got32 - ref) < 1e-4


def test_ssim_identical_is_one_and_grad_finite():
    rng = np.random.default_rng(1)
    a = torch.tensor(rng.random((20, 20, 3)), dtype=torch.float32, requires_grad=True)
    s = ssim(a, a.detach())
    assert abs(s.item() - 1.0) < 1e-5
    s.backward()
    assert torch.isfinite(a.grad).all()


@pytest.mark.stability
def test_extremes_black_constant_images_finite():
    """SSIM/L1 loss on all-black and constant images: finite loss and gradients."""
    black = torch.zeros(16, 16, 3, requires_grad=True)
    white = torch.ones(16, 16, 3)
    for gt in (torch.zeros(16, 16, 3), white):
        loss = photometric_loss(black, gt)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(black.grad).all()
        black.grad = None
    assert float(psnr(black.detach(), torch.zeros(16, 16, 3))) == pytest.approx(100.0)
    assert float(psnr(black.detach(), white)) == pytest.approx(0.0, abs=1e-6)


def test_photometric_loss_value():
    rng = np.random.default_rng(2)
    a = torch.tensor(rng.random((16, 16, 3)), dtype=torch.float64)
    b = torch.tensor(rng.random((16, 16, 3)), dtype=torch.float64)
    want = 0.8 * (a - b).abs().mean() + 0.2 * (1 - ssim(a, b))
    assert float(photometric_loss(a, b)) == pytest.approx(float(want), rel=1e-9)
    # a full mask gives the same L1 term; SSIM term then averages over all pixels
    full = photometric_loss(a, b, mask=torch.ones(16, 16, dtype=torch.bool))
    assert torch.isfinite(full) and float(full) > 0


@pytest.mark.stability
def test_mask_restricts_loss_and_empty_mask_is_zero():
    """Pseudo-view loss with no valid pixel: exactly zero loss and zero gradients, no NaN."""
    gt = torch.zeros(24, 24, 3)
    pred = torch.zeros(24, 24, 3)
    pred[:, 12:] = 1.0  # wrong only on the right half
    pred.requires_grad_(True)
    left = torch.zeros(24, 24, dtype=torch.bool)
    left[:, :6] = True  # far enough from the error that SSIM windows barely reach it
    l_left = photometric_loss(pred, gt, mask=left)
    l_right = photometric_loss(pred, gt, mask=~left)
    assert l_left.item() < 0.01 < l_right.item()
    empty = photometric_loss(pred, gt, mask=torch.zeros(24, 24, dtype=torch.bool))
    assert empty.item() == 0.0
    empty.backward()
    assert torch.isfinite(pred.grad).all() and float(pred.grad.abs().sum()) == 0.0


def test_psnr_known_value():
    a = torch.zeros(8, 8, 3)
    b = torch.full((8, 8, 3), 0.1)
    assert float(psnr(a, b)) == pytest.approx(20.0, abs=1e-4)
    m = torch.zeros(8, 8, dtype=torch.bool)
    assert float(psnr(a, b, mask=m)) == 0.0
