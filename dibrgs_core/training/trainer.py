"""The training loop (both methods), with resumable checkpoints.

Run folder (``WORK``):

* ``config.json`` - the :class:`~dibrgs_core.training.config.TrainConfig` and the scene path;
* ``init/`` - geometry initialisation (dense cloud, height map, its report), reused
  when present (:mod:`.setup`);
* ``pseudo/`` - cached pseudo views;
* ``checkpoint.pt`` / ``model.pt`` - see :mod:`.checkpoint`;
* ``curve.csv`` / ``curve.png`` - held-out PSNR / SSIM against training wall-clock
  seconds (evaluation and checkpoint time excluded; :mod:`.curve`);
* ``report.json`` - every automatic decision and its reason; ``train.log``.

Loss (paper Eq. "Optimization" + Scaffold-GS): ``(1 - 0.2) L1 + 0.2 D-SSIM`` on the
iteration's view (a training view, or on pseudo-view iterations a pseudo view
restricted to its filled pixels), the render first put through the view's colour
transform when the run learns them (:mod:`.appearance`; plus their penalty), plus
``0.01 *`` the method's regulariser (DIBR-GS: the mean ``prod(scales)`` of the
rasterized neural Gaussians, in paper units). A step whose loss or gradients are not
finite is skipped and logged.
"""
from __future__ import annotations

import contextlib
import json
import logging
import logging.handlers
import math
import random
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..common.allocator import allocator_policy
from ..common.blas import blas_policy
from ..common.errors import InputError
from ..common.fileio import write_json
from ..common.limits import MAX_RESOLUTION_SCALE, MIN_RESOLUTION
from ..common.lock import run_folder_lock
from ..common.openmp import wait_policy
from ..common.report import Report
from ..data.load import load_scene
from ..data.scene import Scene, no_data_decision, origin_decision
from ..data.split import require_train_views
from ..models.base import render_model
from .checkpoint import CHECKPOINT, MODEL, load_checkpoint, save_model, save_torch
from .config import TrainConfig, resolve_resolution
from .curve import CurveLog, curve_decision, plot_curve
from .frames import Frame, has_data, views_to_frames
from .guard import all_finite, make_finite, stop_on_signals
from .losses import photometric_loss
from .methods import TrainingMethod
from .run_folder import CONFIG, Identity, check_resumable, replace_earlier_run, resumed_config, stored_identity
from .setup import METHODS, SetupContext

