"""Where a training iteration's CPU time goes (issue 17), for DIBR-GS and 3DGS.

    python scripts/bench_iteration.py --scene SCENE --work WORK [--methods dibrgs 3dgs]
        [--preset cpu] [--warmup 300] [--repeats 5] [--threads 1] [--ratio-rounds R
        [--ratio-threads 2]] [--out result.json]

Builds each method as training does (``Trainer.setup`` with ``--preset``, pseudo views off:
only training views are timed, and a pseudo-view iteration costs the same), trains
``--warmup`` real iterations (``WORK/<method>``, growth included, so the model has a
trained size; the run is resumed when it already exists), then measures with
``--threads`` torch threads, process CPU time (``time.process_time``, all threads; wall time
beside it for forward + backward), the minimum over ``--repeats`` of the mean over the
training views:

* ``iteration``: the trainer's step (render, loss, backward, finite check, optimiser step,
  parameter check, strategy hooks) at an iteration after growth and before P freezes, on
  each training view in turn; its wall time too (for the 2-thread ratio);
* components, each forward and forward + backward (a random upstream gradient), on the
  tensors of a real iteration: ``gaussians`` (frustum, IBR P and decode MLPs for DIBR-GS;
  activation and SH colour for 3DGS), ``ibr_P`` and ``decode`` separately (DIBR-GS),
  ``ibr_P_maps`` (the projection through the full fused maps, as before issue 17, for
  comparison), ``rasterize`` (projection + compositing), ``composite`` (the compositing
  kernel alone), ``loss`` (L1 + D-SSIM), and ``step`` (finite checks + optimiser step).

``--ratio-rounds R`` then times the iteration on one thread and on ``--ratio-threads``
alternately, R rounds in the same process, and reports each round's ratio (two-thread against
one-thread wall time): separate processes differ by the machine's drift between them. Each timing
is bracketed by a control workload on the same threads; the median over the rounds whose controls
were at their best (the host calm on both sides) is reported beside the median of all rounds and
the ratio of each side's fastest round (what the code takes when nothing else slows it).

Run it from the repository root (or with the package on ``PYTHONPATH``); prints a table
and writes JSON with the machine (CPU model, vector extensions, cores), the sizes, the load
average, the OpenMP wait policy chosen at start (:mod:`dibrgs_core.common.openmp`, as the
``dibrgs`` command chooses it) and the torch configuration.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from dibrgs_core.common.allocator import allocator_policy, keep_freed_memory  # noqa: E402
from dibrgs_core.common.blas import blas_policy, single_thread_blas  # noqa: E402
from dibrgs_core.common.openmp import set_wait_policy, wait_policy  # noqa: E402

set_wait_policy()  # as the dibrgs command does, before torch loads libgomp
keep_freed_memory()
single_thread_blas()

import numpy as np  # noqa: E402
import torch  # noqa: E402

from dibrgs_core.bench.machine import cpu  # noqa: E402
from dibrgs_core.common.report import Report  # noqa: E402
from dibrgs_core.models.base import render_model  # noqa: E402
from dibrgs_core.render import composite, project_gaussians, rasterize  # noqa: E402
from dibrgs_core.training.config import preset  # noqa: E402
from dibrgs_core.training.losses import photometric_loss  # noqa: E402
from dibrgs_core.training.trainer import Trainer, train  # noqa: E402

try:  # the fused check (issue 17); the per-tensor test before it
    from dibrgs_core.training.guard import all_finite  # noqa: E402
except ImportError:  # pragma: no cover - measuring an older checkout
    def all_finite(ts):
        return all(t is None or bool(torch.isfinite(t).all()) for t in ts)


def timed(fn: Callable[[], Any], repeats: int) -> dict[str, float]:
    """Min CPU and wall seconds of ``fn()`` over ``repeats`` calls (after one warm-up call)."""
    fn()
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return {"cpu_ms": 1e3 * min(cpu), "wall_ms": 1e3 * min(wall)}


def fwd_bwd(make: Callable[[], Any], repeats: int) -> dict[str, float]:
    """Forward alone (no grad) and forward + backward of ``make()`` (tensor or tuple of tensors)."""
    with torch.no_grad():
        outs = make()
    outs = outs if isinstance(outs, tuple) else (outs,)
    gen = torch.Generator().manual_seed(0)
    grads = [torch.randn(o.shape, generator=gen) if o.is_floating_point() else None for o in outs]

    def fwd():
        with torch.no_grad():
            make()

    def both():
        o = make()
        o = o if isinstance(o, tuple) else (o,)
        pairs = [(a, g) for a, g in zip(o, grads) if g is not None and a.requires_grad]
        torch.autograd.backward([a for a, _ in pairs], [g for _, g in pairs])

    f, b = timed(fwd, repeats), timed(both, repeats)
    return {"fwd_ms": f["cpu_ms"], "fwd_bwd_ms": b["cpu_ms"], "bwd_ms": b["cpu_ms"] - f["cpu_ms"],
            "fwd_bwd_wall_ms": b["wall_ms"]}


def leaf(t: torch.Tensor) -> torch.Tensor:
    return t.detach().clone().requires_grad_(t.is_floating_point())


def build(scene: Path, work: Path, method: str, preset_name: str, warmup: int) -> Trainer:
    cfg = preset(preset_name)
    cfg.method = method
    cfg.pseudo.mode = "off"
    cfg.curve_every_s = 1e12
    cfg.checkpoint_every_s = 1e12
    if warmup and not (work / "checkpoint.pt").exists():
        train(scene, work, cfg, stop_after=warmup)
    t = Trainer(scene, work, cfg, resume=warmup > 0)
    ck = t.setup()
    if ck is not None:
        t.method.load(ck["method"])
    return t


def iteration(t: Trainer, frame, it: int) -> None:
    """The trainer's step (training/trainer.py ``_loop``), without its book-keeping."""
    m, model, strategy, cfg = t.method, t.method.model, t.method.strategy, t.cfg
    m.set_lr(it)
    img, _a, _d, info = render_model(model, frame.cam, t.bg, "RGB")
    strategy.step_pre_backward(model, m.optimizer, it, info)
    loss = photometric_loss(img, frame.image, lam=cfg.lambda_dssim, mask=frame.mask)
    if cfg.lambda_volume:
        loss = loss + m.regulariser(info, cfg.lambda_volume)
    loss.backward()
    if all_finite([p.grad for p in m.parameters()]):
        m.step(it)
    m.zero_grad()
    all_finite(m.parameters())
    changes = strategy.step_post_backward(model, m.optimizer, it, info)
    m.after_step(it, changes, Report())


