"""Benchmark pages from finished runs: ``results.csv``, ``curves.png`` (held-out PSNR against
training seconds, one panel a scene) and the Markdown tables of ``docs/benchmarks.md``.

Units: times in seconds of training wall-clock (evaluation excluded), PSNR in dB, memory in MiB.
"plateau s" is when a run's curve levelled off (:func:`.runner.plateau_seconds`).
"""
from __future__ import annotations

import csv
import json
import platform
import time
from pathlib import Path
from typing import Any, Callable

from ..common.fileio import atomic_path, write_text
from .machine import cpu
from .runner import ABLATION_LABELS, ABLATIONS, RESULT_COLUMNS, RunSpec, Suite, plateau_seconds


def load_results(results: Path, suite: Suite | None = None) -> list[dict[str, Any]]:
    keys = None if suite is None else {s.key for s in suite.runs}
    out = []
    for p in sorted((results / "runs").glob("*.json")):
        r = json.loads(p.read_text())
        if keys is None or RunSpec(**r["spec"]).key in keys:
            if "plateau_seconds" not in r["row"]:  # a result from before the column: its curve says
                r["row"]["plateau_seconds"] = plateau_seconds(r["curve"])
            out.append(r)
    return out


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=RESULT_COLUMNS, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in RESULT_COLUMNS})


def curve_points(res: dict[str, Any]) -> tuple[list[float], list[float], tuple[float, float] | None]:
    """A result's curve to draw: (seconds, PSNR) of its points, the last one on the views the
    earlier points evaluated (when they evaluated a subset, so that the line does not jump at the
    change of views), and the final all-view point (seconds, PSNR) to mark apart (None when the
    points evaluated every view)."""
    c = [p for p in res["curve"] if p["seconds"] > 0]
    xs, ys = [p["seconds"] for p in c], [p["psnr"] for p in c]
    sub = res.get("final_psnr_on_point_views")
    if sub is None or not c:
        return xs, ys, None
    final = (xs[-1], ys[-1])
    ys[-1] = sub
    return xs, ys, final


def draw_curve(ax: Any, res: dict[str, Any], label: str, style: str = "-", color: str | None = None) -> None:
    """Draw one result's curve (:func:`curve_points`) on ``ax``, a star at its all-view final
    PSNR; nothing for a curve without points after the start."""
    xs, ys, final = curve_points(res)
    if not xs:
        return
    line, = ax.plot(xs, ys, style, color=color, marker=".", label=label)
    if final is not None:  # the last point on every held-out view
        ax.plot(*final, marker="*", ms=9, ls="none", color=line.get_color())


def curve_figure(scenes: list[str], draw: Callable[[Any, str], None], path: Path) -> None:
    """One panel a scene, ``draw(ax, scene)`` filling each: held-out PSNR against training
    seconds on a log axis; written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    n = max(1, len(scenes))
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.4), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        draw(ax, scene)
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())  # minor labels overlap on short spans
        ax.set_title(scene)
        ax.set_xlabel("training wall-clock (s)")
        ax.set_ylabel("held-out PSNR (dB)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def plot_curves(res: list[dict[str, Any]], path: Path) -> None:
    """One panel a scene, one line a method: held-out PSNR against training seconds (log x); the
    lines are on the curve's subset of views, a star marks the final PSNR on all of them."""

    def draw(ax: Any, scene: str) -> None:
        for r in sorted((r for r in res if r["row"]["scene"] == scene), key=lambda r: r["row"]["method"]):
            draw_curve(ax, r, r["row"]["method"])

    curve_figure(sorted({r["row"]["scene"] for r in res}), draw, path)


