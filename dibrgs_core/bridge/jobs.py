"""``dibrgs`` subprocesses for the add-on: command lines and a non-blocking runner.

Blender's Python changes between releases and torch is gigabytes, so the
add-on never imports torch: every heavy step runs as
``PYTHON -m dibrgs_core <command> ...`` with an interpreter that has torch.
``PYTHONPATH`` is prefixed with the folder that holds this very
``dibrgs_core`` package, so the subprocess runs the same library version as
the add-on (the one bundled in the extension, or the repository checkout).

:class:`JobRunner` runs a list of steps one after another without blocking:
a reader thread copies each stdout line into the step's log file and a
queue, :meth:`JobRunner.poll` (called from a Blender timer) folds progress
lines in and starts the next step. :meth:`JobRunner.cancel` sends SIGINT
(the training saves its checkpoint on KeyboardInterrupt) and kills the
process if it has not stopped after a grace period.
"""
from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from ..common.limits import MAX_RESOLUTION_SCALE
from ..common.modes import MethodName, choices
from ..training.config import PRESETS
from .progress import Progress, parse_progress_line

METHODS = choices(MethodName)
#: Views rendered along the path into the compositor after training: the pseudo-view count, at
#: most this many, evenly spaced (96 renders of 12-megapixel drone photos would take minutes and
#: gigabytes in Blender; the fly-through renders as many frames as asked).
RESULT_PATH_VIEWS = 16


def result_path_views(preset: str, requested: int = 0) -> int:
    """How many views along the path the results step renders (:data:`RESULT_PATH_VIEWS`)."""
    return min(pseudo_view_count(preset, requested), RESULT_PATH_VIEWS)


def pseudo_view_count(preset: str, requested: int = 0) -> int:
    """Pseudo views to sample on the add-on's path: ``requested``, or when it is 0 the
    preset's own count (:mod:`dibrgs_core.training.config`, 96 for ``cpu``)."""
    if requested > 0:
        return int(requested)
    from ..training.config import preset as make_preset

    return make_preset(preset).pseudo.n_views


def pseudo_views_left_out(preset: str, n_train: int) -> str | None:
    """Why training with ``preset`` will leave pseudo views out for ``n_train`` training views
    (:meth:`~dibrgs_core.training.config.PseudoConfig.dense_reason`), or None."""
    from ..training.config import preset as make_preset

    return make_preset(preset).pseudo.dense_reason(n_train)


def core_root() -> Path:
    """The folder that contains the ``dibrgs_core`` package this module belongs to."""
    return Path(__file__).resolve().parents[2]


