"""The DIBR-GS training loop (and the 3DGS baseline's), with resumable checkpoints.

Run folder (``WORK``):

* ``config.json`` - the :class:`~dibrgs_core.training.config.TrainConfig` and the scene path;
* ``init/`` - geometry initialisation (dense cloud, height map, its report), reused
  when present;
* ``pseudo/`` - cached pseudo views;
* ``checkpoint.pt`` - everything needed to continue bit-for-bit (model, optimiser
  states, growth statistics, RNG states, view orders, iteration, training clock,
  curve), written atomically every ``checkpoint_every_s`` seconds, on SIGINT /
  SIGTERM and at the end;
* ``model.pt`` - the final model for ``eval`` / ``render`` / ``export`` (with the
  per-anchor IBR features frozen, so no encoder is needed to render);
* ``curve.csv`` / ``curve.png`` - held-out PSNR / SSIM against training wall-clock
  seconds (evaluation and checkpoint time excluded);
* ``report.json`` - every automatic decision and its reason; ``train.log``.

Loss (paper Eq. "Optimization" + Scaffold-GS): ``(1 - 0.2) L1 + 0.2 D-SSIM`` on the
iteration's view (a training view, or on pseudo-view iterations a pseudo view
restricted to its filled pixels) plus ``0.01 * mean(prod(scales))`` over the
rasterized neural Gaussians. A step whose loss or gradients are not finite is
skipped and logged.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
import random
import resource
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..camera.pinhole import Camera
from ..camera.serialize import camera_from_dict, camera_to_dict
from .config import TrainConfig, expon_lr
from ..common.errors import InputError
from ..common.fileio import atomic_path, write_json, write_text
from ..common.report import Decision, Report

log = logging.getLogger("dibrgs.train")

CHECKPOINT = "checkpoint.pt"
MODEL = "model.pt"
CURVE_COLUMNS = ["seconds", "iteration", "psnr", "ssim"]


class TrainingFailed(RuntimeError):
    """Training cannot continue (e.g. every anchor was pruned); the message says why."""


# ---------------------------------------------------------------------------
# Scene helpers (shared with eval / render)
# ---------------------------------------------------------------------------
def load_scene(root: str | Path) -> Any:
    """Read a LEVIR-NVS or COLMAP scene folder (``InputError`` when it is neither)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "scene folder does not exist")
    from ..data.load import read_any_scene

    return read_any_scene(root)


def resize_image(img: np.ndarray, scale: float) -> np.ndarray:
    """Area-resize an (H,W,C) float image by ``scale`` (no-op at 1)."""
    if scale == 1.0:
        return np.asarray(img, np.float32)
    t = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)[None]
    H, W = img.shape[:2]
    out = torch.nn.functional.interpolate(t, size=(max(1, round(H * scale)), max(1, round(W * scale))),
                                          mode="area" if scale < 1 else "bilinear")
    return out[0].permute(1, 2, 0).numpy()


@dataclass
class CamT:
    """A camera as float32 tensors."""

    cam: Camera
    K: torch.Tensor
    w2c: torch.Tensor
    center: torch.Tensor

    @staticmethod
    def of(cam: Camera) -> "CamT":
        return CamT(cam, torch.tensor(cam.K, dtype=torch.float32), torch.tensor(cam.w2c, dtype=torch.float32),
                    torch.tensor(cam.center, dtype=torch.float32))


@dataclass
class Frame:
    """A supervised view: camera, target image (H,W,3) and optional per-pixel loss weight (H,W) in [0,1]."""

    cam: CamT
    image: torch.Tensor
    mask: torch.Tensor | None = None


def views_to_frames(views: list[Any], scale: float) -> list[Frame]:
    out = []
    for v in views:
        cam = v.camera.scaled(scale) if scale != 1.0 else v.camera
        img = resize_image(np.clip(np.nan_to_num(v.image), 0.0, 1.0), scale)
        out.append(Frame(CamT.of(cam), torch.from_numpy(np.ascontiguousarray(img[..., :3]))))
    return out