def components(t: Trainer, frame, repeats: int) -> dict[str, dict[str, float]]:
    model, cam = t.method.model, frame.cam
    W, H = cam.cam.width, cam.cam.height
    out: dict[str, dict[str, float]] = {}
    out["gaussians"] = fwd_bwd(lambda: tuple(model.gaussians(cam).as_dict().values()), repeats)
    ibr = getattr(t.method, "ibr", None)
    if t.cfg.method == "dibrgs":
        vis = model.visible_anchors(cam.K, cam.w2c, W, H)
        anchors = model.anchor.detach()
        if ibr is not None:
            import inspect

            if "mask" in inspect.signature(ibr.forward).parameters:
                out["ibr_P"] = fwd_bwd(lambda: ibr(anchors, vis), repeats)
            else:  # pragma: no cover - an older checkout
                out["ibr_P"] = fwd_bwd(lambda: ibr(anchors[vis]), repeats)
            out["ibr_P_maps"] = fwd_bwd(lambda: ibr_through_maps(ibr, anchors[vis]), repeats)
            with torch.no_grad():
                feats = ibr(anchors, vis) if "ibr_P" in out else None
        else:
            feats = None
        f = None if feats is None else leaf(feats)

        def dec():
            d = model.decode(cam.K, cam.w2c, cam.center, W, H, ibr_feats=f, visible=vis)
            return d.means, d.quats, d.scales, d.opacities, d.colors

        out["decode"] = fwd_bwd(dec, repeats)
    with torch.no_grad():
        g = model.gaussians(cam)
    gs = [leaf(x) for x in (g.means, g.quats, g.scales, g.opacities, g.colors)]
    out["rasterize"] = fwd_bwd(lambda: rasterize(*gs, cam.w2c, cam.K, W, H, background=t.bg)[:3], repeats)
    with torch.no_grad():
        p = project_gaussians(*gs[:3], cam.w2c, cam.K, W, H)
        feats_c = torch.cat([gs[4], p.depths[:, None], torch.ones_like(p.depths)[:, None]], 1)
    ins = [leaf(x) for x in (p.means2d, p.conics, gs[3], feats_c)]
    out["composite"] = fwd_bwd(lambda: composite(ins[0], ins[1], ins[2], ins[3], p.depths, p.radii, W, H),
                               repeats)
    with torch.no_grad():
        img = rasterize(*gs, cam.w2c, cam.K, W, H, background=t.bg)[0].clamp(0, 1)
    im = leaf(img)
    out["loss"] = fwd_bwd(lambda: photometric_loss(im, frame.image, lam=t.cfg.lambda_dssim, mask=frame.mask),
                          repeats)
    return out


