"""A/B timing of versions of the C++ compositing kernels, side by side in one process.

On a shared host the same build's times move by 1.5x between runs a minute apart, more than the
few per cent a kernel change is worth. Here every version is built as its own extension module
and all are loaded into one process; their calls alternate (A, B, A, B, ...), so each round's
calls of every version see the same host, and the ratio of their round minima cancels the
host's drift. The forward's outputs of every version are compared with the first's. Stages: the
compositing forward or backward (garden, as ``bench_rasterizer.py``), or the training loss
(``loss``: L1 + D-SSIM forward and backward of a 3-channel image, ``render/ssim.py``).

A version is a git revision of this repository (its ``dibrgs_core/render/csrc``) or a folder
holding those sources; ``+FLAGS`` after it replaces the build's flags (default: this machine's,
``render/fast.py``). Builds are cached in ``$DIBRGS_EXT_DIR/ab`` by content and flags.

    python scripts/ab_kernels.py HEAD~1 HEAD                      # forward, garden 512x512
    python scripts/ab_kernels.py --stage backward --rounds 8 HEAD~1 HEAD
    python scripts/ab_kernels.py HEAD "HEAD+-O3 -march=native -fopenmp -fno-math-errno"
"""
from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))
from dibrgs_core.common.openmp import set_wait_policy

set_wait_policy()  # as the dibrgs command does, before torch loads OpenMP: threads wait as in training
CSRC = "dibrgs_core/render/csrc"


def sources(version: str) -> dict[str, bytes]:
    """The extension's source files of a git revision or a folder."""
    from dibrgs_core.render import fast

    folder = Path(version)
    if folder.is_dir():
        return {name: (folder / name).read_bytes() for name in fast._SOURCES}
    out = {}
    for name in fast._SOURCES:
        res = subprocess.run(["git", "show", f"{version}:{CSRC}/{name}"], cwd=REPO, capture_output=True, check=False)
        if res.returncode != 0:
            raise SystemExit(f"ab_kernels: {version!r} is neither a folder nor a git revision with {CSRC}/{name}")
        out[name] = res.stdout
    return out


def build(version: str):
    """The extension module of ``version`` ([REV or FOLDER][+FLAGS]), compiled on first use."""
    from torch.utils.cpp_extension import load

    from dibrgs_core.render import fast

    where, plus, flags_text = version.partition("+")
    flags = flags_text.split() if plus else fast.build_flags()
    src = sources(where)
    h = hashlib.sha256(" ".join(flags).encode())
    for name in sorted(src):
        h.update(name.encode() + b"\0" + src[name])
    name = f"ab_{h.hexdigest()[:16]}"
    root = Path(os.environ.get("DIBRGS_EXT_DIR", Path.home() / ".cache" / "dibrgs" / "ext")) / "ab" / name
    (root / "src").mkdir(parents=True, exist_ok=True)
    for n, data in src.items():
        (root / "src" / n).write_bytes(data)
    print(f"{version}: {name} ({' '.join(flags)})", flush=True)
    return load(name=name, sources=[str(root / "src" / "rasterize.cpp")], extra_cflags=flags,
                extra_ldflags=["-fopenmp"] if "-fopenmp" in flags else [], build_directory=str(root), verbose=False)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("versions", nargs="+", help="git revisions or source folders, each optionally +FLAGS")
    ap.add_argument("--stage", choices=["forward", "backward", "loss"], default="forward")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--calls", type=int, default=15, help="calls of each version a round")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    import torch
    from bench_rasterizer import composite_inputs, garden

    from dibrgs_core.render import fast
    from dibrgs_core.training.losses import _SIGMA, _WINDOW, _gauss_1d

    torch.set_num_threads(args.threads)
    mods = [build(v) for v in args.versions]
    size = args.size
    means, quats, scales, opac, cols, vm, K = garden(size)
    proj = fast.project_fast(means, quats, scales, vm, K, size, size)
    m2, con, dep, feats, groups = composite_inputs(proj, cols)
    offsets, gids, masks = mods[0].bin_tiles(m2, con, opac, dep, proj.radii, size, size)
    C = feats.shape[1]
    outs = [m.forward(m2, con, opac, feats, offsets, gids, masks, size, size, groups) for m in mods]
    for v, o in zip(args.versions, outs):
        d = max(float((a.double() - b.double()).abs().max()) for a, b in zip(o[:-1], outs[0][:-1]))
        print(f"  {v}: forward outputs differ from {args.versions[0]}'s by at most {d:.3g}")
    g = torch.rand(size, size, C, generator=torch.Generator().manual_seed(1))
    gouts = [g[..., :C - 2].contiguous(), g[..., C - 2:C - 1].contiguous(), g[..., C - 1:].contiguous()]

    gen = torch.Generator().manual_seed(2)
    x, y = torch.rand(size, size, 3, generator=gen), torch.rand(size, size, 3, generator=gen)
    win = _gauss_1d(_WINDOW, _SIGMA, torch.float32, torch.device("cpu")).contiguous()  # the training loss's
    wl = ws = torch.full((size, size, 3), 1.0 / (size * size * 3))

    def call(m, o) -> None:
        if args.stage == "loss":
            loss, a, b, c = m.photometric_forward(x, y, win, wl, ws, 0.2)
            m.photometric_backward(torch.ones_like(loss), x, y, a, b, c, win, wl, ws, 0.2)
        elif args.stage == "forward":
            m.forward(m2, con, opac, feats, offsets, gids, masks, size, size, groups)
        else:
            *_, tfin, ncon, rec = o
            m.backward(rec, offsets, gids, masks, gouts, groups, tfin, ncon, size, size)

    # CPU time on one thread (what the host's other tenants disturb least); wall time on more,
    # where CPU time would add the threads' (and their spinning) together.
    clock, what = (time.process_time, "CPU") if args.threads == 1 else (time.perf_counter, "wall")
    mins: list[list[float]] = [[] for _ in mods]
    for r in range(args.rounds):
        times: list[list[float]] = [[] for _ in mods]
        for _ in range(args.calls):
            for i, (m, o) in enumerate(zip(mods, outs)):
                c0 = clock()
                call(m, o)
                times[i].append(clock() - c0)
        for i, t in enumerate(times):
            mins[i].append(min(t))
        print(f"round {r}: " + "  ".join(f"{min(t) * 1e3:.2f}" for t in times) + f" ms (minimum {what} time)", flush=True)
    print(f"\n{args.stage}, {'random images' if args.stage == 'loss' else 'garden'} {size}x{size}, {args.threads} thread(s), {args.rounds} rounds of {args.calls} "
          "alternating calls:")
    for v, mv in zip(args.versions, mins):
        ratios = sorted(a / b for a, b in zip(mv, mins[0]))
        print(f"  {v}: best {min(mv) * 1e3:.2f} ms, against {args.versions[0]} per round: median "
              f"{statistics.median(ratios):.3f} (rounds {ratios[0]:.3f}-{ratios[-1]:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
