#!/usr/bin/env python
"""Benchmark DIBR-GS against 3DGS and its ablations: error against run time.

    python scripts/benchmark.py --suite quick            # ~15 min here
    python scripts/benchmark.py --suite full --jobs 2    # hours; run in the background
    python scripts/benchmark.py --suite full --ray auto  # on an existing Ray cluster

Resumable: finished runs are kept in <work>/results/runs/*.json and skipped;
an interrupted training resumes from its checkpoint. Writes
docs/benchmarks/results.csv, docs/benchmarks/curves.png and the suite's
section of docs/benchmarks.md.
"""
from __future__ import annotations

import argparse
import logging
import shlex
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dibrgs_core.bench import pages, runner as bm  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", choices=["quick", "full", "tiny"], required=True)
    p.add_argument("--work", type=Path, default=REPO / "runs" / "benchmark",
                   help="scenes, runs and per-run results (default runs/benchmark)")
    p.add_argument("--docs", type=Path, default=REPO / "docs", help="where the pages go (default docs/)")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--iterations", type=int, default=None, help="override the preset's iterations")
    p.add_argument("--lpips", default=None, help="local LPIPS weights; without them LPIPS/AVGE are n/a")
    p.add_argument("--ray", default=None, metavar="auto|ADDRESS|local",
                   help="dispatch runs as Ray tasks: 'auto' joins the cluster of this machine, "
                        "ray://HOST:10001 a remote one, 'local' starts a private instance")
    p.add_argument("--jobs", type=int, default=1,
                   help="runs at a time without Ray (each trains with 1 torch thread; use <= cores)")
    p.add_argument("--ray-cpus", type=float, default=2, help="CPUs per run on the cluster")
    p.add_argument("--ray-gpus", type=float, default=0, help="GPUs per run on the cluster")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")

    suite = bm.make_suite(args.suite, preset=args.preset, iterations=args.iterations)
    results = args.work / "results"
    todo = bm.pending(suite, results)
    print(f"suite {suite.name}: {len(suite.runs)} runs, {len(suite.runs) - len(todo)} already finished")
    if args.ray:
        bm.run_ray(todo, args.work, results, args.ray, lpips=args.lpips, num_cpus=args.ray_cpus,
                   num_gpus=args.ray_gpus)
    else:
        bm.run_local(todo, args.work, results, lpips=args.lpips, jobs=args.jobs)
    command = "python scripts/benchmark.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    res = pages.write_pages(results, suite, args.docs, command)
    print(f"wrote {args.docs / 'benchmarks' / 'results.csv'}, {args.docs / 'benchmarks' / 'curves.png'} "
          f"and the '{suite.name}' section of {args.docs / 'benchmarks.md'} ({len(res)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
