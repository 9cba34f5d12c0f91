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
* Held-out pixels without data (transparent, no-data values, masked: :mod:`~dibrgs_core.data.images`)
  count in no metric: PSNR's and SSIM's means are over the others, and SSIM's and LPIPS's windows
  see the image itself there.
* AVGE (RegNeRF): geometric mean of ``10^(-PSNR/10)``, ``sqrt(1 - SSIM)`` and LPIPS.
* FPS: held-out views rendered repeatedly after a warm-up, wall-clock.
"""
from __future__ import annotations

import logging
import math
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..camera.pinhole import Camera
from ..common.errors import InputError
from ..common.fileio import write_json
from ..models.base import CameraTensors, GaussianModel, render_model
from ..training.checkpoint import load_model
from ..training.config import TrainConfig
from .lpips import load_lpips

log = logging.getLogger("dibrgs.evaluate")


@dataclass
class Trained:
    """A trained model ready to render any camera (see :func:`load_trained`).

    Cameras given to its methods are in the scene's own frame (``Scene.origin`` subtracted, as
    :func:`~dibrgs_core.data.load.load_scene` gives them); :meth:`from_files` turns a camera of the
    scene's files into one.
    """

    model: GaussianModel
    cfg: TrainConfig
    scene: str
    train_cameras: list[Camera]
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def from_files(self, cam: Camera) -> Camera:
        """``cam``, given in the world frame of the scene's files, in the frame the model is in."""
        return cam.translated(-self.origin) if np.any(self.origin) else cam

    @property
    def method(self) -> str:
        return self.model.kind

    @torch.no_grad()
    def gaussians(self, cam: Camera) -> dict[str, torch.Tensor]:
        """Activated Gaussians for ``cam``: means, quats (wxyz), scales, opacities, colors."""
        return self.model.gaussians(CameraTensors.of(cam)).as_dict()

    @torch.no_grad()
    def all_gaussians(self) -> dict[str, torch.Tensor]:
        """Every Gaussian, view-independent (the export's convention, :meth:`GaussianModel.export_gaussians`)."""
        return self.model.export_gaussians(self.train_cameras)

    @torch.no_grad()
    def render(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """(image (H,W,3) float32 in [0,1], z-depth (H,W) float32, 0 where empty)."""
        bg = torch.tensor(self.cfg.background, dtype=torch.float32)
        img, _a, depth, _ = render_model(self.model, CameraTensors.of(cam), bg)
        return img.clamp(0, 1).numpy().astype(np.float32), depth[..., 0].numpy().astype(np.float32)

    @property
    def sizes(self) -> dict[str, int]:
        return self.model.sizes()


def load_trained(work: str | Path) -> Trained:
    """Load ``WORK/model.pt`` (``InputError`` when the run has not finished)."""
    st = load_model(work)
    return Trained(st.model, st.cfg, st.scene, st.train_cameras, st.origin)


def avge(psnr: float, ssim: float, lpips: float) -> float:
    """RegNeRF's average error: geometric mean of MSE, sqrt(1 - SSIM) and LPIPS."""
    mse = 10.0 ** (-psnr / 10.0)
    return float(np.exp(np.mean(np.log([mse, math.sqrt(max(1.0 - ssim, 0.0)), max(lpips, 1e-12)]))))


# ---------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------
def run_split(work: Path) -> tuple[list[str] | None, list[str] | None, str | None]:
    """(train, test, scene digest) the run in ``work`` recorded in its ``config.json`` (Nones when
    it recorded none: runs from before the split was recorded use the scene's own split)."""
    import json

    try:
        d = json.loads((work / "config.json").read_text())
        run = d.get("run") or {}
        return run.get("train"), run.get("test"), run.get("digest")
    except (OSError, ValueError, AttributeError):
        return None, None, None


def run_scale(work: str | Path, tr: Trained, scene: Any) -> float:
    """The resize factor the run in ``work`` trained at (``config.json``); for runs that did not
    record it, resolved again from the configuration and the scene's image sizes."""
    import json

    from ..training.config import resolve_resolution

    try:
        s = float((json.loads((Path(work) / "config.json").read_text()).get("run") or {})["resolution_scale"])
    except (OSError, ValueError, AttributeError, KeyError, TypeError):  # not recorded, or damaged
        s = None
    if s is not None and s > 0:
        return s
    sizes = [(v.camera.width, v.camera.height) for v in scene.train_views() + scene.test_views()]
    return resolve_resolution(tr.cfg, sizes)[0]


#: Half-width of scikit-image's SSIM window (Gaussian, sigma 1.5: 11 pixels), the border its mean leaves out.
_SSIM_PAD = 5


def evaluate(work: str | Path, lpips_weights: str | Path | None = None, lpips_backbone: str | Path | None = None,
             fps_repeats: int = 3, write_renders: bool = True, scene_root: str | Path | None = None
             ) -> dict[str, Any]:
    """Evaluate ``WORK`` on its run's held-out views; writes ``metrics.json`` and ``renders/``.

    The scene is the folder the run trained on, or ``scene_root`` when it has moved since (its
    content must be the same: the run's recorded digest is checked). ``metrics.json`` is strict
    JSON: a metric that is infinite (PSNR of a render identical to its image) or undefined is
    ``null``, with the reason under ``undefined``."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity
    from tqdm import tqdm

    from ..data.images import write_png
    from ..data.load import load_scene
    from ..training.frames import frame_valid, has_data, views_to_frames

    work = Path(work)
    tr = load_trained(work)
    lp = load_lpips(lpips_weights, lpips_backbone) if lpips_weights else None
    root = Path(scene_root) if scene_root is not None else Path(tr.scene)
    if not root.is_dir():
        raise InputError(root, "--scene: no such folder" if scene_root is not None else
                         f"the scene {work} trained on is not there any more; if it moved, give its new folder "
                         "with --scene")
    train, test, digest = run_split(work)
    try:
        scene = load_scene(root, train, test, load_depth=False)
    except InputError as e:
        if scene_root is None:
            raise
        raise InputError(root, f"this is not the scene {work} was trained on ({e.problem})") from e
    if digest is not None and scene.digest() != digest:
        what = "the scene changed since" if scene_root is None else "this is not the scene"
        raise InputError(root, f"{what} {work} was trained on (its digest was {digest}, now {scene.digest()}); "
                               "train again to evaluate on it")
    frames = views_to_frames(scene.test_views(), run_scale(work, tr, scene))
    empty = [f.cam.cam.name for f in frames if not has_data(f)]
    if empty:  # nothing to score
        log.warning("held-out photos without a pixel of data, not scored: %s", ", ".join(empty))
        frames = [f for f in frames if f.cam.cam.name not in empty]
    if not frames:
        raise InputError(root, "the run's split has no held-out views to evaluate"
                         + (" (those it has hold no pixel of data)" if empty else ""))
    no_lpips = "no LPIPS weights given (--lpips); LPIPS and AVGE are not computed"
    small = min(min(f.image.shape[:2]) for f in frames)
    if lp is not None and small < lp.min_side:
        no_lpips = (f"the held-out images' shortest side is {small} px, under the {lp.min_side} px LPIPS-"
                    f"{lp.net_name} has features for; LPIPS and AVGE are not computed")
        log.warning("%s", no_lpips)
        lp = None
    per_view: dict[str, dict[str, Any]] = {}
    undefined: dict[str, str] = {}
    renders = []
    for f in tqdm(frames, desc="eval", unit="view", disable=None):
        img, _ = tr.render(f.cam.cam)
        gt = f.image.numpy()
        valid = frame_valid(f)
        # Pixels without data are scored as rendered right: they count in no mean, and SSIM's
        # and LPIPS's windows that reach them compare only the pixels with data
        scored = img if valid is None else np.where(valid[..., None], img, gt)
        with np.errstate(divide="ignore"):
            p = float(peak_signal_noise_ratio(gt, img, data_range=1.0)) if valid is None else \
                float(10.0 * np.log10(1.0 / np.mean((img[valid].astype(np.float64) - gt[valid]) ** 2)))
        s, smap = structural_similarity(gt, scored, channel_axis=2, data_range=1.0, gaussian_weights=True,
                                        sigma=1.5, use_sample_covariance=False, full=True)
        row: dict[str, Any] = {"psnr": p, "ssim": float(s)}
        if valid is not None:  # as scikit-image's mean: the window's half-width of border left out
            inner = np.zeros_like(valid)
            inner[_SSIM_PAD:-_SSIM_PAD, _SSIM_PAD:-_SSIM_PAD] = True
            row["ssim"] = float(smap[valid & inner].mean()) if (valid & inner).any() else float(smap[valid].mean())
            row["scored_share"] = float(valid.mean())
        if not math.isfinite(p):
            row["psnr"] = None
            undefined[f"per_view.{f.cam.cam.name}.psnr"] = "infinite: the render equals the image (MSE 0)"
        if lp is not None:
            row["lpips"] = float(lp(torch.from_numpy(np.ascontiguousarray(scored)), f.image))
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
    finite = [r["psnr"] for r in per_view.values() if r["psnr"] is not None]
    psnr = float(np.mean(finite)) if len(finite) == len(per_view) else math.inf
    ssim = float(np.mean([r["ssim"] for r in per_view.values()]))
    metrics: dict[str, Any] = {"psnr": psnr, "ssim": ssim, "fps": fps, "views": len(frames),
                               "method": tr.method, "preset": tr.cfg.preset, **tr.sizes}
    if not math.isfinite(psnr):
        metrics["psnr"] = None
        undefined["psnr"] = (f"infinite: {len(per_view) - len(finite)} of {len(per_view)} held-out renders equal "
                             "their images, so the mean PSNR is infinite")
    if lp is not None:
        metrics["lpips"] = float(np.mean([r["lpips"] for r in per_view.values()]))
        metrics["avge"] = avge(psnr, ssim, metrics["lpips"]) if math.isfinite(psnr) else 0.0
    else:
        metrics["lpips"] = None
        metrics["avge"] = None
        metrics["lpips_unavailable"] = no_lpips
    rep_path = work / "report.json"
    if rep_path.exists():
        import json

        try:
            vals = json.loads(rep_path.read_text()).get("values", {})
            if not isinstance(vals, dict):
                raise ValueError(f"values is a {type(vals).__name__}, not an object")
        except (OSError, ValueError, AttributeError) as e:
            log.warning("%s unreadable (%s); training figures left out of the metrics", rep_path, e)
            vals = {}
        metrics["train_seconds"] = vals.get("train_seconds")
        metrics["iterations"] = vals.get("iteration")
        metrics["train_peak_memory_mib"] = vals.get("train_peak_memory_mib")
    metrics["eval_peak_memory_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    metrics["peak_memory_mib"] = max(v for v in (metrics.get("train_peak_memory_mib"),
                                                 metrics["eval_peak_memory_mib"]) if v is not None)
    metrics["split"] = {"train": list(scene.train), "test": list(scene.test), "source": scene.split_source
                        if train is None else f"the run ({work / 'config.json'})"}
    metrics["per_view"] = per_view
    if empty:
        metrics["not_scored"] = {name: "no pixel of the photo holds data" for name in empty}
    if undefined:
        metrics["undefined"] = undefined
    write_json(work / "metrics.json", metrics)
    log.info("held-out PSNR %.2f dB, SSIM %.4f, LPIPS %s, %.1f FPS over %d views", psnr, ssim,
             "n/a" if lp is None else f"{metrics['lpips']:.4f}", fps, len(frames))
    return metrics
