"""Error against run time: held-out PSNR / SSIM at points of the training wall-clock.

Each point evaluates a fixed, evenly spread subset of the held-out views
(``TrainConfig.curve_max_views``), the last point all of them; rendering runs without
autograd and its time is not training time.

``curve.csv`` has one row a point (``seconds`` of training, evaluation and checkpoint time
excluded; ``iteration``; ``psnr`` in dB; ``ssim``); ``curve.png`` plots both against seconds.
"""
from __future__ import annotations

import csv
import io
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..common.fileio import atomic_path, write_text
from ..common.report import Report
from ..models.base import render_model
from .frames import Frame
from .losses import psnr, ssim

CURVE_COLUMNS = ["seconds", "iteration", "psnr", "ssim"]

log = logging.getLogger("dibrgs.train")


def next_curve_time(seconds: float, every: float) -> float:
    """Training second of the curve point after one at ``seconds``: the next multiple of ``every``
    (``every`` 0: right away, a point after every iteration)."""
    return (math.floor(seconds / every) + 1) * every if every > 0 else 0.0


def curve_views(n: int, max_views: int | None) -> list[int]:
    """Indices of the held-out views a curve point evaluates: all ``n``, or ``max_views`` of
    them evenly spread (the same ones at every point, so points compare)."""
    if not max_views or n <= max_views:
        return list(range(n))
    return np.unique(np.linspace(0, n - 1, max_views).round().astype(int)).tolist()


def curve_decision(n_test: int, every_s: float, max_views: int | None) -> tuple[bool, str]:
    """Whether a run evaluates curve points (only when its split holds views out), and why."""
    if not n_test:
        return False, "no held-out views in the split: no error against time"
    return True, (f"held-out PSNR / SSIM every {every_s:g} s of training on {len(curve_views(n_test, max_views))} "
                  f"of {n_test} held-out views, all at the end")


@torch.no_grad()
def heldout_scores(model: Any, frames: list[Frame], background: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """PSNR and SSIM of ``model`` on each of ``frames`` (no autograd; over the pixels that hold data)."""
    ps, ss = [], []
    for f in frames:
        img = render_model(model, f.cam, background, "RGB")[0].clamp(0, 1)
        ps.append(float(psnr(img, f.image, mask=f.mask)))
        ss.append(float(ssim(img, f.image, mask=f.mask)))
    return np.asarray(ps, dtype=np.float64), np.asarray(ss, dtype=np.float64)


def evaluate_heldout(model: Any, frames: list[Frame], background: torch.Tensor,
                     max_views: int | None = None) -> tuple[float, float]:
    """Mean PSNR and SSIM of ``model`` on ``frames`` (at most ``max_views`` of them, evenly spread)."""
    frames = [frames[i] for i in curve_views(len(frames), max_views)]
    if not frames:
        return float("nan"), float("nan")
    ps, ss = heldout_scores(model, frames, background)
    return float(ps.mean()), float(ss.mean())


class CurveLog:
    """A run's curve points, each written to ``curve.csv`` as it is scored: ``every_s`` training
    seconds on :func:`curve_views`' subset of ``frames``, the last point (:meth:`end`) on all of
    them with the subset's mean beside it in ``report``. The caller keeps scoring off its
    training clock."""

    def __init__(self, path: Path, frames: list[Frame], background: torch.Tensor, every_s: float,
                 max_views: int | None, report: Report) -> None:
        self.path, self.frames, self.background, self.every_s, self.report = path, frames, background, every_s, report
        self.subset = curve_views(len(frames), max_views)
        self.points: list[dict[str, float]] = []
        self.final = False  # whether the last point scored every held-out view
        self.next_at = 0.0  # training second of the next point

    def restore(self, points: list[dict[str, float]], final: bool) -> None:
        """A checkpoint's points; ``final``: its last one scored every view (a finished leg)."""
        self.points, self.final = list(points), final
        # From the last point at this run's interval, which a resumed run may have changed.
        self.next_at = next_curve_time(self.points[-1]["seconds"] if self.points else 0.0, self.every_s)

    def add(self, model: Any, it: int, seconds: float, final: bool = False) -> None:
        """Score ``model`` at iteration ``it``, ``seconds`` of training: the subset, every view when ``final``."""
        t0 = time.perf_counter()
        idx = list(range(len(self.frames))) if final else self.subset
        ps, ss = heldout_scores(model, [self.frames[i] for i in idx], self.background)
        p, s = float(ps.mean()), float(ss.mean())
        self.points.append({"seconds": round(seconds, 3), "iteration": it, "psnr": p, "ssim": s})
        self.final, self.next_at = final, next_curve_time(seconds, self.every_s)
        write_curve(self.path, self.points)
        c = self.report.values.setdefault("curve", {"views_per_point": len(self.subset), "eval_seconds": 0.0})
        c["eval_seconds"] += time.perf_counter() - t0  # this process's points
        if final:
            c.update(views_final=len(idx), final_psnr_on_point_views=float(ps[self.subset].mean()))
        log.info("curve: %.1f s, it %d, held-out PSNR %.2f dB, SSIM %.4f (%d views)", seconds, it, p, s, len(idx))

    def go_on(self, model: Any, it: int) -> None:
        """A run resumed at ``it`` goes on: a finished leg's last point, which scored every view, is
        scored again on the subset (``model`` is the one it scored), so that the points before the
        new end compare."""
        if self.final and self.points and self.points[-1]["iteration"] == it and len(self.subset) < len(self.frames):
            seconds = self.points.pop()["seconds"]
            self.add(model, it, seconds)
            log.info("curve: the finished run's last point scored again on the %d held-out views the points use",
                     len(self.subset))

    def end(self, model: Any, it: int, seconds: float) -> None:
        """The last point, on every view (in place of a subset point at the same iteration)."""
        if self.points and self.points[-1]["iteration"] == it:
            self.points.pop()
        self.add(model, it, seconds, final=True)


def write_curve(path: Path, rows: list[dict[str, float]]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CURVE_COLUMNS)
    w.writeheader()
    for r in rows:
        w.writerow(r)
    write_text(path, buf.getvalue())


def plot_curve(path: Path, rows: list[dict[str, float]], title: str) -> None:
    """Held-out PSNR and SSIM against training seconds (PNG); nothing without points."""
    if not rows:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    t = [r["seconds"] for r in rows]
    ax[0].plot(t, [r["psnr"] for r in rows], marker=".")
    ax[0].set(xlabel="training time [s]", ylabel="held-out PSNR [dB]")
    ax[1].plot(t, [r["ssim"] for r in rows], marker=".", color="C1")
    ax[1].set(xlabel="training time [s]", ylabel="held-out SSIM")
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
