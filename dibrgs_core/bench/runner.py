"""Benchmark suites: error against run time for DIBR-GS, the 3DGS baseline and ablations.

Every run is an independent job (generate the scene if missing, ``dibrgs
train``, ``dibrgs eval``) that returns a plain dict, so the same function
runs in-process or as a Ray task on a cluster. Finished runs are stored as
``<results>/runs/<scene>__<method>.json``; a restarted benchmark skips them
and resumes unfinished trainings from their checkpoints.

Units: times in seconds of training wall-clock (evaluation excluded), PSNR
in dB, memory in MiB.
"""
from __future__ import annotations

import csv
import json
import logging
import os
import platform
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from ..common.fileio import write_json
from ..synth.flights import DEFAULT_ORBIT

log = logging.getLogger("dibrgs.benchmark")

_SCENE_LOCK = threading.Lock()

RESULT_COLUMNS = ["scene", "method", "psnr", "ssim", "lpips", "avge", "fps", "train_seconds", "plateau_seconds",
                  "gaussians", "anchors", "peak_memory_mib", "iterations", "preset"]
#: A curve has reached its plateau once its PSNR stays no more than this below the final value.
PLATEAU_TOL_DB = 0.5

# Method name -> extra `dibrgs train` flags.
METHODS: dict[str, list[str]] = {
    "dibrgs": [],
    "3dgs": ["--method", "3dgs"],
    "no-pseudo": ["--no-pseudo"],
    "no-dense-init": ["--no-dense-init"],
    "ibr-none": ["--ibr", "none"],
    "no-height": ["--no-height"],
    "oracle-depth": ["--depth-prior", "gt"],
}
ABLATIONS = ["no-dense-init", "ibr-none", "no-height", "no-pseudo", "oracle-depth"]
# Labels as in the paper's ablation table.
ABLATION_LABELS = {"no-dense-init": "w/o Dense Init.", "ibr-none": "w/o IBR Feature",
                   "no-height": "w/o Height Map", "no-pseudo": "w/o Pseudo Views",
                   "oracle-depth": "Oracle depth prior (gt)", "dibrgs": "Ours (DIBR-GS)"}


@dataclass(frozen=True)
class RunSpec:
    """One training + evaluation job."""

    kind: str  # scene generator kind
    resolution: int
    method: str
    seed: int = 0
    preset: str = "cpu"
    iterations: int | None = None
    orbit: str = DEFAULT_ORBIT  # a synth.flights.ORBITS key

    @property
    def scene(self) -> str:
        return f"{self.kind}{self.resolution}" + ("" if self.orbit == DEFAULT_ORBIT else f"-{self.orbit}")

    @property
    def key(self) -> str:
        return f"{self.scene}__{self.method}"


@dataclass
class Suite:
    name: str
    runs: list[RunSpec] = field(default_factory=list)


def make_suite(name: str, preset: str = "cpu", iterations: int | None = None) -> Suite:
    """``quick``: one 128x128 city, 3dgs / DIBR-GS / DIBR-GS without pseudo views.
    ``full``: four 256x256 scenes with 3dgs and DIBR-GS, plus the ablations on the city.
    ``tiny``: a 64x64 city with two short runs, for tests of the machinery."""
    if name == "quick":
        runs = [RunSpec("city", 128, m, preset=preset, iterations=iterations)
                for m in ("3dgs", "dibrgs", "no-pseudo")]
    elif name == "full":
        runs = []
        for kind in ("city", "mountain", "village", "stadium"):
            runs += [RunSpec(kind, 256, m, preset=preset, iterations=iterations) for m in ("3dgs", "dibrgs")]
        runs += [RunSpec("city", 256, m, preset=preset, iterations=iterations) for m in ABLATIONS]
    elif name == "tiny":
        runs = [RunSpec("city", 64, m, preset=preset, iterations=iterations) for m in ("dibrgs", "no-pseudo")]
    else:
        raise ValueError(f"unknown suite {name!r} (quick, full, tiny)")
    return Suite(name, runs)


def _child(cmd: list[str], log_path: Path, what: str) -> None:
    """Run ``cmd`` in a child process, appending its output to ``log_path``; raise naming ``what``."""
    with open(log_path, "a") as f:
        f.write(f"$ {' '.join(cmd)}\n")
        f.flush()
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed with exit code {proc.returncode}; see {log_path}")


def _dibrgs(argv: list[str], log_path: Path) -> None:
    """Run a ``dibrgs`` command in a child process (so peak memory is its own)."""
    _child([sys.executable, "-m", "dibrgs_core", *argv], log_path, f"`dibrgs {argv[0]}`")