def _fmt(v: Any, nd: int = 2) -> str:
    if v is None or v == "":
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def markdown_tables(res: list[dict[str, Any]]) -> str:
    rows = [r["row"] for r in res]
    lines: list[str] = []
    methods = [m for m in ("3dgs", "dibrgs") if any(r["method"] == m for r in rows)]
    if methods:
        lines += ["### Methods (mean over scenes; as the paper's Table I)", "",
                  "| Method | PSNR | SSIM | LPIPS | AVGE | FPS | train s | plateau s | Gaussians | peak MiB |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for m in methods:
            rs = [r for r in rows if r["method"] == m]

            def mean(k: str) -> float | None:
                vals = [r[k] for r in rs if r.get(k) is not None]
                return sum(vals) / len(vals) if vals else None

            lines.append(f"| {m} | {_fmt(mean('psnr'))} | {_fmt(mean('ssim'), 3)} | {_fmt(mean('lpips'), 3)} | "
                         f"{_fmt(mean('avge'), 3)} | {_fmt(mean('fps'), 1)} | {_fmt(mean('train_seconds'), 0)} | "
                         f"{_fmt(mean('plateau_seconds'), 0)} | {_fmt(mean('gaussians'), 0)} | "
                         f"{_fmt(mean('peak_memory_mib'), 0)} |")
        scenes = sorted({r["scene"] for r in rows})
        lines += ["", "### Per scene PSNR / SSIM (as the paper's Table II)", "",
                  "| Metric | Method | " + " | ".join(scenes) + " |", "|---|---|" + "---|" * len(scenes)]
        for metric, nd in (("psnr", 2), ("ssim", 3), ("lpips", 3)):
            for m in methods:
                vals = []
                for s in scenes:
                    hit = [r for r in rows if r["method"] == m and r["scene"] == s]
                    vals.append(_fmt(hit[0][metric], nd) if hit else "-")
                lines.append(f"| {metric.upper()} | {m} | " + " | ".join(vals) + " |")
    abl = [r for r in rows if r["method"] in ABLATIONS or r["method"] == "dibrgs"]
    abl_scenes = sorted({r["scene"] for r in rows if r["method"] in ABLATIONS})
    for s in abl_scenes:
        lines += ["", f"### Ablation of components on {s} (as the paper's architecture ablation)", "",
                  "| Setting | PSNR | SSIM | LPIPS | AVGE | train s | Gaussians | peak MiB |",
                  "|---|---|---|---|---|---|---|---|"]
        for m in ABLATIONS + ["dibrgs"]:
            hit = [r for r in abl if r["method"] == m and r["scene"] == s]
            if hit:
                r = hit[0]
                lines.append(f"| {ABLATION_LABELS[m]} | {_fmt(r['psnr'])} | {_fmt(r['ssim'], 3)} | "
                             f"{_fmt(r['lpips'], 3)} | {_fmt(r['avge'], 3)} | {_fmt(r['train_seconds'], 0)} | "
                             f"{_fmt(r['gaussians'], 0)} | {_fmt(r['peak_memory_mib'], 0)} |")
    return "\n".join(lines) + "\n"


def machine_description() -> str:
    """One line for a suite's page: cores, CPU model and vector extensions, OS, Python, torch."""
    import torch

    c = cpu()
    return (f"{c['cores']} CPU cores ({c['model']}; {c['vector'] or 'no x86 vector flags'}), "
            f"{platform.system()} {platform.release()}, Python {platform.python_version()}, "
            f"torch {torch.__version__}; each run is a `dibrgs train` child process with its default "
            f"of 1 torch thread")


def update_benchmarks_md(md_path: Path, suite: str, command: str, body: str, figure_rel: str) -> None:
    """Replace (or append) the section for ``suite`` in docs/benchmarks.md, leaving other sections."""
    start, end = f"<!-- benchmark:{suite}:start -->", f"<!-- benchmark:{suite}:end -->"
    section = (f"{start}\n## Benchmark suite `{suite}`\n\n"
               f"Command: `{command}`  \nDate: {time.strftime('%Y-%m-%d')}  \nMachine: {machine_description()}\n\n"
               f"![held-out PSNR against training time]({figure_rel})\n\n{body}{end}")
    text = md_path.read_text() if md_path.exists() else "# Benchmarks\n"
    if start in text and end in text:
        text = text.split(start)[0] + section + text.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    write_text(md_path, text)


def write_pages(results: Path, suite: Suite, docs: Path, command: str) -> list[dict[str, Any]]:
    """Write results.csv and curves.png over every finished run (all suites: their
    scenes differ by resolution), and the markdown section of ``suite``."""
    everything = load_results(results)
    res = load_results(results, suite)
    if not res:
        return res
    write_csv([r["row"] for r in everything], docs / "benchmarks" / "results.csv")
    fig = docs / "benchmarks" / "curves.png"
    plot_curves(everything, fig)
    update_benchmarks_md(docs / "benchmarks.md", suite.name, command, markdown_tables(res),
                         fig.relative_to(docs).as_posix())
    return res
