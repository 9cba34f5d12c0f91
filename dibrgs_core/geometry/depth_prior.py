"""Dense depth priors and their affine alignment to SfM points.

Priors, by name:

* ``depth-anything-v2``: Depth Anything V2 through ``transformers`` from a
  local folder (``--depth-model PATH``); output is *relative disparity*
  (larger = nearer, unknown scale and shift).
* ``mvs``: :mod:`dibrgs_core.geometry.mvs` plane sweep; metric z-depth, NaN where
  unreliable. The default when no weights are given.
* ``gt``: the dataset's depth maps (oracle ablations only).

Relative disparity is mapped to a pseudo-depth ("Inv.": ``1/disparity``,
"Neg.": ``-disparity``) and then aligned by ``depth = a * pseudo + b`` with a
robust least-squares fit against the depths of the SfM points that project
into the view (paper eq. 2).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..common.errors import InputError
from ..common.modes import DepthMap, DepthPrior, choices
from ..data.images import fill_no_data, to_uint8

log = logging.getLogger("dibrgs.depth_prior")

#: Priors that can be computed (``auto`` picks one of them).
PRIORS = tuple(p for p in choices(DepthPrior) if p != "auto")
MAPS = choices(DepthMap)


# ---------------------------------------------------------------------------
# Depth Anything V2
# ---------------------------------------------------------------------------
def load_depth_anything(path: str | Path):
    """Load a Depth Anything (V2) model and its image processor from a local folder.

    Never touches the network: a hub id or a missing folder fails at once
    with a message naming ``--depth-model``.
    """
    p = Path(path)
    if not p.is_dir():
        raise InputError(p, "Depth Anything weights not found: --depth-model must name a local folder "
                            "holding config.json, the weights and preprocessor_config.json (no network here; "
                            "hub ids cannot be downloaded)")
    if not (p / "config.json").exists():
        raise InputError(p, "not a transformers model folder (config.json missing); pass it with --depth-model")
    from transformers import AutoImageProcessor, DepthAnythingForDepthEstimation

    try:
        model = DepthAnythingForDepthEstimation.from_pretrained(p, local_files_only=True)
        processor = AutoImageProcessor.from_pretrained(p, local_files_only=True)
    except Exception as e:  # OSError, ValueError, safetensors' own error for damaged weights, ...
        raise InputError(p, f"cannot load the Depth Anything model given by --depth-model "
                            f"({type(e).__name__}: {e}); check or replace the files") from None
    model.eval()
    return model, processor


def predict_disparity(model: Any, processor: Any, image: np.ndarray) -> np.ndarray:
    """Relative disparity (HxW float32, the image's size) of an HxWx3 [0,1] image."""
    import torch
    import torch.nn.functional as F

    H, W = image.shape[:2]
    img8 = to_uint8(image[..., :3])
    inputs = processor(images=img8, return_tensors="pt")
    with torch.no_grad():
        out = model(**inputs).predicted_depth  # (1, h, w)
    disp = F.interpolate(out[:, None].float(), size=(H, W), mode="bilinear", align_corners=False)[0, 0]
    return disp.numpy().astype(np.float32)


# ---------------------------------------------------------------------------
# Mapping and alignment
# ---------------------------------------------------------------------------
def map_disparity(disp: np.ndarray, mode: str) -> np.ndarray:
    """Relative disparity -> pseudo-depth. ``inv``: 1/disp (non-positive -> NaN); ``neg``: -disp."""
    d = np.asarray(disp, np.float64)
    if mode == "inv":
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.where(np.isfinite(d) & (d > 0), 1.0 / np.where(d > 0, d, 1.0), np.nan)
        return out
    if mode == "neg":
        return np.where(np.isfinite(d), -d, np.nan)
    raise ValueError(f"unknown disparity map {mode!r} (use one of {MAPS})")


@dataclass
class Alignment:
    """``depth = a * pseudo + b`` for one view, and how it was obtained."""

    a: float
    b: float
    method: str
    n_points: int
    n_inliers: int = 0
    residual: float = float("nan")
    reason: str = ""

    def apply(self, pseudo: np.ndarray) -> np.ndarray:
        """Aligned depth; non-finite or non-positive results become NaN."""
        d = self.a * np.asarray(pseudo, np.float64) + self.b
        return np.where(np.isfinite(d) & (d > 0), d, np.nan)


def sample_points_in_view(cam: Camera, points: np.ndarray, pseudo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pseudo value at the projection, SfM z-depth) for the points that land on finite pixels."""
    if points is None or len(points) == 0:
        return np.zeros(0), np.zeros(0)
    uv, z = cam.project(points)
    u = np.floor(uv[:, 0]).astype(np.int64)
    v = np.floor(uv[:, 1]).astype(np.int64)
    ok = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height) & np.isfinite(uv).all(1)
    x = np.asarray(pseudo, np.float64)[v[ok], u[ok]]
    y = z[ok]
    good = np.isfinite(x)
    return x[good], y[good]


def robust_affine(x: np.ndarray, y: np.ndarray, iters: int = 20, ransac_trials: int = 200, seed: int = 0
                  ) -> tuple[float, float, np.ndarray]:
    """Fit ``y ~ a x + b`` robustly: RANSAC on point pairs, then Tukey-weighted IRLS.

    Returns (a, b, inlier mask). Assumes at least 2 points with distinct x.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    n = len(x)
    # Work in normalised coordinates so the thresholds are scale-free.
    xm, xs = np.median(x), max(np.std(x), 1e-300)
    ym, ys = np.median(y), max(np.std(y), 1e-300)
    xn, yn = (x - xm) / xs, (y - ym) / ys
    rng = np.random.default_rng(seed)
    best = (np.inf, 1.0, 0.0)
    if n > 2:
        for _ in range(ransac_trials):
            i, j = rng.choice(n, 2, replace=False)
            if abs(xn[i] - xn[j]) < 1e-9:
                continue
            a = (yn[i] - yn[j]) / (xn[i] - xn[j])
            b = yn[i] - a * xn[i]
            r = np.abs(yn - a * xn - b)
            score = np.median(r)  # LMedS: no threshold to tune
            if score < best[0]:
                best = (score, a, b)
        a, b = best[1], best[2]
    else:
        a = (yn[1] - yn[0]) / (xn[1] - xn[0])
        b = yn[0] - a * xn[0]
    w = np.ones(n)
    for _ in range(iters):
        r = yn - a * xn - b
        s = 1.4826 * np.median(np.abs(r)) + 1e-9
        c = 4.685 * s
        w = np.where(np.abs(r) < c, (1 - (r / c) ** 2) ** 2, 0.0)
        if w.sum() < 2 or np.ptp(xn[w > 0]) < 1e-12:
            break
        A = np.stack([xn, np.ones(n)], 1) * np.sqrt(w)[:, None]
        sol, *_ = np.linalg.lstsq(A, yn * np.sqrt(w), rcond=None)
        a, b = float(sol[0]), float(sol[1])
    inl = w > 0
    # Back to original units: y = ys*(a*(x-xm)/xs + b) + ym
    A_ = ys * a / xs
    B_ = ys * b + ym - A_ * xm
    return float(A_), float(B_), inl


def fallback_alignment(pseudo: np.ndarray, mode: str, ref_depth: float, reason: str, n: int) -> Alignment:
    """Alignment without usable SfM points: assume the view's median depth is ``ref_depth``.

    ``inv`` (and metric ``depth``): scale only, ``a = ref/median(pseudo)``, ``b = 0``.
    ``neg``: the first-order expansion of the same assumption around the
    median disparity m: depth ~ ref * (2 - disp/m), i.e. ``a = ref/m``, ``b = 2 ref``.
    """
    vals = np.asarray(pseudo, np.float64)
    vals = vals[np.isfinite(vals)]
    if mode == "depth":
        return Alignment(1.0, 0.0, "identity", n, reason=reason)
    if vals.size == 0:
        return Alignment(1.0, 0.0, "none", n, reason=reason + "; the prior has no finite values")
    med = float(np.median(vals))
    if mode == "neg":
        m = -med  # median disparity
        if m > 0:
            return Alignment(ref_depth / m, 2 * ref_depth, "camera-distance", n, reason=reason)
        # Disparity with a non-positive median: align spread only around ref.
        s = max(float(np.std(vals)), 1e-12)
        return Alignment(0.1 * ref_depth / s, ref_depth - 0.1 * ref_depth / s * med, "camera-distance", n, reason=reason)
    if med > 0:
        return Alignment(ref_depth / med, 0.0, "camera-distance", n, reason=reason)
    return Alignment(1.0, 0.0, "none", n, reason=reason + "; the prior's median is not positive")


def align_view(cam: Camera, pseudo: np.ndarray, points: np.ndarray | None, mode: str, ref_depth: float,
               min_points: int = 2) -> Alignment:
    """Solve ``a, b`` for one view against the SfM points that project into it.

    ``mode`` is ``inv``/``neg`` for mapped disparity or ``depth`` for a metric
    prior (expected result a ~ 1, b ~ 0). Degenerate cases fall back (see
    :func:`fallback_alignment`) with the reason recorded in the result.
    """
    x, y = sample_points_in_view(cam, points if points is not None else np.zeros((0, 3)), pseudo)
    n = len(x)
    if n < max(min_points, 2):
        return fallback_alignment(pseudo, mode, ref_depth, f"only {n} SfM points in the view (need {max(min_points, 2)})", n)
    if np.ptp(x) < 1e-12 * max(1.0, np.abs(x).max()):
        # Zero variance: only a shift (metric) or scale (relative) can be fitted.
        if mode in ("inv", "depth") and np.median(x) > 0:
            a = float(np.median(y) / np.median(x)) if mode == "inv" else 1.0
            b = 0.0 if mode == "inv" else float(np.median(y - x))
            return Alignment(a, b, "degenerate-x", n, reason="the prior is constant at the SfM points")
        return fallback_alignment(pseudo, mode, ref_depth, "the prior is constant at the SfM points", n)
    a, b, inl = robust_affine(x, y)
    res = float(np.median(np.abs(y[inl] - a * x[inl] - b))) if inl.any() else float("nan")
    if not (np.isfinite(a) and np.isfinite(b)) or a <= 0:
        # Negative scale means depth order reversed: the fit is meaningless.
        pos = (x > 0) & (y > 0)
        if mode == "inv" and pos.sum() >= 1:
            return Alignment(float(np.median(y[pos] / x[pos])), 0.0, "scale-only", n, int(pos.sum()), res,
                             reason=f"robust fit gave scale {a:.3g} <= 0; fitted a scale only")
        return fallback_alignment(pseudo, mode, ref_depth, f"robust fit gave scale {a:.3g} <= 0", n)
    return Alignment(a, b, "robust-lsq", n, int(inl.sum()), res)


# ---------------------------------------------------------------------------
# The prior for a set of views
# ---------------------------------------------------------------------------
@dataclass
class PriorMaps:
    """Raw prior per view before alignment.

    Attributes:
        kind: ``"disparity"`` (relative, needs mapping) or ``"depth"`` (metric z-depth).
        maps: HxW float arrays, NaN where the prior has no value.
        confidence: optional HxW weights in [0, 1].
    """

    kind: str
    maps: list[np.ndarray]
    confidence: list[np.ndarray] | None = None
    info: dict = field(default_factory=dict)


def compute_prior(name: str, cameras: Sequence[Camera], images: Sequence[np.ndarray],
                  gt_depths: Sequence[np.ndarray | None] | None, sparse_points: np.ndarray | None,
                  ref_distance: float, depth_model: str | Path | None = None, mvs_config=None,
                  checkpoint: Path | None = None, valid: Sequence[np.ndarray | None] | None = None) -> PriorMaps:
    """Run the named prior on the views. See the module docstring for the names. ``checkpoint``:
    a folder where the plane sweep keeps each view's result as it finishes (``mvs`` only).
    ``valid``: per view, bool (H, W) pixels that hold data or None: the plane sweep matches only
    those (the maps are not masked here: :func:`~.pipeline.prior_depths` leaves the rest out)."""
    if name == "depth-anything-v2":
        if depth_model is None:
            raise InputError(None, "the depth-anything-v2 prior needs its weights: pass a local folder with --depth-model")
        model, proc = load_depth_anything(depth_model)
        import time

        t = time.time()
        maps = [predict_disparity(model, proc, im) for im in images]
        return PriorMaps("disparity", maps, info={"inference_s": time.time() - t})
    if name == "mvs":
        from .mvs import mvs_depths

        if valid is not None:
            images = [fill_no_data(np.asarray(im, np.float32), v, np.nan) for im, v in zip(images, valid)]
        res = mvs_depths(cameras, images, sparse_points, ref_distance, mvs_config, checkpoint=checkpoint)
        return PriorMaps("depth", [r.depth for r in res], [r.confidence for r in res])
    if name == "gt":
        if gt_depths is None or any(d is None for d in gt_depths):
            raise InputError(None, "the gt prior needs the dataset's depth maps (Depths/), which this scene lacks")
        return PriorMaps("depth", [np.where(np.isfinite(d) & (d > 0), d, np.nan).astype(np.float32) for d in gt_depths])
    raise InputError(None, f"unknown depth prior {name!r} (use one of {PRIORS})")