def ibr_through_maps(ibr, X: torch.Tensor) -> torch.Tensor:
    """The IBR projection as before issue 17: P on every view's full maps, upsampled, sampled."""
    import torch.nn.functional as F

    maps = ibr.feature_maps()
    R, tr = ibr.w2c[:, :3, :3], ibr.w2c[:, :3, 3]
    Xc = torch.einsum("vij,nj->vni", R, X) + tr[:, None, :]
    z = Xc[..., 2]
    front = z > 1e-6
    pix = torch.einsum("vij,vnj->vni", ibr.K, Xc / torch.where(front, z, torch.ones_like(z))[..., None])
    u, v = pix[..., 0], pix[..., 1]
    W, H = ibr.size[:, 0, None], ibr.size[:, 1, None]
    ok = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    grid = torch.stack([2.0 * u / W - 1.0, 2.0 * v / H - 1.0], dim=-1)
    grid = torch.where(ok[..., None], grid, torch.zeros_like(grid))
    s = torch.stack([F.grid_sample(m[None], g[None, None], mode="bilinear", padding_mode="border",
                                   align_corners=False)[0, :, 0] for m, g in zip(maps, grid)])
    w = ok.to(s.dtype)
    return ((s * w[:, None]).sum(0) / w.sum(0).clamp(min=1.0)).T


def bench_method(args, method: str) -> dict[str, Any]:
    t = build(args.scene, args.work / method, method, args.preset, args.warmup)
    torch.set_num_threads(args.threads)
    frames = t.train_frames
    cfg = t.cfg
    # an iteration after growth ends and before P freezes, never a growth step
    it0 = cfg.it(cfg.growth.densify_until) + 1
    res: dict[str, Any] = {"method": method, "size": f"{frames[0].cam.cam.width}x{frames[0].cam.cam.height}",
                           "sizes": t.method.model.sizes(), "timed_at_iteration": it0,
                           "P_trainable": bool(getattr(t.method, "p_params", [])) and
                           bool(t.method.p_params[0].requires_grad)}
    n = {"v": 0}

    def one():
        f = frames[n["v"] % len(frames)]
        n["v"] += 1
        iteration(t, f, it0)

    def all_views():
        for _ in frames:
            one()

    full = timed(all_views, args.repeats)
    res["iteration"] = {k: v / len(frames) for k, v in full.items()}
    per = [components(t, f, args.repeats) for f in frames]
    res["components"] = {k: {q: float(np.mean([p[k][q] for p in per])) for q in per[0][k]} for k in per[0]}
    ps = t.method.parameters()
    for p in ps:
        p.grad = torch.zeros_like(p)
    res["components"]["finite_checks"] = timed(lambda: (all_finite([p.grad for p in ps]), all_finite(ps)),
                                               args.repeats)
    t.method.zero_grad()
    res["sizes_after"] = t.method.model.sizes()
    if args.ratio_rounds:
        res["ratio"] = thread_ratio(all_views, len(frames), args.ratio_threads, args.ratio_rounds, args.repeats)
    torch.set_num_threads(args.threads)
    return res


#: A round counts as calm when each of its control timings is within this factor of the run's best
#: for that thread count (a neighbour on the host slows either side of a round).
CALM_SLACK = 1.1


