#!/usr/bin/env python
"""The full suite's main runs (3DGS and DIBR-GS on its four scenes), one at a time with one torch
thread, with whichever ``dibrgs_core`` is first on ``sys.path``: the "before and after" of
docs/benchmarks.md ("Error against time before and after issue 17").

    PYTHONPATH=CHECKOUT python scripts/plateau_driver.py WORK [METHOD]

METHOD (``3dgs`` or ``dibrgs``) runs only that method's four runs, so that two drivers can share
the machine as the before-and-after runs did (generate the scenes first, or copy them into
``WORK/scenes``, so that the two do not both write them).

Results go where the benchmark runner puts them (``WORK/results/runs/*.json``, finished runs
skipped), each with its whole run's wall time (``wall_seconds``);
``scripts/compare_benchmarks.py BEFORE AFTER`` compares two such folders.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import dibrgs_core
from dibrgs_core.bench import runner


def timed_run(spec: runner.RunSpec, work: Path, lpips: str | None, threads: int) -> dict:
    """``runner.run_one`` with one torch thread whatever the machine has, plus its wall time."""
    t0 = time.time()
    res = runner.run_one(spec, work, lpips, threads=1)
    res["wall_seconds"] = time.time() - t0
    return res


def main(argv: list[str]) -> int:
    methods = ("3dgs", "dibrgs")
    if len(argv) not in (1, 2) or (len(argv) == 2 and argv[1] not in methods):
        print(__doc__, file=sys.stderr)
        return 2
    work = Path(argv[0])
    if len(argv) == 2:
        methods = (argv[1],)
    print("package", dibrgs_core.__file__, flush=True)
    results = work / "results"
    specs = [s for s in runner.pending(runner.make_suite("full"), results) if s.method in methods]
    runner.run_local(specs, work, results, job=timed_run)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
