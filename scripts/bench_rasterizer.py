"""Benchmark the rasterizer on the test_garden scene (138,766 Gaussians).

Renders camera 0 of ``shared/data/test_garden.npz`` at square sizes with both
paths, forward and forward+backward, on 1 and 2 threads. Each configuration
runs in its own subprocess so that its peak memory (``ru_maxrss``, whole
process: python + torch + the scene) is its own. Quaternions, scales (from the
mean distance to the 3 nearest neighbours, times a log-normal factor) and
opacities are drawn with a fixed seed. Each call is timed after one warm-up
call (which also compiles the C++ path on first use); the table gives the
minimum and the median wall time and the minimum process CPU time (all
threads) over the repeats: on a shared machine the minimum is the least
disturbed figure, and CPU time does not count the time other jobs held the
cores. Speed-ups are ratios of minima. Workers wait passively at OpenMP
barriers (``OMP_WAIT_POLICY=PASSIVE`` unless set): spinning threads slow a
contended machine down several times.

The kernel section (``--kernels``, on by default) times the C++ stages one by
one on 1 thread at the largest size (minimum CPU time of ``--repeats`` calls):
projection, binning, compositing forward and backward (the extension's
``forward`` and ``backward``: records, tiles, gradient reduction), counts the
(Gaussian, pixel) pairs the kernels evaluate, and compares the arithmetic they
do with this core's FMA peak, measured by a small C program compiled here
(``cc -O2 -march=native``, independent FMA chains) before and after the stages;
the higher reading is the peak, as a probe that fell in a slow spell of a shared
host would flatter the kernels. The FLOPs per evaluated
pair (one lane of a vector) are counted from ``csrc/composite.h``: add, sub,
mul, div = 1, FMA = 2; compares, min/max, blends and bit operations are not
counted.

    python scripts/bench_rasterizer.py                 # 256 and 512, 1 and 2 threads
    python scripts/bench_rasterizer.py --sizes 512 --threads 1 --repeats 5
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # benchmark this checkout's package, not an installed one
from dibrgs_core.bench.machine import cpu  # noqa: E402


def flops_per_lane(C: int, simd: str) -> tuple[int, int]:
    """Arithmetic per evaluated (Gaussian, pixel) lane of the compositing kernels with C channels
    on the vector code path ``simd`` (the extension's ``simd()`` name).

    Forward: first pass 20 (dx 1, power 2 FMA = 4, exp2 15: round by adding and subtracting
    1.5 2^23 and f = t - n = 3, 6 FMA; with AVX-512 14: f = t - floor(t) by vreduceps 1, 6 FMA,
    scalef 1), second pass 2 + 2C (alpha T 1, T - alpha T 1, C FMA).
    Backward: first pass as the forward's, second 17 + 5C (T / (1 - alpha): 2, weight 1, per
    channel 1 + 2 FMA, dL/dalpha 1, dL/dpower 1, moments 1 + 1 + 1 + 1 + 1 + 1 + 3 FMA), third
    pass 2C.
    """
    first = 19 if simd.startswith("avx512 ") else 20
    return first + 2 + 2 * C, first + 17 + 7 * C


FMA_PEAK_C = r"""
#include <immintrin.h>
#include <stdio.h>
#include <time.h>
static double now(void) { struct timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t); return t.tv_sec + 1e-9 * t.tv_nsec; }
#if defined(__AVX512F__)
typedef __m512 V; enum { L = 16 };
#define SET(x) _mm512_set1_ps(x)
#define FMA(a, b, c) _mm512_fmadd_ps(a, b, c)
#elif defined(__FMA__)
typedef __m256 V; enum { L = 8 };
#define SET(x) _mm256_set1_ps(x)
#define FMA(a, b, c) _mm256_fmadd_ps(a, b, c)
#else
#error "no FMA"
#endif
int main(void) {
  V a0 = SET(1.0f), a1 = SET(1.1f), a2 = SET(1.2f), a3 = SET(1.3f), a4 = SET(1.4f);
  V a5 = SET(1.5f), a6 = SET(1.6f), a7 = SET(1.7f), a8 = SET(1.8f), a9 = SET(1.9f);
  const V m = SET(0.999999f), c = SET(1e-7f);
  const long n = 20000000;
  double best = 1e30;
  for (int rep = 0; rep < 7; ++rep) {
    double t0 = now();
    for (long i = 0; i < n; ++i) {
      a0 = FMA(a0, m, c); a1 = FMA(a1, m, c); a2 = FMA(a2, m, c); a3 = FMA(a3, m, c); a4 = FMA(a4, m, c);
      a5 = FMA(a5, m, c); a6 = FMA(a6, m, c); a7 = FMA(a7, m, c); a8 = FMA(a8, m, c); a9 = FMA(a9, m, c);
      __asm__ volatile("" : "+x"(a0), "+x"(a1), "+x"(a2), "+x"(a3), "+x"(a4));
    }
    double t = now() - t0;
    if (t < best) best = t;
  }
  float s[L];
  V sum = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7 + a8 + a9;
  __builtin_memcpy(s, &sum, sizeof s);
  printf("%.3f %d %g\n", n * 10.0 * L * 2.0 / best / 1e9, L, s[0]);
  return 0;
}
"""


def target_flags() -> list[str]:
    """The extension build's target options (``-march=...``, ``-m...``), so that the FMA peak
    is measured at the vector width the kernels were built for (an AVX2 build on an
    AVX-512 machine is compared with the 8-lane peak; a build without them, for the
    baseline target, has no FMA and no peak)."""
    from dibrgs_core.render import fast

    return [f for f in fast.build_flags() if f.startswith("-m")]


def fma_peak() -> tuple[float, int] | None:
    """(GFLOP/s, float lanes) of one core's FMA units at the build's vector width, or None
    without a compiler/FMA."""
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        src, exe = Path(tmp) / "fma.c", Path(tmp) / "fma"
        src.write_text(FMA_PEAK_C)
        if subprocess.run([cc, "-O2", *target_flags(), str(src), "-o", str(exe)], capture_output=True,
                          check=False).returncode != 0:
            return None
        out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    return float(out[0]), int(out[1])


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


def _timed(fn, repeats: int) -> tuple[list[float], list[float]]:
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


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
    if backend == "fast":
        from dibrgs_core.render import fast

        out["simd"] = fast.extension().simd()
    for name, fn in (("fwd", fwd), ("fwd_bwd", fwd_bwd)):
        wall, cpu = _timed(fn, repeats)
        out[f"{name}_s"] = min(wall)
        out[f"{name}_med_s"] = statistics.median(wall)
        out[f"{name}_cpu_s"] = min(cpu)
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def composite_inputs(proj, cols):
    """The compositing kernels' inputs from a projection of the garden: screen-space means, conics and
    depths (detached, contiguous), the features (colour, depth, alpha) and their channel groups, the
    planes rasterize() asks for."""
    import torch

    feats = torch.cat([cols, proj.depths[:, None].detach(), torch.ones(len(cols), 1)], 1).contiguous()
    C = feats.shape[1]
    return (proj.means2d.detach().contiguous(), proj.conics.detach().contiguous(), proj.depths.detach(), feats,
            [C - 2, 1, 1])


def kernel_worker(size: int, repeats: int) -> dict:
    """Stage CPU times (1 thread, minimum over repeats) and pair counts of the C++ path."""
    import torch

    torch.set_num_threads(1)
    from dibrgs_core.render import fast

    means, quats, scales, opac, cols, vm, K = garden(size)
    mod = fast.extension()
    ps = [p.clone().requires_grad_() for p in (means, quats, scales)]
    res: dict = {"size": size, "simd": mod.simd()}
    times: dict[str, float] = {}

    def stage(name, fn):
        out = fn()
        times[name] = min(_timed(fn, repeats)[1])
        return out

    proj = stage("project_fwd", lambda: fast.project_fast(*ps, vm, K, size, size))
    m2, con, dep, feats, groups = composite_inputs(proj, cols)
    offsets, gids, masks = stage("bin", lambda: mod.bin_tiles(m2, con, opac, dep, proj.radii, size, size))
    *_, tfin, ncon, rec = stage("composite_fwd", lambda: mod.forward(m2, con, opac, feats, offsets, gids, masks, size,
                                                                     size, groups))
    gen = torch.Generator().manual_seed(1)
    gouts = [torch.rand(size, size, n, generator=gen) for n in groups]
    stage("composite_bwd", lambda: mod.backward(rec, offsets, gids, masks, gouts, groups, tfin, ncon, size, size))
    g = [torch.randn_like(t) for t in (proj.means2d, proj.conics, proj.depths)]

    def proj_bwd():
        p2 = fast.project_fast(*ps, vm, K, size, size)
        torch.autograd.backward([p2.means2d, p2.conics, p2.depths], g)

    proj_bwd()
    times["project_fwd_bwd"] = min(_timed(proj_bwd, repeats)[1])
    stats = mod.composite_stats(rec, offsets, gids, masks, torch.cat(gouts, -1), size, size).tolist()
    res.update(times=times, channels=int(feats.shape[1]), entries=int(offsets[-1]))
    for row, name in zip(stats, ("fwd", "bwd")):
        res[name] = dict(zip(("vectors", "lanes", "contrib", "gaussians", "entries"), row))
    return res


def run_child(args: list[str], threads: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    res = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, env=env, cwd=REPO,
                         check=False)
    if res.returncode != 0:
        sys.stderr.write(res.stderr)
        raise SystemExit(1)
    return json.loads(res.stdout.strip().splitlines()[-1])


def report_kernels(k: dict, probes: list[tuple[float, int]]) -> None:
    """Prints the kernel worker's stage times and FLOP rates against the FMA peak: the highest of
    ``probes`` (the probe run before and after the worker; on a shared host either may fall in a
    slow spell, which would flatter the kernels)."""
    t = k["times"]
    peak = max(probes) if probes else None
    print(f"\nC++ stages at {k['size']}x{k['size']}, 1 thread, min CPU time of the calls ({k['simd']}):")
    for name in ("project_fwd", "bin", "composite_fwd", "composite_bwd", "project_fwd_bwd"):
        print(f"  {name:<16} {t[name] * 1e3:8.1f} ms")
    ffl, bfl = flops_per_lane(k["channels"], k["simd"])
    lanes = int(re.search(r" x(\d+)$", k["simd"]).group(1))
    for name, fl, tt in (("fwd", ffl, t["composite_fwd"]), ("bwd", bfl, t["composite_bwd"])):
        s = k[name]
        ev = s["vectors"] * lanes
        line = (f"  compositing {name}: {s['vectors']:,} vectors = {ev:,} lanes evaluated ({s['lanes']:,} inside the "
                f"image), {s['contrib']:,} pairs composite ({s['contrib'] / ev:.0%} of lanes), {s['gaussians']:,} "
                f"of {s['entries']:,} list entries reach a vector; {fl} FLOP/lane -> {ev * fl / tt / 1e9:.1f} GFLOP/s")
        if peak:
            line += f" = 1/{peak[0] / (ev * fl / tt / 1e9):.1f} of the FMA peak"
        print(line)
    if peak:
        print(f"  FMA peak of one core: {peak[0]:.1f} GFLOP/s ({peak[1]} float lanes, 2 FLOP per FMA; the higher of "
              f"the probes before and after the stages: {' / '.join(f'{p[0]:.1f}' for p in probes)})")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--backends", nargs="+", default=["fast", "reference"])
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per configuration (fast path)")
    ap.add_argument("--ref-repeats", type=int, default=1, help="timed calls per configuration (reference path)")
    ap.add_argument("--kernels", action=argparse.BooleanOptionalAction, default=True,
                    help="C++ stage times, pair counts and FLOP rate against the FMA peak")
    ap.add_argument("--worker", nargs=4, metavar=("BACKEND", "SIZE", "THREADS", "REPEATS"), help=argparse.SUPPRESS)
    ap.add_argument("--kernel-worker", nargs=2, metavar=("SIZE", "REPEATS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        b, s, t, r = args.worker
        print(json.dumps(worker(b, int(s), int(t), int(r))))
        return 0
    if args.kernel_worker:
        print(json.dumps(kernel_worker(*map(int, args.kernel_worker))))
        return 0

    m = cpu()
    print(f"machine: {m['model']}, {m['cores']} cores, vector extensions: {m['vector']}")
    print(f"load average before: {m['load'][0]:.2f} {m['load'][1]:.2f} {m['load'][2]:.2f}")
    rows = []
    print(f"{'backend':>9} {'size':>5} {'thr':>3} {'fwd s':>8} {'(median)':>8} {'f+b s':>8} {'(median)':>8} "
          f"{'fwd cpu':>8} {'f+b cpu':>8} {'peak MiB':>9}", flush=True)
    for size in args.sizes:
        for threads in args.threads:
            for backend in args.backends:
                reps = args.repeats if backend == "fast" else args.ref_repeats
                r = run_child(["--worker", backend, str(size), str(threads), str(reps)], threads)
                rows.append(r)
                print(f"{backend:>9} {size:>5} {threads:>3} {r['fwd_s']:>8.3f} {r['fwd_med_s']:>8.3f} "
                      f"{r['fwd_bwd_s']:>8.3f} {r['fwd_bwd_med_s']:>8.3f} {r['fwd_cpu_s']:>8.3f} "
                      f"{r['fwd_bwd_cpu_s']:>8.3f} {r['peak_rss_mib']:>9.0f}", flush=True)
    by = {(r["backend"], r["size"], r["threads"]): r for r in rows}
    for size in args.sizes:
        for threads in args.threads:
            f, ref = by.get(("fast", size, threads)), by.get(("reference", size, threads))
            if f and ref:
                print(f"speed-up fast ({f['simd']}) vs reference at {size}x{size}, {threads} thread(s), min wall: "
                      f"forward {ref['fwd_s'] / f['fwd_s']:.1f}x, forward+backward "
                      f"{ref['fwd_bwd_s'] / f['fwd_bwd_s']:.1f}x; min CPU: forward "
                      f"{ref['fwd_cpu_s'] / f['fwd_cpu_s']:.1f}x, forward+backward "
                      f"{ref['fwd_bwd_cpu_s'] / f['fwd_bwd_cpu_s']:.1f}x")
    if args.kernels and "fast" in args.backends:
        before = fma_peak()
        k = run_child(["--kernel-worker", str(max(args.sizes)), str(max(args.repeats, 3))], 1)
        report_kernels(k, [p for p in (before, fma_peak()) if p is not None])
    load = os.getloadavg()
    print(f"load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
