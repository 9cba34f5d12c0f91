"""Evaluation of a trained run: held-out PSNR / SSIM / LPIPS / AVGE, rendering FPS, test renders.

* PSNR and SSIM with scikit-image (``peak_signal_noise_ratio``,
  ``structural_similarity`` with a Gaussian window, sigma 1.5, data range 1), on
  renders clamped to [0, 1] against the held-out images.
* LPIPS only from local weights the user gives (``--lpips FILE``): a state dict in
  the official ``lpips`` package layout (``net.slice{1..5}.*`` backbone + ``lin{0..4}.model.1.weight``
  1x1 heads, as ``lpips.LPIPS(net=...).state_dict()``), or only the heads (the
  package's ``weights/v0.1/{vgg,alex}.pth``) together with ``--lpips-backbone`` (the
  torchvision ``vgg16`` / ``alexnet`` state dict, ``features.*`` keys). The network
  is rebuilt here in plain torch. Without weights LPIPS and AVGE are reported as
  ``null`` with the reason; nothing is estimated.
* AVGE (RegNeRF): geometric mean of ``10^(-PSNR/10)``, ``sqrt(1 - SSIM)`` and LPIPS.
* FPS: held-out views rendered repeatedly after a warm-up, wall-clock.
"""
from __future__ import annotations

import logging
import math
import resource
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..camera.pinhole import Camera
from ..camera.serialize import camera_from_dict
from ..training.config import TrainConfig
from ..common.errors import InputError
from ..common.fileio import write_json
from .lpips import load_lpips

log = logging.getLogger("dibrgs.evaluate")


# ---------------------------------------------------------------------------
# Loading a trained model
# ---------------------------------------------------------------------------
@dataclass
class Trained:
    """A trained model ready to render any camera."""

    method: str
    model: Any
    cfg: TrainConfig
    scene: str
    train_cameras: list[Camera]
    ibr_feats: torch.Tensor | None = None

    @torch.no_grad()
    def gaussians(self, cam: Camera) -> dict[str, torch.Tensor]:
        """Activated Gaussians for ``cam``: means, quats (wxyz), scales, opacities, colors."""
        from ..training.trainer import CamT

        c = CamT.of(cam)
        if self.method == "3dgs":
            means, quats, scales, opac, rgb = self.model.activated(c.center)
            return {"means": means, "quats": quats, "scales": scales, "opacities": opac, "colors": rgb}
        m = self.model
        vis = m.visible_anchors(c.K, c.w2c, cam.width, cam.height)
        feats = None if self.ibr_feats is None else self.ibr_feats[vis]
        d = m.decode(c.K, c.w2c, c.center, cam.width, cam.height, ibr_feats=feats, visible=vis)
        return {"means": d.means, "quats": d.quats, "scales": d.scales, "opacities": d.opacities,
                "colors": d.colors}

    @torch.no_grad()
    def all_gaussians(self) -> dict[str, torch.Tensor]:
        """Every Gaussian, view-independent: neural Gaussians decoded from the mean training
        camera with frustum culling off (the export's convention)."""
        if self.method == "3dgs":
            center = torch.tensor(np.mean([c.center for c in self.train_cameras], 0), dtype=torch.float32)
            means, quats, scales, opac, _ = self.model.activated(center)
            return {"means": means, "quats": quats, "scales": scales, "opacities": opac,
                    "sh_dc": self.model.sh_dc[:, 0], "sh_rest": self.model.sh_rest}
        cam = mean_camera(self.train_cameras)
        from ..training.trainer import CamT

        c = CamT.of(cam)
        vis = torch.ones(self.model.num_anchors, dtype=torch.bool)
        d = self.model.decode(c.K, c.w2c, c.center, cam.width, cam.height, ibr_feats=self.ibr_feats, visible=vis)
        return {"means": d.means, "quats": d.quats, "scales": d.scales, "opacities": d.opacities,
                "colors": d.colors}

    @torch.no_grad()
    def render(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """(image (H,W,3) float32 in [0,1], z-depth (H,W) float32, 0 where empty)."""
        from ..render import rasterize

        g = self.gaussians(cam)
        bg = torch.tensor(self.cfg.background, dtype=torch.float32)
        if g["means"].shape[0] == 0:
            return (np.broadcast_to(bg.numpy(), (cam.height, cam.width, 3)).astype(np.float32).copy(),
                    np.zeros((cam.height, cam.width), np.float32))
        img, _a, depth, _ = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                      torch.tensor(cam.w2c, dtype=torch.float32),
                                      torch.tensor(cam.K, dtype=torch.float32), cam.width, cam.height,
                                      background=bg)
        return img.clamp(0, 1).numpy().astype(np.float32), depth[..., 0].numpy().astype(np.float32)

    @property
    def sizes(self) -> dict[str, int]:
        if self.method == "3dgs":
            return {"anchors": 0, "gaussians": self.model.num_gaussians}
        return {"anchors": self.model.num_anchors, "gaussians": self.model.num_anchors * self.model.n_offsets}


def mean_camera(cams: list[Camera]) -> Camera:
    """The training camera nearest to the mean camera centre (a representative viewpoint)."""
    c = np.mean([x.center for x in cams], 0)
    return min(cams, key=lambda x: float(np.linalg.norm(x.center - c)))