def scene_path(spec: RunSpec, work_root: str | Path) -> Path:
    """Where the generated scene of ``spec`` lives under ``work_root``."""
    return Path(work_root) / "scenes" / f"{spec.kind}{spec.resolution}_{spec.orbit}_s{spec.seed}"


def ensure_scene(spec: RunSpec, scene_dir: Path) -> Path:
    """Render ``spec``'s scene into ``scene_dir`` unless it is there (safe from several threads)."""
    with _SCENE_LOCK:  # one render at a time per process; another process may race us (rename below)
        if not (scene_dir / "Cams").is_dir():
            # Rendered in a child process: bpy crashes when driven from more than one thread of a
            # process, and local jobs are threads.
            tmp = scene_dir.with_name(scene_dir.name + f".tmp{os.getpid()}")
            code = ("import sys; from dibrgs_core.synth.writer import make_scene; "
                    "make_scene(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], orbit=sys.argv[5])")
            scene_dir.parent.mkdir(parents=True, exist_ok=True)
            _child([sys.executable, "-c", code, spec.kind, str(spec.resolution), str(spec.seed), str(tmp), spec.orbit],
                   scene_dir.parent / f"{scene_dir.name}.log", f"rendering scene {scene_dir.name}")
            try:
                os.replace(tmp, scene_dir)
            except OSError:
                import shutil

                shutil.rmtree(tmp, ignore_errors=True)
    return scene_dir


def run_one(spec: RunSpec, work_root: str | Path, lpips: str | None = None, threads: int | None = None
            ) -> dict[str, Any]:
    """Generate the scene if needed, train (resuming), evaluate; return the result row and curve.

    ``threads``: torch threads of the child commands (None: their default, every available core).

    Runs on whichever machine executes it (locally or a Ray worker): the
    scene is regenerated from its seed there if absent, so workers need no
    shared file system.
    """
    work_root = Path(work_root)
    scene_dir = scene_path(spec, work_root)
    work = work_root / "runs" / spec.key
    work.mkdir(parents=True, exist_ok=True)
    logf = work / "benchmark.log"
    ensure_scene(spec, scene_dir)
    train = ["train", str(scene_dir), "--out", str(work), "--preset", spec.preset, "--resume",
             *METHODS[spec.method]]
    if spec.iterations:
        train += ["--iterations", str(spec.iterations)]
    if threads:
        train += ["--threads", str(threads)]
    _dibrgs(train, logf)
    ev = ["eval", str(work)] + (["--threads", str(threads)] if threads else [])
    if lpips:
        ev += ["--lpips", lpips]
    _dibrgs(ev, logf)
    return {"spec": asdict(spec), **folder_result(work, spec.scene, spec.method, spec.preset),
            "host": platform.node()}


def folder_result(work: Path, scene: str, method: str, preset: str) -> dict[str, Any]:
    """The result row and curve of a trained run folder ``work`` (``dibrgs train --out``).

    The row's metrics come from ``metrics.json`` (``dibrgs eval``); a folder that was not evaluated
    takes PSNR and SSIM from its curve's last point (the mean over every held-out view, as the
    training curve scores them) and leaves the rest undefined (None)."""
    curve = read_curve(work / "curve.csv")
    mpath = work / "metrics.json"
    metrics = json.loads(mpath.read_text()) if mpath.exists() else (
        {"psnr": curve[-1]["psnr"], "ssim": curve[-1]["ssim"]} if curve else {})
    final_on_point_views = _final_on_point_views(work)
    row = {"scene": scene, "method": method, "psnr": metrics.get("psnr"),
           "ssim": metrics.get("ssim"), "lpips": metrics.get("lpips"), "avge": metrics.get("avge"),
           "fps": metrics.get("fps"), "train_seconds": metrics.get("train_seconds",
                                                                     curve[-1]["seconds"] if curve else None),
           "plateau_seconds": plateau_seconds(curve, final_on_point_views),
           "gaussians": metrics.get("gaussians"), "anchors": metrics.get("anchors"),
           "peak_memory_mib": metrics.get("peak_memory_mib"), "iterations": metrics.get("iterations"),
           "preset": preset}
    return {"row": row, "curve": curve, "final_psnr_on_point_views": final_on_point_views}


def read_curve(path: Path) -> list[dict[str, float]]:
    """Read a training run's curve.csv into [{'seconds', 'iteration', 'psnr', 'ssim'}]."""
    if not path.exists():
        return []
    out = []
    with open(path) as f:
        for r in csv.DictReader(f):
            sec = r.get("seconds", r.get("elapsed_s", r.get("train_seconds")))
            out.append({"seconds": float(sec), "iteration": int(float(r.get("iteration", 0))),
                        "psnr": float(r["psnr"]), "ssim": float(r["ssim"])})
    return out


