"""Options several commands share, validated when the command line is parsed.

* ``--threads``: torch CPU threads, by default every core this process may run on
  (``os.sched_getaffinity``: a container's or ``taskset``'s limit, not the machine's count); how
  the threads wait between operators is chosen at start (:mod:`dibrgs_core.common.openmp`);
  numpy's and scipy's BLAS run on one thread (:mod:`dibrgs_core.common.blas`);
* ``--rasterizer``: the compiled C++ rasterizer (``auto``, the default) or the torch reference
  path (``reference``: no compiler needed, about 100x slower);
* ``--train`` / ``--test``: the split (comma-separated view names or LEVIR ids), overriding
  ``split.json`` and the default (:func:`dibrgs_core.data.split.make_split`);
* argparse types that refuse impossible numbers at parse time with one line naming the option.

Commands that write into a folder hold its lock (:func:`locked`) for their whole run.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
from pathlib import Path
from typing import Any, Callable, Iterator

from ..common.allocator import allocator_policy
from ..common.blas import single_thread_blas
from ..common.limits import MAX_RESOLUTION_SCALE, MIN_RESOLUTION
from ..common.openmp import wait_policy

#: The scene layouts the readers take (``data.load.read_any_scene``), as the commands' help names them.
SCENE_LAYOUTS = ("LEVIR-NVS, COLMAP, transforms.json, Metashape XML, OpenDroneMap / OpenSfM, Meshroom "
                 "cameras.sfm, OpenMVG sfm_data.json, Bundler .out or RealityCapture XMP")

log = logging.getLogger("dibrgs")


def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def add_compute(p: argparse.ArgumentParser) -> None:
    """``--threads`` and ``--rasterizer``."""
    p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help=f"torch CPU threads (default: the cores available to this process, {available_cores()} here)")
    p.add_argument("--rasterizer", choices=["auto", "fast", "reference"], default=None,
                   help="auto/fast: the compiled C++ rasterizer (built on first use; a failed build is an error "
                        "saying why); reference: the torch path, no compiler needed, about 100x slower "
                        "(default: $DIBRGS_RASTERIZER, else auto)")


def apply_compute(args: argparse.Namespace) -> int:
    """Set torch's thread count from ``--threads`` (default: the available cores) and the rasterizer
    backend from ``--rasterizer``; returns the thread count."""
    import torch

    from ..render import set_backend

    n = args.threads or available_cores()
    torch.set_num_threads(n)
    blas = single_thread_blas()
    if n > 1:
        log.info("%d torch threads; OpenMP workers wait: %s; numpy's BLAS: %s; memory: %s", n, wait_policy(), blas,
                 allocator_policy())
    else:
        log.info("1 torch thread; numpy's BLAS: %s; memory: %s", blas, allocator_policy())
    if getattr(args, "rasterizer", None) is not None:
        set_backend(args.rasterizer)
    return n


def add_split(p: argparse.ArgumentParser) -> None:
    p.add_argument("--train", type=name_list, default=None, metavar="NAMES",
                   help="training views, comma-separated names (with or without extension) or LEVIR ids, or "
                        "'all' (every view but those of --test; nothing held out without --test); overrides "
                        "the scene's split.json (default without either: 001,008,015 for LEVIR-NVS scenes, "
                        "else 3 evenly spaced views)")
    p.add_argument("--test", type=name_list, default=None, metavar="NAMES",
                   help="held-out views, as --train, or 'none' (nothing held out) (default: split.json's, else "
                        "the views not trained on)")


@contextlib.contextmanager
def locked(folder: Path, command: str) -> Iterator[None]:
    """Hold ``folder``'s run-folder lock (:mod:`dibrgs_core.common.lock`) while the command writes into it."""
    from ..common.lock import run_folder_lock

    with run_folder_lock(folder, command):
        yield


# -- argparse types: ValueError / ArgumentTypeError messages become "argument --x: ..." -----------
def name_list(s: str) -> list[str]:
    names = [x.strip() for x in s.split(",") if x.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected comma-separated view names, got {s!r}")
    return names


def _number(kind: Callable, s: str):
    try:
        v = kind(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {s!r}") from None
    if isinstance(v, float) and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {s!r}")
    return v


def _checked(kind: Callable, ok: Callable[[Any], bool], must: str, name: str) -> Callable[[str], Any]:
    """An argparse type: ``kind`` parsed by :func:`_number`, refused with "must be ``must``" unless ``ok``."""

    def parse(s: str):
        v = _number(kind, s)
        if not ok(v):
            raise argparse.ArgumentTypeError(f"must be {must}, got {s}")
        return v

    parse.__name__ = name
    return parse


positive_int = _checked(int, lambda v: v >= 1, "a positive integer", "positive_int")
nonnegative_int = _checked(int, lambda v: v >= 0, ">= 0", "nonnegative_int")
seed = _checked(int, lambda v: 0 <= v < 2 ** 32, "in [0, 2^32)", "seed")
resolution = _checked(int, lambda v: v >= MIN_RESOLUTION, f"at least {MIN_RESOLUTION} pixels", "resolution")
resolution_scale = _checked(float, lambda v: 0.0 < v <= MAX_RESOLUTION_SCALE, f"in (0, {MAX_RESOLUTION_SCALE:g}]",
                            "resolution_scale")
nonnegative_float = _checked(float, lambda v: v >= 0, ">= 0", "nonnegative_float")
positive_float = _checked(float, lambda v: v > 0, "> 0", "positive_float")