def subprocess_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for a ``dibrgs`` subprocess: this library first on PYTHONPATH, unbuffered output."""
    env = dict(os.environ if base is None else base)
    paths = [str(core_root())] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    env["PYTHONUNBUFFERED"] = "1"
    return env


def dibrgs_command(python: str, command: str, *args: str | os.PathLike) -> list[str]:
    """``[python, -m, dibrgs_core, command, *args]`` with every argument as a string."""
    return [str(python), "-m", "dibrgs_core", command, *map(str, args)]


@dataclass
class Weights:
    """Optional local weight paths (empty or None = not given); nothing is downloaded."""

    depth_model: str | None = None
    dino_resnet: str | None = None
    dino_vit: str | None = None
    lpips: str | None = None

    def flags(self, *names: str) -> list[str]:
        out: list[str] = []
        for name in names:
            value = getattr(self, name)
            if value:
                out += ["--" + name.replace("_", "-"), str(value)]
        return out


@dataclass
class TrainOptions:
    """What the add-on passes to ``dibrgs train`` (``iterations`` / ``resolution_scale`` /
    ``pseudo_views`` None: the preset's; ``pseudo_path``: cameras of a path the user edited, else
    None and training samples pseudo views along the trajectory itself; ``split``: (training,
    held-out) view ids the user chose in Blender, else None and the scene's own split holds)."""

    preset: str = "cpu"
    method: str = "dibrgs"
    iterations: int | None = None
    resolution_scale: float | None = None
    pseudo_views: int | None = None
    pseudo_path: Path | None = None
    resume: bool = False
    weights: Weights = field(default_factory=Weights)
    split: tuple[list[str], list[str]] | None = None
    extra: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; expected one of {PRESETS}")
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; expected one of {METHODS}")
        if self.iterations is not None and self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.resolution_scale is not None and not 0 < self.resolution_scale <= MAX_RESOLUTION_SCALE:
            raise ValueError(f"resolution_scale must be in (0, {MAX_RESOLUTION_SCALE:g}], got {self.resolution_scale}")
        if self.pseudo_views is not None and self.pseudo_views < 1:
            raise ValueError(f"pseudo_views must be >= 1, got {self.pseudo_views}")


def train_command(python: str, scene: Path, work: Path, opts: TrainOptions) -> list[str]:
    """``dibrgs train SCENE --out WORK ... --progress-json``."""
    args: list[str] = [str(scene), "--out", str(work), "--preset", opts.preset, "--method", opts.method,
                       "--progress-json"]
    if opts.iterations is not None:
        args += ["--iterations", str(opts.iterations)]
    if opts.resolution_scale is not None:
        args += ["--resolution-scale", repr(float(opts.resolution_scale))]
    if opts.pseudo_path is not None:
        args += ["--pseudo-path", str(opts.pseudo_path)]
    elif opts.pseudo_views is not None:
        args += ["--pseudo-views", str(opts.pseudo_views)]
    if opts.resume:
        args.append("--resume")
    args += split_flags(opts.split)
    args += opts.weights.flags("depth_model", "dino_resnet", "dino_vit")
    args += list(opts.extra)
    return dibrgs_command(python, "train", *args)


def init_command(python: str, scene: Path, work: Path, weights: Weights | None = None,
                 split: tuple[list[str], list[str]] | None = None) -> list[str]:
    """``dibrgs init SCENE --out WORK`` (writes ``WORK/init/``), with ``split`` as for :class:`TrainOptions`."""
    return dibrgs_command(python, "init", scene, "--out", work, *split_flags(split),
                          *(weights or Weights()).flags("depth_model"))


def split_flags(split: tuple[list[str], list[str]] | None) -> list[str]:
    """``--train A,B --test C`` for (training, held-out) view ids (``--test none`` for none), or
    nothing for None. ValueError for no training view or a view id the option cannot hold."""
    if split is None:
        return []
    train, test = split
    if not train:
        raise ValueError("no training view")
    bad = [n for n in [*train, *test] if "," in n or n != n.strip() or not n]
    bad += [n for n in train if not test and n.lower() == "none"]  # "--test none" would name that view
    if bad:
        raise ValueError(f"view {bad[0]!r} cannot be named in --train / --test here (a comma, outer spaces, or "
                         "'none' with nothing held out): give the scene a split.json instead")
    return ["--train", ",".join(train), "--test", ",".join(test) or "none"]


def render_command(python: str, work: Path, cameras: Path, out: Path) -> list[str]:
    """``dibrgs render WORK --cameras PATH --out DIR`` (writes ``DIR/NAME.png``)."""
    return dibrgs_command(python, "render", work, "--cameras", cameras, "--out", out)


def eval_command(python: str, work: Path, weights: Weights | None = None) -> list[str]:
    """``dibrgs eval WORK`` (writes ``WORK/metrics.json``)."""
    return dibrgs_command(python, "eval", work, *(weights or Weights()).flags("lpips"))


def check_command(python: str) -> list[str]:
    """``dibrgs check --json``: imports every dependency, builds the rasterizer (see :mod:`.checks`)."""
    return dibrgs_command(python, "check", "--json")


#: What ``dibrgs eval|render|export`` load: written when training reaches its last iteration.
MODEL_FILE = "model.pt"
#: Written at every checkpoint and on interruption; ``--resume`` continues from it.
CHECKPOINT_FILE = "checkpoint.pt"
#: The run's scene, split and configuration (``training/run_folder.py``), written when it starts.
CONFIG_FILE = "config.json"


def model_problem(work: Path) -> str | None:
    """None when ``work`` holds a trained model, else why not (one line for the user)."""
    work = Path(work)
    if (work / MODEL_FILE).is_file():
        return None
    if (work / CHECKPOINT_FILE).is_file():
        return f"training in {work} stopped before the end: train with Resume to finish it"
    return f"no trained model in {work}: train first"


def run_pseudo_path(work: Path) -> str | None:
    """The ``--pseudo-path`` the run in ``work`` was started with (its ``config.json``), or None
    (none, or no readable run there)."""
    try:
        cfg = json.loads((Path(work) / CONFIG_FILE).read_text())["config"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    path = cfg.get("pseudo_path") if isinstance(cfg, dict) else None
    return path if isinstance(path, str) and path else None


def log_tail(path: Path, lines: int = 5) -> str:
    """The last ``lines`` non-empty lines of a log file ("" if unreadable)."""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return ""
    return "\n".join([ln for ln in text.splitlines() if ln.strip()][-lines:])


@dataclass
class Step:
    """One subprocess of a job. ``progress``: its stdout carries ``--progress-json`` lines."""

    label: str
    cmd: list[str]
    log_path: Path
    progress: bool = False


class JobRunner:
    """Runs steps sequentially in subprocesses; poll it, or :meth:`wait` for it.

    States: ``pending`` -> ``running`` -> ``done`` | ``failed`` | ``cancelled``.
    On failure :attr:`error` names the step, the exit code and the log path,
    followed by the log's last lines.
    """

    def __init__(self, steps: Sequence[Step], env: dict[str, str] | None = None,
                 cwd: Path | None = None, on_line: Callable[[str], None] | None = None):
        if not steps:
            raise ValueError("a job needs at least one step")
        self.steps = list(steps)
        self.env = subprocess_env() if env is None else env
        self.cwd = cwd
        self.on_line = on_line
        self.state = "pending"
        self.index = -1
        self.progress = Progress()
        self.error: str | None = None
        self.returncode: int | None = None
        self._proc: subprocess.Popen | None = None
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._reader: threading.Thread | None = None
        self._log = None
        self._cancel_at: float | None = None
        self._cancelled = False

    # -- public -----------------------------------------------------------------
    @property
    def step(self) -> Step | None:
        return self.steps[self.index] if 0 <= self.index < len(self.steps) else None

    @property
    def finished(self) -> bool:
        return self.state in ("done", "failed", "cancelled")

    def start(self) -> "JobRunner":
        if self.state != "pending":
            raise RuntimeError(f"job already {self.state}")
        self.state = "running"
        self._next_step()
        return self

    def poll(self) -> str:
        """Consume the output so far, advance to the next step when one ends; never blocks."""
        if self.state != "running":
            return self.state
        while True:
            try:
                line = self._lines.get_nowait()
            except queue.Empty:
                break
            if line is None:  # reader reached EOF: the process is ending
                self._reap()
                return self.state
            self._handle_line(line)
        if self._cancel_at is not None and time.monotonic() > self._cancel_at and self._proc:
            self._proc.kill()  # did not stop within the grace period
            self._cancel_at = None
        return self.state

    def wait(self, interval_s: float = 0.1, timeout_s: float | None = None) -> str:
        """Block until the job ends (the batch-mode variant of polling)."""
        t0 = time.monotonic()
        if self.state == "pending":
            self.start()
        while not self.finished:
            self.poll()
            if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                self.cancel(grace_s=5.0)
                timeout_s = None
            time.sleep(interval_s)
        return self.state

    def cancel(self, grace_s: float = 30.0) -> None:
        """Ask the running step to stop (SIGINT, so training keeps its checkpoint); later steps are dropped."""
        if self.state != "running" or self._proc is None:
            if self.state == "pending":
                self.state = "cancelled"
            return
        # The state stays "running" until the process has exited (see poll).
        self.steps = self.steps[: self.index + 1]
        self._cancelled = True
        if self._proc.poll() is None:
            if sys.platform == "win32":
                self._proc.terminate()
            else:
                self._proc.send_signal(signal.SIGINT)
            self._cancel_at = time.monotonic() + grace_s

    # -- internals --------------------------------------------------------------
    def _next_step(self) -> None:
        self.index += 1
        step = self.steps[self.index]
        step.log_path.parent.mkdir(parents=True, exist_ok=True)
        self.progress = Progress()
        self._log = open(step.log_path, "a", encoding="utf-8")
        self._log.write("$ " + " ".join(step.cmd) + "\n")
        self._log.flush()
        try:
            self._proc = subprocess.Popen(
                step.cmd, stdout=subprocess.PIPE, stderr=self._log, stdin=subprocess.DEVNULL,
                text=True, bufsize=1, env=self.env, cwd=self.cwd,
                start_new_session=(sys.platform != "win32"))
        except OSError as e:
            self._log.write(f"cannot start: {e}\n")
            self._log.close()
            self.state = "failed"
            self.error = f"{step.label}: cannot start {step.cmd[0]!r} ({e}); log: {step.log_path}"
            return
        self._reader = threading.Thread(target=self._read, args=(self._proc, self._log), daemon=True)
        self._reader.start()

    def _read(self, proc: subprocess.Popen, log) -> None:
        assert proc.stdout is not None
        with proc.stdout:  # the pipe is done with at EOF (left open, it outlives the job)
            for line in proc.stdout:
                log.write(line)
                log.flush()
                self._lines.put(line)
        self._lines.put(None)

    def _handle_line(self, line: str) -> None:
        step = self.step
        if step is not None and step.progress:
            ev = parse_progress_line(line)
            if ev is not None:
                self.progress.update(ev)
                return
        if self.on_line is not None:
            self.on_line(line.rstrip("\n"))

    def _reap(self) -> None:
        assert self._proc is not None and self.step is not None
        rc = self._proc.wait()
        if self._reader is not None:
            self._reader.join()
        self._log.close()
        self.returncode = rc
        step = self.step
        if self._cancelled:
            self.state = "cancelled"
        elif rc != 0:
            self.state = "failed"
            tail = log_tail(step.log_path)
            self.error = (f"{step.label} failed (exit code {rc}); log: {step.log_path}"
                          + (f"\n{tail}" if tail else ""))
        elif self.index + 1 < len(self.steps):
            self._next_step()
        else:
            self.state = "done"