def _final_on_point_views(work: Path) -> float | None:
    """The final model's PSNR on the held-out views the earlier curve points evaluated (report.json;
    None when those points evaluated every view)."""
    try:
        rep = json.loads((work / "report.json").read_text())
    except (OSError, ValueError):
        return None
    return rep.get("values", {}).get("curve", {}).get("final_psnr_on_point_views")


def plateau_seconds(curve: list[dict[str, float]], final_psnr: float | None = None,
                    tol_db: float = PLATEAU_TOL_DB) -> float | None:
    """Training seconds from which a curve's PSNR stays within ``tol_db`` below its final value
    (or above it) to the end: when the run's quality had levelled off. ``final_psnr`` is the final
    model's PSNR on the views the earlier points evaluated, when they evaluated a subset (the last
    point evaluates every view); None: the last point's. None for an empty curve."""
    if not curve:
        return None
    final = curve[-1]["psnr"] if final_psnr is None else final_psnr
    values = [p["psnr"] for p in curve[:-1]] + [final]
    at = curve[-1]["seconds"]
    for p, v in zip(reversed(curve), reversed(values)):
        if v < final - tol_db:
            break
        at = p["seconds"]
    return at


# ---------------------------------------------------------------------------
# Dispatch
# ---------------------------------------------------------------------------
def result_path(results: Path, spec: RunSpec) -> Path:
    """Where a finished run's result (JSON) is kept under a results folder."""
    return results / "runs" / f"{spec.key}.json"


def pending(suite: Suite, results: Path) -> list[RunSpec]:
    return [s for s in suite.runs if not result_path(results, s).exists()]


def run_local(specs: Iterable[RunSpec], work_root: Path, results: Path, lpips: str | None = None,
              progress: Callable[[str], None] = print, jobs: int = 1,
              job: Callable[..., dict[str, Any]] = run_one) -> None:
    """Run the jobs on this machine, ``jobs`` at a time (each is a child process with its own
    torch threads: the available cores are shared out between them). Results are saved as
    each run finishes; a failed run is reported after the others have finished. ``job`` is
    the function each run calls (``run_one``; tests pass a variant)."""
    from concurrent.futures import ThreadPoolExecutor, as_completed

    specs = list(specs)
    threads = max(1, len(os.sched_getaffinity(0)) // max(1, jobs))

    def one(spec: RunSpec) -> tuple[RunSpec, dict[str, Any], float]:
        progress(f"start {spec.key}")
        t0 = time.perf_counter()
        res = job(spec, work_root, lpips, threads=threads)
        write_json(result_path(results, spec), res)
        return spec, res, time.perf_counter() - t0

    errors = []
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        futures = [pool.submit(one, s) for s in specs]
        for i, fut in enumerate(as_completed(futures), 1):
            try:
                spec, res, sec = fut.result()
            except Exception as e:  # keep the other runs going; report at the end
                errors.append(e)
                progress(f"[{i}/{len(specs)}] failed: {e}")
                continue
            progress(f"[{i}/{len(specs)}] {spec.key}: PSNR {res['row']['psnr']:.2f} dB ({sec:.0f} s)")
    if errors:
        raise RuntimeError(f"{len(errors)} of {len(specs)} runs failed; first: {errors[0]}")


def run_ray(specs: Iterable[RunSpec], work_root: Path, results: Path, address: str, lpips: str | None = None,
            num_cpus: float = 2, num_gpus: float = 0, max_retries: int = 3,
            progress: Callable[[str], None] = print,
            job: Callable[..., dict[str, Any]] = run_one) -> None:
    """Submit every run as a Ray task to the cluster at ``address`` (``auto``, ``ray://host:port``,
    or ``local`` to start a private instance). A task whose worker dies is retried by Ray
    (``max_retries``); finished runs are saved as they arrive, so a killed driver resumes.
    ``job`` is the function each task runs (``run_one``; tests pass a variant)."""
    import ray

    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=max(1, os.cpu_count() or 1), include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    task = ray.remote(num_cpus=num_cpus, num_gpus=num_gpus, max_retries=max_retries,
                      retry_exceptions=False)(job)
    specs = list(specs)
    refs = {task.remote(s, str(work_root), lpips, threads=max(1, int(num_cpus))): s for s in specs}
    done = 0
    while refs:
        ready, _ = ray.wait(list(refs), num_returns=1)
        spec = refs.pop(ready[0])
        res = ray.get(ready[0])
        write_json(result_path(results, spec), res)
        done += 1
        progress(f"[{done}/{len(specs)}] {spec.key} on {res['host']}: PSNR {res['row']['psnr']:.2f} dB")