def load_trained(work: str | Path) -> Trained:
    """Load ``WORK/model.pt`` (``InputError`` when the run has not finished)."""
    from ..training.trainer import MODEL, _gs3d_from_state, _neural_from_state

    path = Path(work) / MODEL
    if not path.exists():
        raise InputError(path, "no trained model here; run `dibrgs train` to completion first "
                               "(an interrupted run continues with `dibrgs train ... --resume`)")
    try:
        st = torch.load(path, map_location="cpu", weights_only=False)
        cfg = TrainConfig.from_dict(st["config"])
    except Exception as e:  # a corrupt or foreign file
        raise InputError(path, f"cannot read the trained model ({e})") from None
    cams = [camera_from_dict(d, str(path)) for d in st["train_cameras"]]
    if st["method"] == "3dgs":
        model = _gs3d_from_state(st["model"], cfg)
        model.active_sh_degree = st["active_sh_degree"]
        return Trained("3dgs", model, cfg, st["scene"], cams)
    model = _neural_from_state(st["model"], st["model_meta"], cfg)
    model.eval()
    return Trained("dibrgs", model, cfg, st["scene"], cams, st.get("ibr_feats"))


def avge(psnr: float, ssim: float, lpips: float) -> float:
    """RegNeRF's average error: geometric mean of MSE, sqrt(1 - SSIM) and LPIPS."""
    mse = 10.0 ** (-psnr / 10.0)
    return float(np.exp(np.mean(np.log([mse, math.sqrt(max(1.0 - ssim, 0.0)), max(lpips, 1e-12)]))))


# ---------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------
def evaluate(work: str | Path, lpips_weights: str | Path | None = None, lpips_backbone: str | Path | None = None,
             fps_repeats: int = 3, write_renders: bool = True) -> dict[str, Any]:
    """Evaluate ``WORK`` on its scene's held-out views; writes ``metrics.json`` and ``renders/``."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity
    from tqdm import tqdm

    from ..data.images import write_png
    from ..training.trainer import load_scene, views_to_frames

    work = Path(work)
    tr = load_trained(work)
    lp = load_lpips(lpips_weights, lpips_backbone) if lpips_weights else None
    scene = load_scene(tr.scene)
    frames = views_to_frames(scene.test_views(), tr.cfg.resolution_scale)
    if not frames:
        raise InputError(tr.scene, "the scene has no held-out views to evaluate")
    per_view = {}
    renders = []
    for f in tqdm(frames, desc="eval", unit="view", disable=None):
        img, _ = tr.render(f.cam.cam)
        gt = f.image.numpy()
        p = float(peak_signal_noise_ratio(gt, img, data_range=1.0))
        s = float(structural_similarity(gt, img, channel_axis=2, data_range=1.0, gaussian_weights=True,
                                        sigma=1.5, use_sample_covariance=False))
        row: dict[str, Any] = {"psnr": p, "ssim": s}
        if lp is not None:
            row["lpips"] = float(lp(torch.from_numpy(img), f.image))
        per_view[f.cam.cam.name] = row
        renders.append((f.cam.cam.name, img))
        if write_renders:
            write_png(work / "renders" / f"{f.cam.cam.name}.png", img)
    # Rendering speed (model decode + rasterization), after one warm-up frame.
    tr.render(frames[0].cam.cam)
    t0 = time.perf_counter()
    n = 0
    for _ in range(max(1, fps_repeats)):
        for f in frames:
            tr.render(f.cam.cam)
            n += 1
    fps = n / (time.perf_counter() - t0)
    psnr = float(np.mean([r["psnr"] for r in per_view.values()]))
    ssim = float(np.mean([r["ssim"] for r in per_view.values()]))
    metrics: dict[str, Any] = {"psnr": psnr, "ssim": ssim, "fps": fps, "views": len(frames),
                               "method": tr.method, "preset": tr.cfg.preset, **tr.sizes}
    if lp is not None:
        metrics["lpips"] = float(np.mean([r["lpips"] for r in per_view.values()]))
        metrics["avge"] = avge(psnr, ssim, metrics["lpips"])
    else:
        metrics["lpips"] = None
        metrics["avge"] = None
        metrics["lpips_unavailable"] = "no LPIPS weights given (--lpips); LPIPS and AVGE are not computed"
    rep_path = work / "report.json"
    if rep_path.exists():
        import json

        vals = json.loads(rep_path.read_text()).get("values", {})
        metrics["train_seconds"] = vals.get("train_seconds")
        metrics["iterations"] = vals.get("iteration")
        metrics["train_peak_memory_mib"] = vals.get("train_peak_memory_mib")
    metrics["eval_peak_memory_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    metrics["peak_memory_mib"] = max(v for v in (metrics.get("train_peak_memory_mib"),
                                                 metrics["eval_peak_memory_mib"]) if v is not None)
    metrics["per_view"] = per_view
    write_json(work / "metrics.json", metrics)
    log.info("held-out PSNR %.2f dB, SSIM %.4f, LPIPS %s, %.1f FPS over %d views", psnr, ssim,
             "n/a" if lp is None else f"{metrics['lpips']:.4f}", fps, len(frames))
    return metrics