def control_ms(x: torch.Tensor, y: torch.Tensor, repeats: int = 5) -> float:
    """Wall time (ms, best of ``repeats``) of a fixed workload that splits evenly over any thread
    count (``exp`` then ``sin`` of 2^20 floats, 4 MiB, no Python between): what the machine gives
    this many threads right now, beside the step."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.sin(torch.exp(x, out=y), out=y)
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def control_ranges(controls: list[list[float]]) -> tuple[tuple[float, float], tuple[float, float]]:
    """(best, worst) of the controls (a round's one thread before / after, many before / after)
    on one thread and on many, over all rounds."""
    one = [x for c in controls for x in c[:2]]
    many = [x for c in controls for x in c[2:]]
    return (min(one), max(one)), (min(many), max(many))


def calm_rounds(controls: list[list[float]], slack: float = CALM_SLACK) -> list[int]:
    """Indices of the rounds whose controls were each within ``slack`` of the best control of their
    thread count over all rounds."""
    (best1, _), (bestn, _) = control_ranges(controls)
    return [i for i, c in enumerate(controls) if max(c[:2]) <= slack * best1 and max(c[2:]) <= slack * bestn]


def thread_ratio(all_views: Callable[[], None], n_views: int, threads: int, rounds: int,
                 repeats: int) -> dict[str, Any]:
    """Iteration wall time on one thread and on ``threads``, alternating in this process for
    ``rounds`` rounds (the same build and model; drift of the machine hits both), and the ratio of
    each round.

    A shared host (a cloud VM whose cores' other hardware threads run other tenants) can slow one
    core for seconds, so each timing is bracketed by a control workload on the same thread count
    (:func:`control_ms`); the rounds whose four controls were all within ``CALM_SLACK`` of their
    thread count's best are reported apart (``calm_*``), beside all rounds and the ratio of each
    side's fastest round (``ratio_of_minima``), with the controls' own best ratio (about
    1 / ``threads`` when the cores are the machine's own)."""
    x = torch.rand(1 << 20)
    y = torch.empty_like(x)
    one, many, ctrl = [], [], []
    for _ in range(rounds):
        c = []
        for n, acc in ((1, one), (threads, many)):
            torch.set_num_threads(n)
            c.append(control_ms(x, y))
            acc.append(timed(all_views, repeats)["wall_ms"] / n_views)
            c.append(control_ms(x, y))
        ctrl.append(c)  # one thread before / after, then ``threads`` before / after
    ratios = [b / a for a, b in zip(one, many)]
    calm = calm_rounds(ctrl)
    (best1, _), (bestn, _) = control_ranges(ctrl)
    res = {"threads": threads, "one_ms": one, "many_ms": many, "ratios": ratios,
           "median_ratio": float(np.median(ratios)), "median_one_ms": float(np.median(one)),
           "median_many_ms": float(np.median(many)), "ratio_of_minima": min(many) / min(one), "control_ms": ctrl,
           "control_ratio": bestn / best1,
           "calm_rounds": calm}
    if calm:
        res["calm_median_ratio"] = float(np.median([ratios[i] for i in calm]))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--work", type=Path, required=True, help="run folders (init cache, warm-up runs)")
    ap.add_argument("--methods", nargs="+", default=["dibrgs", "3dgs"], choices=["dibrgs", "3dgs"])
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--warmup", type=int, default=300, help="real training iterations before timing")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--ratio-rounds", type=int, default=0,
                    help="also time the iteration on one thread and on --ratio-threads, alternating, this many rounds")
    ap.add_argument("--ratio-threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)  # set-up and warm-up as training does by default
    from dibrgs_core.render import fast

    out = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": cpu(), "loadavg_start": os.getloadavg(),
           "threads": args.threads, "openmp_wait": wait_policy(), "blas": blas_policy(), "allocator": allocator_policy(),
           "preset": args.preset, "warmup": args.warmup,
           "repeats": args.repeats,
           "fast_rasterizer": fast.available(required=False), "results": []}
    for m in args.methods:
        r = bench_method(args, m)
        out["results"].append(r)
        print(f"\n{m} {r['size']}, {r['sizes']}, {args.threads} thread(s): iteration "
              f"{r['iteration']['cpu_ms']:.1f} ms CPU, {r['iteration']['wall_ms']:.1f} ms wall")
        for k, v in r["components"].items():
            print("  " + f"{k:14s} " + ", ".join(f"{q} {x:7.1f}" for q, x in v.items()))
        if "ratio" in r:
            q = r["ratio"]
            print(f"  {q['threads']} threads against 1, {len(q['ratios'])} alternating rounds: "
                  f"{q['median_one_ms']:.2f} and {q['median_many_ms']:.2f} ms wall (medians), ratio per round "
                  f"{min(q['ratios']):.3f}-{max(q['ratios']):.3f}, median {q['median_ratio']:.3f}; "
                  f"fastest round of each {min(q['one_ms']):.2f} and {min(q['many_ms']):.2f} ms, "
                  f"ratio {q['ratio_of_minima']:.3f}")
            calm = (f"median {q['calm_median_ratio']:.3f}" if q["calm_rounds"] else "none")
            (lo1, hi1), (lon, hin) = control_ranges(q["control_ms"])
            print(f"  rounds whose controls were within {CALM_SLACK - 1:.0%} of their best: {len(q['calm_rounds'])} of "
                  f"{len(q['ratios'])}, {calm} (the control's own {q['threads']}-thread ratio "
                  f"{q['control_ratio']:.3f}; controls {lo1:.2f}-{hi1:.2f} ms on one thread, "
                  f"{lon:.2f}-{hin:.2f} on {q['threads']})")
    out["loadavg_end"] = os.getloadavg()
    m = out["machine"]
    print(f"\nmachine: {m['model']}, {m['cores']} cores, vector extensions: {m['vector']}")
    print(f"load average {out['loadavg_start']} -> {out['loadavg_end']}; OpenMP wait: {out['openmp_wait']}")
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