# ---------------------------------------------------------------------------
# Methods: DIBR-GS (neural Gaussians) and 3DGS behind one small interface
# ---------------------------------------------------------------------------
class DibrgsMethod:
    """Neural Gaussians + IBR features + anchor strategy + their optimisers."""

    name = "dibrgs"

    def __init__(self, model: Any, cfg: TrainConfig, ibr: Any | None, height_map: Any | None,
                 frozen_ibr: torch.Tensor | None = None) -> None:
        from ..strategy.anchor import AnchorStrategy

        self.model = model
        self.cfg = cfg
        self.ibr = ibr
        self.frozen_ibr = frozen_ibr
        self.strategy = AnchorStrategy(model, cfg.growth, cfg.iterations, height_map)
        lr = cfg.lr
        groups = [
            {"params": [model.offset], "lr": lr.offset[0], "name": "offset"},
            {"params": [model.anchor_feat], "lr": lr.anchor_feat, "name": "anchor_feat"},
            {"params": [model.scaling], "lr": lr.scaling, "name": "scaling"},
        ]
        for name, params in model.mlp_parameters().items():
            groups.append({"params": params, "lr": getattr(lr, name)[0], "name": name})
        model.anchor.requires_grad_(False)  # Scaffold-GS: anchor positions have lr 0
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        self.p_params = list(ibr.projection_parameters()) if ibr is not None else []
        self.p_optimizer = (torch.optim.AdamW(self.p_params, lr=lr.projection) if self.p_params else None)
        self.p_freeze_at = cfg.it(lr.projection_freeze)
        self.last: Any = None

    def set_lr(self, it: int) -> None:
        T = self.cfg.iterations
        for g in self.optimizer.param_groups:
            sched = getattr(self.cfg.lr, g["name"])
            if isinstance(sched, tuple):
                g["lr"] = expon_lr(it, T, *sched)

    def ibr_features(self, visible: torch.Tensor) -> torch.Tensor | None:
        if self.frozen_ibr is not None:
            return self.frozen_ibr[visible]
        if self.ibr is None:
            return None
        return self.ibr(self.model.anchor[visible].detach())

    def render(self, c: CamT, bg: torch.Tensor, need_grad_stats: bool = False) -> tuple[torch.Tensor, ...]:
        from ..render import rasterize

        m = self.model
        W, H = c.cam.width, c.cam.height
        vis = m.visible_anchors(c.K, c.w2c, W, H)
        feats = self.ibr_features(vis)
        dec = m.decode(c.K, c.w2c, c.center, W, H, ibr_feats=feats, visible=vis)
        if dec.means.shape[0] == 0:
            img = bg.expand(H, W, 3).clone()
            zero = torch.zeros(H, W, 1)
            self.last = None
            return img, zero, zero, dec
        img, alpha, depth, meta = rasterize(dec.means, dec.quats, dec.scales, dec.opacities, dec.colors,
                                            c.w2c, c.K, W, H, background=bg)
        self.last = (dec, meta, W, H)
        return img, alpha, depth, dec

    def regulariser(self, dec: Any) -> torch.Tensor:
        if dec.scales.shape[0] == 0:
            return torch.zeros(())
        return dec.scales.prod(dim=1).mean()

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        if self.p_optimizer is not None:
            self.p_optimizer.zero_grad(set_to_none=True)

    def parameters(self) -> list[torch.Tensor]:
        return [p for g in self.optimizer.param_groups for p in g["params"]] + self.p_params

    def step(self, it: int) -> None:
        self.optimizer.step()
        if self.p_optimizer is not None and it <= self.p_freeze_at:
            self.p_optimizer.step()
            if it == self.p_freeze_at:
                for p in self.p_params:
                    p.requires_grad_(False)
                log.info("IBR projection P frozen at iteration %d", it)

    def after_backward(self, it: int) -> None:
        if self.last is None or not self.strategy.collects(it):
            return
        dec, meta, W, H = self.last
        g = meta["means2d"].grad
        self.strategy.update(dec, g, meta["radii"], W, H)

    def after_step(self, it: int, report: Report) -> None:
        if self.strategy.adjusts(it):
            r = self.strategy.adjust(self.model, self.optimizer)
            log.debug("anchors @%d: +%d (vetoed %d) -%d -> %d", it, r.added, r.vetoed, r.pruned,
                      self.model.num_anchors)
            report.values.setdefault("growth", {"added": 0, "vetoed": 0, "pruned": 0})
            for k in ("added", "vetoed", "pruned"):
                report.values["growth"][k] += getattr(r, k)
            report.values["growth"]["left_out_by_max_anchors"] = self.strategy.capped
            if self.model.num_anchors == 0:
                raise TrainingFailed(
                    f"every anchor was pruned at iteration {it} (opacity stayed below "
                    f"{self.cfg.growth.min_opacity} per visit); check the images and learning rates")

    def sizes(self) -> dict[str, int]:
        return {"anchors": self.model.num_anchors, "gaussians": self.model.num_anchors * self.model.n_offsets}

    def state(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "p_optimizer": None if self.p_optimizer is None else self.p_optimizer.state_dict(),
                "ibr": None if self.ibr is None else self.ibr.state_dict(),
                "p_frozen": bool(self.p_params) and not self.p_params[0].requires_grad,
                "strategy": self.strategy.state_dict()}

    def load(self, st: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(st["optimizer"])
        if self.p_optimizer is not None and st["p_optimizer"] is not None:
            self.p_optimizer.load_state_dict(st["p_optimizer"])
        if self.ibr is not None and st["ibr"] is not None:
            self.ibr.load_state_dict(st["ibr"])
        if st.get("p_frozen"):
            for p in self.p_params:
                p.requires_grad_(False)
        self.strategy.load_state_dict(st["strategy"])

    @torch.no_grad()
    def final_ibr(self) -> torch.Tensor | None:
        if self.ibr is None:
            return None
        return self.ibr(self.model.anchor.detach())


class GS3DMethod:
    """Vanilla 3DGS."""

    name = "3dgs"

    def __init__(self, model: Any, cfg: TrainConfig, extent: float) -> None:
        from ..models.gs3d import DensifyStrategy, optimizer_for

        self.model = model
        self.cfg = cfg
        self.extent = extent
        self.optimizer = optimizer_for(model, cfg.gs3d, extent)
        self.strategy = DensifyStrategy(model, cfg.gs3d, cfg.iterations, extent)
        self.last: Any = None

    def set_lr(self, it: int) -> None:
        init, final = self.cfg.gs3d.position_lr
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = expon_lr(it, self.cfg.iterations, init * self.extent, final * self.extent)

    def render(self, c: CamT, bg: torch.Tensor, need_grad_stats: bool = False) -> tuple[torch.Tensor, ...]:
        from ..render import rasterize

        means, quats, scales, opac, rgb = self.model.activated(c.center)
        img, alpha, depth, meta = rasterize(means, quats, scales, opac, rgb, c.w2c, c.K,
                                            c.cam.width, c.cam.height, background=bg)
        self.last = (meta, c.cam.width, c.cam.height)
        return img, alpha, depth, scales

    def regulariser(self, scales: Any) -> torch.Tensor:
        return torch.zeros(())  # vanilla 3DGS has none

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def parameters(self) -> list[torch.Tensor]:
        return [p for g in self.optimizer.param_groups for p in g["params"]]

    def step(self, it: int) -> None:
        self.optimizer.step()

    def after_backward(self, it: int) -> None:
        if self.last is None or it >= self.strategy.until:
            return
        meta, W, H = self.last
        self.strategy.update(meta["means2d"].grad, meta["radii"], W, H)

    def after_step(self, it: int, report: Report) -> None:
        self.strategy.step(it, self.model, self.optimizer)

    def sizes(self) -> dict[str, int]:
        return {"anchors": 0, "gaussians": self.model.num_gaussians}

    def state(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "strategy": self.strategy.state_dict(), "active_sh_degree": self.model.active_sh_degree}

    def load(self, st: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(st["optimizer"])
        self.strategy.load_state_dict(st["strategy"])
        self.model.active_sh_degree = st["active_sh_degree"]


# ---------------------------------------------------------------------------
# Building a model (fresh, or with the shapes stored in a state dict)
# ---------------------------------------------------------------------------
def _neural_from_state(sd: dict[str, torch.Tensor], meta: dict[str, Any], cfg: TrainConfig) -> Any:
    from ..models.scaffold import NeuralGaussians

    n = sd["anchor"].shape[0]
    model = NeuralGaussians(torch.zeros(n, 3), meta["voxel_size"], meta["dist_scale"], cfg.model,
                            meta["use_ibr"])
    model.load_state_dict(sd)
    return model


def _gs3d_from_state(sd: dict[str, torch.Tensor], cfg: TrainConfig) -> Any:
    from ..models.gs3d import Gaussians3D

    n = sd["means"].shape[0]
    model = Gaussians3D(np.zeros((n, 3)), np.zeros((n, 3)), cfg.gs3d.sh_degree)
    for name, t in sd.items():
        setattr(model, name, torch.nn.Parameter(t.clone()))
    return model


# ---------------------------------------------------------------------------
# The trainer
# ---------------------------------------------------------------------------
@dataclass
class TrainResult:
    status: str                     # "done" | "interrupted"
    iteration: int
    work: Path
    seconds: float
    skipped_steps: int = 0
    sizes: dict[str, int] = field(default_factory=dict)


class Trainer:
    """One training run in ``work``. ``run()`` trains (or continues) to ``cfg.iterations``."""

    def __init__(self, scene_root: str | Path, work: str | Path, cfg: TrainConfig, *, resume: bool = False,
                 progress_json: bool = False, depth_model: str | None = None,
                 stream: Any = None) -> None:
        self.scene_root = Path(scene_root)
        self.work = Path(work)
        self.cfg = cfg
        self.resume = resume
        self.progress_json = progress_json
        self.depth_model = depth_model
        self.stream = stream
        self.report = Report()
        self._stop = False

    # -- setup ----------------------------------------------------------------
    def _setup(self) -> dict[str, Any] | None:
        cfg = self.cfg
        self.work.mkdir(parents=True, exist_ok=True)
        ck_path = self.work / CHECKPOINT
        ckpt = None
        if self.resume and ck_path.exists():
            ckpt = torch.load(ck_path, map_location="cpu", weights_only=False)
            saved = TrainConfig.from_dict(ckpt["config"])
            if saved.method != cfg.method:
                raise InputError(ck_path, f"checkpoint is a {saved.method} run, asked to resume as {cfg.method}")
            # A resumed run continues with the configuration it started with,
            # except for a longer/shorter target length.
            saved.iterations = cfg.iterations
            self.cfg = cfg = saved
            log.info("resuming %s from iteration %d", ck_path, ckpt["iteration"])
        elif self.resume:
            log.info("--resume: no checkpoint in %s, starting fresh", self.work)
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)
        self.rng0 = np.random.default_rng(cfg.seed + 1)  # set-up only (random init)
        write_json(self.work / "config.json", {"scene": str(self.scene_root.resolve()), "config": cfg.to_dict()})

        scene = load_scene(self.scene_root)
        train_views, test_views = scene.train_views(), scene.test_views()
        if not train_views:
            raise InputError(self.scene_root, "the scene has no training views")
        s = cfg.resolution_scale
        self.train_frames = views_to_frames(train_views, s)
        self.test_frames = views_to_frames(test_views, s)
        self.report.values["scene"] = {"root": str(self.scene_root), "train": list(scene.train),
                                       "test": list(scene.test), "resolution_scale": s}
        self.bg = torch.tensor(cfg.background, dtype=torch.float32)
        if cfg.method == "3dgs":
            self._setup_3dgs(scene, ckpt)
        elif cfg.method == "dibrgs":
            self._setup_dibrgs(scene, ckpt)
        else:
            raise InputError(None, f"unknown method {cfg.method!r} (dibrgs or 3dgs)")
        return ckpt

    def _sfm_points(self, scene: Any) -> tuple[np.ndarray, np.ndarray]:
        from ..geometry.sfm import triangulate_known_poses

        views = scene.train_views()
        cache = self.work / "init" / "sfm_points.npz"
        if cache.exists():
            d = np.load(cache)
            return d["points"], d["colors"]
        sc = triangulate_known_poses([v.camera for v in views], [v.image for v in views])
        with atomic_path(cache) as tmp:
            np.savez(tmp, points=sc.points, colors=sc.colors)
        return sc.points, sc.colors

    def _setup_3dgs(self, scene: Any, ckpt: dict | None) -> None:
        from ..models.gs3d import Gaussians3D

        cfg = self.cfg
        centers = np.stack([f.cam.cam.center for f in self.train_frames])
        # 3DGS's cameras_extent: 1.1 x the largest camera distance from their mean.
        extent = 1.1 * float(np.max(np.linalg.norm(centers - centers.mean(0), axis=1)))
        extent = max(extent, 1e-6)
        if ckpt is not None:
            model = _gs3d_from_state(ckpt["method"]["model"], cfg)
        else:
            pts, cols = self._sfm_points(scene)
            if len(pts) >= cfg.gs3d.min_sfm_points:
                self.report.decide("train", "sfm_init", True, f"3DGS baseline starts from {len(pts)} SfM points")
                cols = np.asarray(cols, np.float64) / 255.0
            else:
                # 3DGS's own fallback for scenes without SfM points: random points.
                rp, rc = random_init([f.cam.cam for f in self.train_frames], cfg.gs3d.random_points, self.rng0)
                self.report.decide("train", "sfm_init", False,
                                   f"SfM found only {len(pts)} points (< {cfg.gs3d.min_sfm_points}); "
                                   f"3DGS starts from {len(rp)} random points in the viewed volume as well")
                pts = np.concatenate([np.asarray(pts).reshape(-1, 3), rp])
                cols = np.concatenate([np.asarray(cols, np.float64).reshape(-1, 3) / 255.0, rc])
            model = Gaussians3D(pts, cols, cfg.gs3d.sh_degree)
        self.method = GS3DMethod(model, cfg, extent)
        self.report.values["extent"] = extent

    def _init_geometry(self, scene: Any) -> Any:
        """Run the geometry initialisation, or reuse ``WORK/init`` when it was made with the same options."""
        from ..geometry.height_map import HeightMap
        from ..geometry.pipeline import InitConfig, InitResult, initialise

        out = self.work / "init"
        icfg = InitConfig()
        if self.cfg.depth_prior != "auto":
            icfg.depth_prior = self.cfg.depth_prior
        if self.depth_model:
            icfg.depth_model = self.depth_model
        rep_path, ply = out / "init_report.json", out / "points.ply"
        if rep_path.exists() and ply.exists():
            old = json.loads(rep_path.read_text())
            oc = old.get("values", {}).get("config", {})
            if oc.get("depth_prior") == icfg.depth_prior and oc.get("depth_model") == icfg.depth_model:
                import trimesh

                pc = trimesh.load(ply)
                rep = Report()
                rep.values.update(old.get("values", {}))
                rep.decisions.extend(Decision(**d) for d in old.get("decisions", []))
                hm = HeightMap.load(out / "height_map.npz") if (out / "height_map.npz").exists() else None
                cols = np.asarray(pc.colors)[:, :3] if len(getattr(pc, "colors", [])) else np.zeros((len(pc.vertices), 3))
                log.info("reusing the geometry initialisation in %s", out)
                return InitResult(np.asarray(pc.vertices, np.float64), cols.astype(np.uint8), hm, rep)
        return initialise(scene, out, icfg)

    def _setup_dibrgs(self, scene: Any, ckpt: dict | None) -> None:
        from ..models.scaffold import build_model

        cfg = self.cfg
        rep = self.report
        res = self._init_geometry(scene)
        scale = res.report.values.get("scale")
        if not scale:
            from ..geometry.pipeline import InitConfig, scene_geometry

            scale = scene_geometry(scene, InitConfig()).scale
        if cfg.dense_init:
            # float32-rounded, so a fresh cloud and one re-read from points.ply are the same
            # numbers (the pseudo-view cache is keyed on them).
            points = np.asarray(res.points, np.float32).astype(np.float64)
            rep.decide("train", "dense_init", True, f"anchors from the dense initial cloud ({len(points)} points)")
        else:
            points, _ = self._sfm_points(scene)
            points = np.asarray(points, np.float32).astype(np.float64).reshape(-1, 3)
            rep.decide("train", "dense_init", False, f"ablation --no-dense-init: anchors from {len(points)} SfM points")
        # Height constraint
        hm = res.height_map
        if cfg.height == "off":
            rep.decide("train", "height_constraint", False, "switched off (--no-height)")
            hm = None
        elif hm is None:
            rep.decide("train", "height_constraint", False,
                       "the geometry stage built no height map (scene not near-nadir or too few points)")
        else:
            near_nadir = _init_says_near_nadir(res)
            if cfg.height == "auto" and near_nadir is False:
                rep.decide("train", "height_constraint", False, "geometry report: the views are not near-nadir")
                hm = None
            else:
                rep.decide("train", "height_constraint", True,
                           "height map vetoes coarse-level growth above its relaxed bound")
        # IBR encoder
        ibr = None
        if ckpt is None or ckpt["method"]["ibr"] is not None:
            ibr = self._build_ibr()
        centers = np.stack([f.cam.cam.center for f in self.train_frames])
        if ckpt is not None:
            model = _neural_from_state(ckpt["method"]["model"], ckpt["model_meta"], cfg)
        else:
            model, why = build_model(points, centers, cfg.model, use_ibr=ibr is not None, scale=float(scale))
            rep.values["anchor_voxel"] = why
        self.model_meta = {"voxel_size": model.voxel_size, "dist_scale": model.dist_scale,
                           "use_ibr": model.use_ibr}
        self.method = DibrgsMethod(model, cfg, ibr, hm)
        self._setup_pseudo(points)

    def _build_ibr(self) -> Any:
        from ..models.ibr.features import build_ibr, resolve_encoder

        cfg = self.cfg
        name, reason = resolve_encoder(cfg.ibr, (cfg.dino_resnet, cfg.dino_vit))
        self.report.decide("train", "ibr_features", name != "none", f"encoder {name}: {reason}", encoder=name)
        if name == "none":
            return None
        imgs = torch.stack([f.image.permute(2, 0, 1) for f in self.train_frames])
        cams = [f.cam.cam for f in self.train_frames]
        return build_ibr(name, imgs, cams, c_r=cfg.model.ibr_channels, dino_resnet=cfg.dino_resnet,
                         dino_vit=cfg.dino_vit)

    def _setup_pseudo(self, points: np.ndarray) -> None:
        cfg = self.cfg
        n_train = len(self.train_frames)
        self.pseudo_frames: list[Frame] = []
        if cfg.pseudo.mode == "off":
            self.report.decide("train", "pseudo_views", False, "switched off (--no-pseudo)")
            return
        if cfg.pseudo.mode == "auto" and n_train >= cfg.pseudo.dense_views:
            self.report.decide("train", "pseudo_views", False,
                               f"{n_train} training views are dense enough (>= {cfg.pseudo.dense_views})")
            return
        from .pseudo_views import build_pseudo_views

        path = None
        if cfg.pseudo_path:
            from ..data.levir import read_cameras

            path = read_cameras(cfg.pseudo_path)
        frames = [f.cam.cam for f in self.train_frames]
        train_views = [_SimpleView(c, f.image.numpy()) for c, f in zip(frames, self.train_frames)]
        from ..geometry.surface import decide

        surface, why = decide(cfg.pseudo.surface, frames)
        self.report.decide("train", "pseudo_depth_height_field", surface, why)
        pvs = build_pseudo_views(train_views, np.asarray(points), cfg.pseudo.n_views, cfg.seed,
                                 self.work / "pseudo", path=path, surface=surface,
                                 consistency_tol=cfg.pseudo.consistency_tol)
        if cfg.pseudo.consistency_tol > 0:
            rej = float(np.mean([pv.rejected.mean() for pv in pvs if pv.rejected is not None] or [0.0]))
            self.report.values["pseudo_rejected_fraction"] = rej
            log.info("pseudo views: %.1f%% of pixels rejected (training views disagree by > %.2f)",
                     100 * rej, cfg.pseudo.consistency_tol)
        empty = 0
        for pv in pvs:
            weight = np.asarray(pv.valid, np.float32)
            if getattr(pv, "padded", None) is not None:
                weight = np.maximum(weight, cfg.pseudo.padded_weight * np.asarray(pv.padded, np.float32))
            if not (weight > 0).any():
                empty += 1
                continue
            self.pseudo_frames.append(Frame(CamT.of(pv.camera), torch.from_numpy(
                np.ascontiguousarray(np.clip(pv.image[..., :3], 0, 1), dtype=np.float32)),
                torch.from_numpy(weight)))
        self.report.decide("train", "pseudo_views", bool(self.pseudo_frames),
                           f"{len(self.pseudo_frames)} progressive-DIBR pseudo views"
                           + (f" ({empty} without any filled pixel left out)" if empty else "")
                           + (f" on the path {cfg.pseudo_path}" if cfg.pseudo_path else " on the acquisition orbit"))

    # -- evaluation for the curve ---------------------------------------------------
    @torch.no_grad()
    def evaluate_heldout(self) -> tuple[float, float]:
        from .losses import psnr, ssim

        frames = self.test_frames
        if self.cfg.curve_max_views and len(frames) > self.cfg.curve_max_views:
            idx = np.linspace(0, len(frames) - 1, self.cfg.curve_max_views).round().astype(int)
            frames = [frames[i] for i in idx]
        if not frames:
            return float("nan"), float("nan")
        ps, ss = [], []
        for f in frames:
            img = self.method.render(f.cam, self.bg)[0].clamp(0, 1)
            ps.append(float(psnr(img, f.image)))
            ss.append(float(ssim(img, f.image)))
        self.method.last = None
        return float(np.mean(ps)), float(np.mean(ss))

    def _write_curve(self) -> None:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=CURVE_COLUMNS)
        w.writeheader()
        for r in self.curve:
            w.writerow(r)
        write_text(self.work / "curve.csv", buf.getvalue())

    def _plot_curve(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
        t = [r["seconds"] for r in self.curve]
        ax[0].plot(t, [r["psnr"] for r in self.curve], marker=".")
        ax[0].set(xlabel="training time [s]", ylabel="held-out PSNR [dB]")
        ax[1].plot(t, [r["ssim"] for r in self.curve], marker=".", color="C1")
        ax[1].set(xlabel="training time [s]", ylabel="held-out SSIM")
        fig.suptitle(f"{self.cfg.method} ({self.cfg.preset} preset)")
        fig.tight_layout()
        with atomic_path(self.work / "curve.png") as tmp:
            fig.savefig(tmp, dpi=100)
        plt.close(fig)

    def _curve_point(self, it: int) -> None:
        p, s = self.evaluate_heldout()
        self.curve.append({"seconds": round(self.elapsed, 3), "iteration": it, "psnr": p, "ssim": s})
        self._write_curve()
        log.info("curve: %.1f s, it %d, held-out PSNR %.2f dB, SSIM %.4f", self.elapsed, it, p, s)

    # -- checkpoints ---------------------------------------------------------------
    def _save_checkpoint(self, it: int) -> None:
        st = {
            "version": 1, "iteration": it, "config": self.cfg.to_dict(), "method": self.method.state(),
            "model_meta": getattr(self, "model_meta", None),
            "rng": {"torch": torch.get_rng_state(), "numpy": self.rng.bit_generator.state},
            "view_stack": list(self.view_stack), "pseudo_stack": list(self.pseudo_stack),
            "elapsed": self.elapsed, "next_curve_at": self.next_curve_at, "curve": self.curve,
            "skipped": self.skipped, "report": self.report.to_dict(),
        }
        with atomic_path(self.work / CHECKPOINT) as tmp:
            torch.save(st, tmp)

    def _restore(self, ck: dict[str, Any]) -> int:
        self.method.load(ck["method"])
        torch.set_rng_state(ck["rng"]["torch"])
        self.rng.bit_generator.state = ck["rng"]["numpy"]
        self.view_stack = list(ck["view_stack"])
        self.pseudo_stack = list(ck["pseudo_stack"])
        self.elapsed = float(ck["elapsed"])
        self.next_curve_at = float(ck["next_curve_at"])
        self.curve = list(ck["curve"])
        self.skipped = int(ck["skipped"])
        g = ck["report"]["values"].get("growth")
        if g:
            self.report.values["growth"] = g
        return int(ck["iteration"])

    def save_model(self) -> Path:
        m = self.method
        st: dict[str, Any] = {"method": m.name, "config": self.cfg.to_dict(),
                              "scene": str(self.scene_root.resolve()), "model": m.model.state_dict(),
                              "train_cameras": [camera_to_dict(f.cam.cam) for f in self.train_frames]}
        if m.name == "dibrgs":
            st["model_meta"] = self.model_meta
            st["ibr_feats"] = m.final_ibr()
        else:
            st["active_sh_degree"] = m.model.active_sh_degree
        path = self.work / MODEL
        with atomic_path(path) as tmp:
            torch.save(st, tmp)
        return path

    # -- signals -------------------------------------------------------------------
    @contextlib.contextmanager
    def _signals(self):
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def handler(signum, frame):
            log.warning("signal %d: checkpointing and stopping after this iteration", signum)
            self._stop = True

        old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, h in old.items():
                signal.signal(s, h)

    def request_stop(self) -> None:
        self._stop = True

    def _emit(self, obj: dict[str, Any]) -> None:
        if self.progress_json:
            import sys

            out = self.stream or sys.stdout
            out.write(json.dumps(obj) + "\n")
            out.flush()

    # -- the loop --------------------------------------------------------------------
    def run(self, stop_after: int | None = None) -> TrainResult:
        """Train to ``cfg.iterations``; ``stop_after`` checkpoints and stops early (as an interrupt)."""
        from tqdm import tqdm

        from .losses import photometric_loss

        log_handler = logging.FileHandler(self.work / "train.log") if self.work.exists() else None
        ckpt = self._setup()
        if log_handler is None:
            log_handler = logging.FileHandler(self.work / "train.log")
        log_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logging.getLogger("dibrgs").addHandler(log_handler)
        try:
            return self._loop(ckpt, stop_after, tqdm, photometric_loss)
        finally:
            logging.getLogger("dibrgs").removeHandler(log_handler)
            log_handler.close()

    def _loop(self, ckpt: dict | None, stop_after: int | None, tqdm: Any, photometric_loss: Callable) -> TrainResult:
        cfg = self.cfg
        T = cfg.iterations
        self.rng = np.random.default_rng(cfg.seed)
        self.view_stack: list[int] = []
        self.pseudo_stack: list[int] = []
        self.elapsed = 0.0
        self.curve: list[dict[str, float]] = []
        self.next_curve_at = 0.0
        self.skipped = 0
        start_it = 0
        if ckpt is not None:
            start_it = self._restore(ckpt)
        p_start, p_until = cfg.it(cfg.pseudo.start), cfg.it(cfg.pseudo.until)
        p_every = max(cfg.pseudo.min_every, cfg.it(cfg.pseudo.every))
        use_pseudo = bool(getattr(self, "pseudo_frames", []))
        self.report.values["schedule"] = {
            "iterations": T, "pseudo": [p_start, p_until, p_every] if use_pseudo else None,
            "growth": [self.method.strategy.start, self.method.strategy.until, self.method.strategy.every],
        }
        self.report.save(self.work / "report.json")
        if start_it == 0 and not self.curve:
            self._curve_point(0)
            self.next_curve_at = cfg.curve_every_s
        last_ckpt = time.monotonic()
        ema = None
        it = start_it
        status = "done"
        bar = tqdm(total=T, initial=start_it, desc=f"train {cfg.method}", unit="it", dynamic_ncols=True,
                   disable=None)
        with self._signals():
            while it < T:
                if self._stop or (stop_after is not None and it >= stop_after):
                    status = "interrupted"
                    break
                t0 = time.perf_counter()
                it += 1
                self.method.set_lr(it)
                pseudo_it = use_pseudo and p_start <= it <= p_until and it % p_every == 0
                if pseudo_it:
                    if not self.pseudo_stack:
                        self.pseudo_stack = self.rng.permutation(len(self.pseudo_frames)).tolist()
                    frame = self.pseudo_frames[self.pseudo_stack.pop()]
                else:
                    if not self.view_stack:
                        self.view_stack = self.rng.permutation(len(self.train_frames)).tolist()
                    frame = self.train_frames[self.view_stack.pop()]
                img, _alpha, _depth, aux = self.method.render(frame.cam, self.bg)
                loss = photometric_loss(img, frame.image, lam=cfg.lambda_dssim, mask=frame.mask)
                if cfg.lambda_volume:
                    loss = loss + cfg.lambda_volume * self.method.regulariser(aux)
                lv = float(loss.detach())
                stepped = False
                if not math.isfinite(lv):
                    self._skip(it, "loss is not finite")
                elif loss.requires_grad:
                    loss.backward()
                    if self._grads_finite():
                        self.method.after_backward(it)
                        self.method.step(it)
                        stepped = True
                    else:
                        self._skip(it, "gradients are not finite")
                self.method.zero_grad()
                if stepped:
                    self._sanitize_params()
                self.method.after_step(it, self.report)
                self.method.last = None
                self.elapsed += time.perf_counter() - t0
                if math.isfinite(lv):
                    ema = lv if ema is None else 0.6 * ema + 0.4 * lv
                bar.update(1)
                if it % 10 == 0 and ema is not None:
                    bar.set_postfix(loss=f"{ema:.4f}", **self.method.sizes())
                if self.progress_json and (it % cfg.progress_every == 0 or it == T):
                    rate = self.elapsed / max(it - start_it, 1)
                    self._emit({"iteration": it, "total": T, "loss": ema, "eta_s": rate * (T - it),
                                "elapsed_s": self.elapsed})
                if self.elapsed >= self.next_curve_at and it < T:
                    self._curve_point(it)
                    while self.next_curve_at <= self.elapsed:
                        self.next_curve_at += cfg.curve_every_s
                if time.monotonic() - last_ckpt >= cfg.checkpoint_every_s:
                    self._save_checkpoint(it)
                    last_ckpt = time.monotonic()
        bar.close()
        if status == "done" and (not self.curve or self.curve[-1]["iteration"] != it):
            self._curve_point(it)
        self._save_checkpoint(it)
        self.report.values["sizes"] = self.method.sizes()
        self.report.values["skipped_steps"] = self.skipped
        self.report.values["train_seconds"] = self.elapsed
        self.report.values["iteration"] = it
        # Peak resident memory of this process (Linux reports KiB); a resumed run reports its last leg.
        self.report.values["train_peak_memory_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        self.report.save(self.work / "report.json")
        if status == "done":
            self.save_model()
            with contextlib.suppress(Exception):
                self._plot_curve()
            self._emit({"done": True, "work": str(self.work), "iteration": it, "elapsed_s": self.elapsed})
        else:
            log.info("stopped at iteration %d; `--resume` continues from %s", it, self.work / CHECKPOINT)
        return TrainResult(status, it, self.work, self.elapsed, self.skipped, self.method.sizes())

    def _skip(self, it: int, why: str) -> None:
        self.skipped += 1
        log.warning("iteration %d: %s; step skipped", it, why)

    def _grads_finite(self) -> bool:
        for p in self.method.parameters():
            if p.grad is not None and not torch.isfinite(p.grad).all():
                return False
        return True

    @torch.no_grad()
    def _sanitize_params(self) -> None:
        """Keep parameters finite even under absurd learning rates (logged once per step)."""
        bad = False
        for p in self.method.parameters():
            if not torch.isfinite(p).all():
                torch.nan_to_num_(p, nan=0.0, posinf=1e6, neginf=-1e6)
                bad = True
        if bad:
            log.warning("non-finite parameters replaced by finite values")


def random_init(cams: list[Camera], n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points (and grey colours in [0,1]) in the volume the cameras look at.

    A flat box around the cameras' common look-at point: horizontally as wide as
    the mean image footprint there, vertically a quarter of that.
    """
    from ..camera.frame import estimate_up, look_at_target, up_frame

    target = look_at_target(cams)
    up, _ = estimate_up(cams)
    R = up_frame(up)
    half = float(np.mean([np.linalg.norm(c.center - target) * c.width / (2 * c.K[0, 0]) for c in cams]))
    local = rng.uniform(-1, 1, (n, 3)) * np.array([half, half, half / 4])
    return target + local @ R, np.full((n, 3), 0.5)


class _SimpleView:
    """(camera, image) pair handed to the pseudo-view builder."""

    def __init__(self, camera: Camera, image: np.ndarray) -> None:
        self.camera = camera
        self.image = image
        self.depth = None


def _init_says_near_nadir(res: Any) -> bool | None:
    """What the geometry report says about near-nadir views (None when it says nothing)."""
    rep = getattr(res, "report", None)
    if rep is None:
        return None
    for key in ("near_nadir", "height_map"):
        v = rep.applied(key) if hasattr(rep, "applied") else None
        if v is not None:
            return bool(v)
    val = getattr(rep, "values", {}).get("near_nadir")
    return None if val is None else bool(val)


def train(scene_root: str | Path, work: str | Path, cfg: TrainConfig, **kw: Any) -> TrainResult:
    """Convenience wrapper: build a :class:`Trainer` and run it."""
    stop_after = kw.pop("stop_after", None)
    return Trainer(scene_root, work, cfg, **kw).run(stop_after=stop_after)
