#!/usr/bin/env python
"""Compare two sets of benchmark runs (before / after a change): quality, time, and when each
run's error-against-time curve levelled off.

    python scripts/compare_benchmarks.py BEFORE AFTER [--labels before after] [--md T.md] [--png C.png]

BEFORE and AFTER are benchmark work folders (``scripts/benchmark.py --work``): their
``results/runs/*.json``; or folders of ``dibrgs train --out`` run folders (a real scene's
runs with two versions of the code, say), paired by scene folder name and method (a
benchmark's runs against run folders by the benchmark's scene folders, ``city256_levir_s0``);
or two run folders, compared with each other whatever they ran. A run folder's metrics come from
``metrics.json`` when ``dibrgs eval`` wrote one, else PSNR and SSIM from the curve's last point.
Runs present in both are compared: held-out PSNR (dB), training
seconds, plateau seconds (:func:`dibrgs_core.bench.runner.plateau_seconds`: the training second
from which held-out PSNR stays within 0.5 dB of its final value) and, where the result records
it (``wall_seconds``), the whole run's wall time (set-up, training, evaluation). The PNG draws
both curves of each run, one panel a scene (training seconds, log axis; dashed: before; a star:
the final PSNR on every held-out view where the points evaluated a subset; thin verticals: the
plateau seconds).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dibrgs_core.bench.pages import curve_figure, draw_curve, load_results  # noqa: E402
from dibrgs_core.bench.runner import RunSpec, folder_result, scene_path  # noqa: E402
from dibrgs_core.common.fileio import write_text  # noqa: E402


def is_run_folder(path: Path) -> bool:
    """Whether ``path`` is a ``dibrgs train`` run folder (its config and curve), not a benchmark's."""
    return (path / "config.json").is_file() and (path / "curve.csv").is_file()


def run_folder(path: Path) -> tuple[str, dict[str, Any]]:
    """(``<scene>__<method>``, result) of a trained run folder; the scene named by its folder."""
    try:
        cfg = json.loads((path / "config.json").read_text())
        scene, method, preset = Path(cfg["scene"]).name, cfg["config"]["method"], cfg["config"]["preset"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"compare_benchmarks.py: error: {path / 'config.json'} is not a run's config ({e!r})")
    return f"{scene}__{method}", folder_result(path, scene, method, preset)


def results_in(folder: Path) -> dict[str, dict[str, Any]]:
    """Results by run key: a benchmark folder's ``results/runs``, else the run folders directly in
    ``folder`` (or ``folder`` itself when it is one)."""
    if is_run_folder(folder):
        return dict([run_folder(folder)])
    if (folder / "results" / "runs").is_dir():
        return {RunSpec(**r["spec"]).key: r for r in load_results(folder / "results")}
    subs = sorted(p for p in folder.iterdir() if is_run_folder(p)) if folder.is_dir() else []
    return dict(run_folder(p) for p in subs)


def by_scene_folder(results: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``results`` with a benchmark's runs keyed as run folders are (``<scene folder>__<method>``:
    ``city256_levir_s0__dibrgs`` for ``city256__dibrgs``), the others as they were."""
    out = {}
    for k, r in results.items():
        spec = RunSpec(**r["spec"]) if "spec" in r else None
        out[f"{scene_path(spec, '').name}__{spec.method}" if spec else k] = r
    return out


def paired(before: Path, after: Path) -> list[tuple[str, dict[str, Any], dict[str, Any]]]:
    """(run key, before result, after result) for the runs both folders finished, by key; two run
    folders make one pair whatever their keys (``A / B`` when they differ)."""
    a, b = results_in(before), results_in(after)
    if not a or not b:
        raise SystemExit(f"compare_benchmarks.py: error: no finished runs in {before if not a else after} "
                         "(neither results/runs nor run folders)")
    if is_run_folder(before) and is_run_folder(after):
        (ka, ra), (kb, rb) = next(iter(a.items())), next(iter(b.items()))
        return [(ka if ka == kb else f"{ka} / {kb}", ra, rb)]
    common = sorted(set(a) & set(b))
    if not common:  # a benchmark's runs against run folders: the benchmark's named by their scene folders
        a, b = by_scene_folder(a), by_scene_folder(b)
        common = sorted(set(a) & set(b))
    if not common:
        raise SystemExit(f"compare_benchmarks.py: error: {before} and {after} have no run in common "
                         f"({', '.join(sorted(a))} against {', '.join(sorted(b))})")
    return [(k, a[k], b[k]) for k in common]


def table(pairs: list[tuple[str, dict, dict]], labels: tuple[str, str]) -> str:
    def f(v: Any, nd: int = 0) -> str:
        return "n/a" if v is None else f"{v:.{nd}f}"

    x, y = labels
    lines = [f"| run | PSNR {x} | PSNR {y} | train s {x} | train s {y} | plateau s {x} | plateau s {y} | "
             f"whole run s {x} | whole run s {y} |", "|---|" + "---:|" * 8]
    for k, a, b in pairs:
        ra, rb = a["row"], b["row"]
        lines.append(f"| {k} | {f(ra['psnr'], 2)} | {f(rb['psnr'], 2)} | {f(ra['train_seconds'])} | "
                     f"{f(rb['train_seconds'])} | {f(ra['plateau_seconds'])} | {f(rb['plateau_seconds'])} | "
                     f"{f(a.get('wall_seconds'))} | {f(b.get('wall_seconds'))} |")
    return "\n".join(lines) + "\n"


def plot(pairs: list[tuple[str, dict, dict]], labels: tuple[str, str], path: Path) -> None:
    def draw(ax, scene: str) -> None:
        for i, (_, a, b) in enumerate(p for p in pairs if p[1]["row"]["scene"] == scene):
            for res, label, style in ((a, labels[0], "--"), (b, labels[1], "-")):
                draw_curve(ax, res, f"{res['row']['method']} {label}", style, color=f"C{i}")
                if res["row"].get("plateau_seconds"):
                    ax.axvline(res["row"]["plateau_seconds"], color=f"C{i}", ls=style, lw=0.6, alpha=0.6)

    curve_figure(sorted({a["row"]["scene"] for _, a, _ in pairs}), draw, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--labels", nargs=2, default=["before", "after"])
    ap.add_argument("--md", type=Path, help="write the table here")
    ap.add_argument("--png", type=Path, help="both curves of each run, one panel a scene")
    args = ap.parse_args(argv)
    labels = (args.labels[0], args.labels[1])
    pairs = paired(args.before, args.after)
    md = table(pairs, labels)
    print(md)
    if args.md:
        write_text(args.md, md)
    if args.png:
        plot(pairs, labels, args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