log = logging.getLogger("dibrgs.train")


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
                 stream: Any = None, train_ids: list[str] | None = None, test_ids: list[str] | None = None,
                 force_config: bool = False) -> None:
        self.scene_root = Path(scene_root)
        self.scene_origin = np.zeros(3)  # the scene's Scene.origin, once it is read
        self.work = Path(work)
        self.cfg = cfg
        self.resume = resume
        self.progress_json = progress_json
        self.depth_model = depth_model
        self.stream = stream
        self.split_request = (train_ids, test_ids)
        self.force_config = force_config
        self.report = Report()
        self._stop = False
        self._prepared: tuple[dict[str, Any] | None, Scene, str] | None = None
        self.method: TrainingMethod
        self.train_frames: list[Frame] = []
        self.test_frames: list[Frame] = []
        self.pseudo_frames: list[Frame] = []

    # -- setup ----------------------------------------------------------------
    def _prepare(self) -> tuple[dict[str, Any] | None, Scene, str]:
        """Check the options, read the scene with its split, and settle what happens to an earlier run
        in the folder (:mod:`.run_folder`): (checkpoint to resume or None, scene, scene digest)."""
        cfg = self.cfg
        if cfg.method not in METHODS:
            raise InputError(None, f"unknown method {cfg.method!r} ({' or '.join(METHODS)})")
        if not (isinstance(cfg.iterations, int) and cfg.iterations >= 1):
            raise InputError(None, f"--iterations must be a positive integer, got {cfg.iterations!r}")
        if cfg.resolution_scale is not None and not (0.0 < cfg.resolution_scale <= MAX_RESOLUTION_SCALE):
            raise InputError(None, f"--resolution-scale must be in (0, {MAX_RESOLUTION_SCALE:g}], "
                                   f"got {cfg.resolution_scale!r}")
        if self.work.exists() and not self.work.is_dir():
            raise InputError(self.work, "is a file, not a folder; give --out a folder for the run")
        self.work.mkdir(parents=True, exist_ok=True)
        scene = load_scene(self.scene_root, *self.split_request)
        require_train_views(scene)
        digest = scene.digest()
        split = (list(scene.train), list(scene.test))
        ck_path = self.work / CHECKPOINT
        ckpt = None
        if self.resume and ck_path.exists():
            ckpt = load_checkpoint(ck_path)
            check_resumable(ck_path, Identity.of(ckpt["report"].get("values", {}).get("scene", {})), digest, split)
            self.cfg = resumed_config(ck_path, ckpt, self.cfg, self.force_config, self.report)
        else:
            old = stored_identity(self.work)
            if self.resume and old is not None and old.digest not in (None, digest):
                raise InputError(self.work, f"holds a run of another scene ({old.scene}); refusing to --resume "
                                            "it: choose another --out, or drop --resume to replace it")
            if self.resume:
                log.info("--resume: no checkpoint in %s, starting fresh", self.work)
            replace_earlier_run(self.work, digest, split, "train")
        return ckpt, scene, digest

    def setup(self) -> dict[str, Any] | None:
        """Read the scene, build the method (and pseudo views); returns the checkpoint to resume."""
        if self._prepared is None:
            self._prepared = self._prepare()
        ckpt, scene, digest = self._prepared
        cfg = self.cfg
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)
        train_views, test_views = scene.train_views(), scene.test_views()
        # The configuration keeps what the user gave (None: the preset's pixel budget decides),
        # so a resumed run compares like with like; evaluation resolves it the same way.
        s, budget, why = resolve_resolution(cfg, [(v.camera.width, v.camera.height) for v in train_views + test_views])
        self.report.decide("train", "pixel_budget", budget, why)
        self.train_frames = views_to_frames(train_views, s)
        self.test_frames = [f for f in views_to_frames(test_views, s) if has_data(f)]  # else nothing to score
        for f in self.train_frames + self.test_frames:
            h, w = f.image.shape[:2]
            if min(h, w) < MIN_RESOLUTION:
                raise InputError(None, f"--resolution-scale {s:g} gives {w}x{h} images; training needs at least "
                                       f"{MIN_RESOLUTION} pixels a side: use a larger scale")
        h, w = self.train_frames[0].image.shape[:2]
        run = {"digest": digest, "train": list(scene.train), "test": list(scene.test),
               "split_source": scene.split_source, "resolution_scale": s}
        self.report.values["scene"] = dict(root=str(self.scene_root), layout=scene.layout, **run, resolution=[w, h])
        log.info("scene %s (digest %s): train %s, %d test views; split from %s", self.scene_root, digest,
                 ", ".join(scene.train), len(scene.test), scene.split_source)
        self.scene_origin = np.asarray(scene.origin, np.float64)
        self.report.values["scene_origin"] = self.scene_origin.tolist()
        self.report.decide("train", "recentre", *origin_decision(scene))
        self.report.decide("train", "no_data", *no_data_decision(scene))
        write_json(self.work / CONFIG, {"scene": str(self.scene_root.resolve()), "run": run,
                                        "config": cfg.to_dict(),
                                        "forced_config": self.report.values.get("forced_config", [])})
        self.bg = torch.tensor(cfg.background, dtype=torch.float32)
        self._build_rasterizer()
        # set-up randomness only (random init), apart from the training streams
        ctx = SetupContext(cfg, self.work, scene, self.train_frames, self.report,
                           np.random.default_rng(cfg.seed + 1), ckpt, self.depth_model, self._stage, s)
        built = METHODS[cfg.method](ctx)
        self.method, self.pseudo_frames = built.method, built.pseudo_frames
        return ckpt

    # -- checkpoints ---------------------------------------------------------------
    def _save_checkpoint(self, it: int) -> None:
        save_torch(self.work / CHECKPOINT, {
            "version": 2, "iteration": it, "config": self.cfg.to_dict(), "method": self.method.state(),
            "rng": {"torch": torch.get_rng_state(), "numpy": self.rng.bit_generator.state},
            "view_stack": list(self.view_stack), "pseudo_stack": list(self.pseudo_stack),
            "elapsed": self.elapsed, "curve": self.curve.points,
            "skipped": self.skipped, "report": self.report.to_dict(),
        })

    def _restore(self, ck: dict[str, Any]) -> int:
        self.method.load(ck["method"])
        torch.set_rng_state(ck["rng"]["torch"])
        self.rng.bit_generator.state = ck["rng"]["numpy"]
        self.view_stack, self.pseudo_stack = list(ck["view_stack"]), list(ck["pseudo_stack"])
        self.elapsed = float(ck["elapsed"])
        # Only a finished leg's report has views_final: its last point scored every held-out view.
        self.curve.restore(ck["curve"], "views_final" in ck["report"]["values"].get("curve", {}))
        self.skipped = int(ck["skipped"])
        if g := ck["report"]["values"].get("growth"):
            self.report.values["growth"] = g
        return int(ck["iteration"])

    def save_model(self) -> Path:
        return save_model(self.work / MODEL, self.method, self.cfg, self.scene_root,
                          [f.cam.cam for f in self.train_frames], self.scene_origin)

    def request_stop(self) -> None:
        self._stop = True

    def _stage(self, what: str, done: int | None = None, total: int | None = None) -> None:
        """Announce a long set-up stage (``{"stage": ...}`` on the progress stream)."""
        if not done:
            log.info("%s", what)
        self._emit({"stage": what} if total is None else {"stage": what, "done": done, "total": total})

    def _build_rasterizer(self) -> None:
        """Build the C++ rasterizer before set-up when it will be used, announcing a compile."""
        from ..render import get_backend

        if get_backend() == "reference":
            return
        from ..render import fast

        fast.build(on_start=lambda msg: self._stage(f"compiling the C++ rasterizer (first run, {fast.BUILD_TIME})"))

    def _emit(self, obj: dict[str, Any]) -> None:
        if self.progress_json:
            out = self.stream or sys.stdout
            out.write(json.dumps(obj) + "\n")
            out.flush()

    # -- the loop --------------------------------------------------------------------
    def run(self, stop_after: int | None = None) -> TrainResult:
        """Train to ``cfg.iterations``; ``stop_after`` checkpoints and stops early (as an interrupt).

        Holds the run folder's lock throughout (a second writer gets ``RunFolderBusy``)."""
        if self.work.exists() and not self.work.is_dir():
            raise InputError(self.work, "is a file, not a folder; give --out a folder for the run")
        with run_folder_lock(self.work, "train"):
            # What _prepare says (resume changes, a replaced run) is held back until an earlier
            # run's train.log is gone, then written first into this run's.
            held = logging.handlers.MemoryHandler(capacity=1 << 16, flushLevel=logging.CRITICAL + 1)
            logging.getLogger("dibrgs").addHandler(held)
            try:
                self._prepared = self._prepare()
            finally:
                logging.getLogger("dibrgs").removeHandler(held)
            log_handler = logging.FileHandler(self.work / "train.log")
            log_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
            held.setTarget(log_handler)
            held.close()  # flushes into train.log
            logging.getLogger("dibrgs").addHandler(log_handler)
            try:
                ckpt = self.setup()
                return self._loop(ckpt, stop_after)
            finally:
                logging.getLogger("dibrgs").removeHandler(log_handler)
                log_handler.close()

    def _next_frame(self, it: int, pseudo: tuple[int, int, int] | None) -> Frame:
        """The iteration's view: a pseudo view on pseudo iterations, else the next training view
        (each list is drawn in random order without repeats until it is used up)."""
        if pseudo is not None and pseudo[0] <= it <= pseudo[1] and it % pseudo[2] == 0:
            if not self.pseudo_stack:
                self.pseudo_stack = self.rng.permutation(len(self.pseudo_frames)).tolist()
            return self.pseudo_frames[self.pseudo_stack.pop()]
        if not self.view_stack:
            self.view_stack = self.rng.permutation(len(self.train_frames)).tolist()
        return self.train_frames[self.view_stack.pop()]

    def _loop(self, ckpt: dict | None, stop_after: int | None) -> TrainResult:
        from tqdm import tqdm

        cfg = self.cfg
        T = cfg.iterations
        method, model, strategy = self.method, self.method.model, self.method.strategy
        self.rng = np.random.default_rng(cfg.seed)
        self.view_stack: list[int] = []
        self.pseudo_stack: list[int] = []
        self.elapsed = 0.0
        self.curve = CurveLog(self.work / "curve.csv", self.test_frames, self.bg, cfg.curve_every_s,
                              cfg.curve_max_views, self.report)
        self.skipped = 0
        start_it = 0
        if ckpt is not None:
            start_it = self._restore(ckpt)
        pseudo_every = max(cfg.pseudo.min_every, cfg.it(cfg.pseudo.every))
        pseudo = (cfg.it(cfg.pseudo.start), cfg.it(cfg.pseudo.until), pseudo_every) if self.pseudo_frames else None
        self.report.values["schedule"] = {"iterations": T, "pseudo": list(pseudo) if pseudo else None,
                                          "growth": [strategy.start, strategy.until, strategy.every]}
        self.report.values["compute"] = {"threads": torch.get_num_threads(), "openmp_wait": wait_policy(),
                                         "blas": blas_policy(), "allocator": allocator_policy()}
        self.report.save(self.work / "report.json")
        curve = self.report.decide("train", "curve", *curve_decision(len(self.test_frames), cfg.curve_every_s,
                                                                     cfg.curve_max_views))
        if curve and start_it == 0 and not self.curve.points:
            self.curve.add(model, 0, 0.0)
        elif curve and start_it < T:
            self.curve.go_on(model, start_it)
        last_ckpt = time.monotonic()
        ema = None
        it = start_it
        status = "done"
        bar = tqdm(total=T, initial=start_it, desc=f"train {cfg.method}", unit="it", dynamic_ncols=True,
                   disable=None)
        with stop_on_signals(self.request_stop):
            while it < T:
                if self._stop or (stop_after is not None and it >= stop_after):
                    status = "interrupted"
                    break
                t0 = time.perf_counter()
                it += 1
                method.set_lr(it)
                frame = self._next_frame(it, pseudo)
                img, _alpha, _depth, info = render_model(model, frame.cam, self.bg, "RGB")
                strategy.step_pre_backward(model, method.optimizer, it, info)
                # Through the view's colour transform (new views render without one).
                seen, colour_penalty = method.as_photographed(img, frame.cam)
                loss = photometric_loss(seen, frame.image, lam=cfg.lambda_dssim, mask=frame.mask) + colour_penalty
                if cfg.lambda_volume:
                    loss = loss + method.regulariser(info, cfg.lambda_volume)
                lv = float(loss.detach())
                stepped = False
                if not math.isfinite(lv):
                    self._skip(it, "loss is not finite")
                elif loss.requires_grad:
                    loss.backward()
                    if all_finite([p.grad for p in method.parameters()]):
                        method.step(it)
                        stepped = True
                    else:
                        self._skip(it, "gradients are not finite")
                method.zero_grad()
                if stepped and make_finite(method.parameters()):
                    log.warning("non-finite parameters replaced by finite values")
                changes = strategy.step_post_backward(model, method.optimizer, it, info if stepped else None)
                method.after_step(it, changes, self.report)
                self.elapsed += time.perf_counter() - t0
                if math.isfinite(lv):
                    ema = lv if ema is None else 0.6 * ema + 0.4 * lv
                bar.update(1)
                if it % 10 == 0 and ema is not None:
                    bar.set_postfix(loss=f"{ema:.4f}", **model.sizes())
                if self.progress_json and (it % cfg.progress_every == 0 or it == T):
                    rate = self.elapsed / max(it - start_it, 1)
                    self._emit({"iteration": it, "total": T, "loss": ema, "eta_s": rate * (T - it),
                                "elapsed_s": self.elapsed})
                if curve and self.elapsed >= self.curve.next_at and it < T:
                    self.curve.add(model, it, self.elapsed)
                if time.monotonic() - last_ckpt >= cfg.checkpoint_every_s:
                    self._save_checkpoint(it)
                    last_ckpt = time.monotonic()
        bar.close()
        if status == "done" and curve:
            self.curve.end(model, it, self.elapsed)
        self._save_checkpoint(it)
        self.report.values["sizes"] = model.sizes()
        self.report.values["skipped_steps"] = self.skipped
        self.report.values["train_seconds"] = self.elapsed
        self.report.values["iteration"] = it
        # Peak resident memory of this process (Linux reports KiB); a resumed run reports its last leg.
        self.report.values["train_peak_memory_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        self.report.save(self.work / "report.json")
        if status == "done":
            self.save_model()
            with contextlib.suppress(Exception):
                plot_curve(self.work / "curve.png", self.curve.points, f"{cfg.method} ({cfg.preset} preset)")
            self._emit({"done": True, "work": str(self.work), "iteration": it, "elapsed_s": self.elapsed})
        else:
            log.info("stopped at iteration %d; `--resume` continues from %s", it, self.work / CHECKPOINT)
        return TrainResult(status, it, self.work, self.elapsed, self.skipped, model.sizes())

    def _skip(self, it: int, why: str) -> None:
        self.skipped += 1
        log.warning("iteration %d: %s; step skipped", it, why)


def train(scene_root: str | Path, work: str | Path, cfg: TrainConfig, **kw: Any) -> TrainResult:
    """Convenience wrapper: build a :class:`Trainer` and run it."""
    stop_after = kw.pop("stop_after", None)
    return Trainer(scene_root, work, cfg, **kw).run(stop_after=stop_after)
