"""Benchmark the rasterizer on the test_garden scene (138,766 Gaussians).

Renders camera 0 of ``shared/data/test_garden.npz`` at square sizes with both
paths, forward and forward+backward, on 1 and 2 threads. Each configuration
runs in its own subprocess so that its peak memory (``ru_maxrss``, whole
process: python + torch + the scene) is its own. Quaternions, scales (from the
mean distance to the 3 nearest neighbours, times a log-normal factor) and
opacities are drawn with a fixed seed. Times are medians over repeats, after
one warm-up call (which also compiles the C++ path on first use); the process
CPU time of the same calls (all threads) is printed too, since wall times on a
shared machine depend on the other jobs. Workers wait passively at OpenMP
barriers (``OMP_WAIT_POLICY=PASSIVE`` unless set): spinning threads slow a
contended machine down several times.

    python scripts/bench_rasterizer.py                 # 256 and 512, 1 and 2 threads
    python scripts/bench_rasterizer.py --sizes 512 --threads 2 --repeats 5
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # benchmark this checkout's package, not an installed one


def garden(size: int):
    """(means, quats, scales, opacities, colours, viewmat, K) at size x size."""
    import numpy as np
    import torch
    from scipy.spatial import cKDTree

    path = Path(os.environ.get("DIBRGS_SHARED", REPO.parent / "shared")) / "data" / "test_garden.npz"
    d = np.load(path)
    pts = d["means3d"].astype(np.float64)
    n = len(pts)
    g = torch.Generator().manual_seed(0)
    dist, _ = cKDTree(pts).query(pts, k=4)
    s = torch.tensor(dist[:, 1:].mean(1), dtype=torch.float32).clamp(min=1e-4)
    scales = s[:, None] * torch.exp(0.3 * torch.randn(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    opac = 0.05 + 0.9 * torch.rand(n, generator=g)
    cols = torch.tensor(d["colors"], dtype=torch.float32) / 255.0
    K = torch.tensor(d["Ks"][0], dtype=torch.float32).clone()
    K[0] *= size / float(d["width"])
    K[1] *= size / float(d["height"])
    vm = torch.tensor(d["viewmats"][0], dtype=torch.float32)
    return torch.tensor(pts, dtype=torch.float32), quats, scales, opac, cols, vm, K


def worker(backend: str, size: int, threads: int, repeats: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    from dibrgs_core.render import rasterize

    means, quats, scales, opac, cols, vm, K = garden(size)
    params = [means, quats, scales, opac, cols]

    def fwd():
        with torch.no_grad():
            rasterize(*params, vm, K, size, size, backend=backend)

    def fwd_bwd():
        ps = [p.clone().requires_grad_() for p in params]
        img, alpha, depth, meta = rasterize(*ps, vm, K, size, size, backend=backend)
        (img.sum() + alpha.sum() + depth.mean()).backward()
        return meta

    meta = fwd_bwd()  # warm-up (and compile)
    out = {"backend": backend, "size": size, "threads": threads, "visible": int(meta["visible"].sum())}
    for name, fn in (("fwd", fwd), ("fwd_bwd", fwd_bwd)):
        times, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        out[f"{name}_s"] = statistics.median(times)
        out[f"{name}_cpu_s"] = statistics.median(cpu)
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--backends", nargs="+", default=["fast", "reference"])
    ap.add_argument("--repeats", type=int, default=3, help="timed calls per configuration (reference: 1)")
    ap.add_argument("--worker", nargs=4, metavar=("BACKEND", "SIZE", "THREADS", "REPEATS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        b, s, t, r = args.worker
        print(json.dumps(worker(b, int(s), int(t), int(r))))
        return 0

    rows = []
    print(f"{'backend':>9} {'size':>5} {'thr':>3} {'fwd s':>8} {'fwd+bwd s':>10} {'fwd cpu s':>10} "
          f"{'f+b cpu s':>10} {'peak MiB':>9}", flush=True)
    for size in args.sizes:
        for threads in args.threads:
            for backend in args.backends:
                reps = args.repeats if backend == "fast" else 1
                env = dict(os.environ, OMP_NUM_THREADS=str(threads))
                env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
                res = subprocess.run(
                    [sys.executable, __file__, "--worker", backend, str(size), str(threads), str(reps)],
                    capture_output=True, text=True, env=env, cwd=REPO,
                )
                if res.returncode != 0:
                    print(res.stderr, file=sys.stderr)
                    return 1
                r = json.loads(res.stdout.strip().splitlines()[-1])
                rows.append(r)
                print(f"{backend:>9} {size:>5} {threads:>3} {r['fwd_s']:>8.3f} {r['fwd_bwd_s']:>10.3f} "
                      f"{r['fwd_cpu_s']:>10.3f} {r['fwd_bwd_cpu_s']:>10.3f} {r['peak_rss_mib']:>9.0f}", flush=True)
    by = {(r["backend"], r["size"], r["threads"]): r for r in rows}
    for size in args.sizes:
        for threads in args.threads:
            f, ref = by.get(("fast", size, threads)), by.get(("reference", size, threads))
            if f and ref:
                print(f"speed-up fast vs reference at {size}x{size}, {threads} thread(s): "
                      f"forward {ref['fwd_s'] / f['fwd_s']:.1f}x, forward+backward {ref['fwd_bwd_s'] / f['fwd_bwd_s']:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
