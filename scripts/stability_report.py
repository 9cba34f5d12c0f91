#!/usr/bin/env python
"""Run every extreme-case check (tests marked ``stability``: rasterizer, geometry,
training) and write the table docs/stability.md: case, what was checked, result.

The cases live once, in the test suite; this script runs them with pytest and
reads each test's docstring as "what was checked". Any failing case (a NaN or
Inf included) fails the script with a non-zero exit and leaves the page as it
was: a failure is a bug to fix, not a row in the table.

    python scripts/stability_report.py [--out docs/stability.md] [-k EXPR]
"""
from __future__ import annotations

import argparse
import inspect
import platform
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dibrgs_core.common.fileio import write_text  # noqa: E402


class Collector:
    """pytest plugin that records each stability test's outcome and docstring."""

    def __init__(self) -> None:
        self.rows: dict[str, dict] = {}

    def pytest_collection_modifyitems(self, items):  # noqa: D401 - pytest hook
        for it in items:
            doc = inspect.getdoc(getattr(it, "obj", None)) or ""
            area = Path(str(it.fspath)).stem.removeprefix("test_")
            self.rows[it.nodeid] = {"area": area, "case": it.name, "checked": " ".join(doc.split()),
                                    "result": "not run", "seconds": 0.0}

    def pytest_runtest_logreport(self, report):
        row = self.rows.get(report.nodeid)
        if row is None:
            return
        if report.when == "call" or (report.when == "setup" and report.outcome != "passed"):
            row["result"] = {"passed": "finite, as expected", "failed": "FAILED",
                             "skipped": "skipped"}[report.outcome]
            if report.outcome == "skipped" and isinstance(report.longrepr, tuple):
                row["result"] = f"skipped: {report.longrepr[2]}"
            row["seconds"] += report.duration


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=REPO / "docs" / "stability.md")
    p.add_argument("-k", default=None, help="pytest -k expression to run a subset")
    args = p.parse_args(argv)
    col = Collector()
    # In this process (-n 0): the collector reads the items, which test processes would hold.
    pargs = [str(REPO / "tests"), "-m", "stability", "-q", "-p", "no:cacheprovider", "-n", "0"]
    if args.k:
        pargs += ["-k", args.k]
    t0 = time.perf_counter()
    rc = pytest.main(pargs, plugins=[col])
    # Items deselected by -m/-k were collected but never reported: leave them out.
    rows = sorted((r for r in col.rows.values() if r["result"] != "not run"),
                  key=lambda r: (r["area"], r["case"]))
    failed = [r for r in rows if r["result"] == "FAILED"]
    if rc not in (0,) or failed or not rows:
        print(f"stability report: {len(failed)} failing case(s), pytest exit {rc}; {args.out} not updated",
              file=sys.stderr)
        return 1
    lines = ["# Stability report", "",
             "Extreme and stiff cases of the rasterizer, the geometry stage and training. Every case asserts",
             "finite outputs and gradients (and the expected value where one is known); a NaN or Inf fails",
             "the script instead of appearing here.", "",
             "Command: `python scripts/stability_report.py`  ",
             f"Date: {time.strftime('%Y-%m-%d')}  ",
             f"Machine: {platform.machine()}, {__import__('os').cpu_count()} cores, Python "
             f"{platform.python_version()}; {len(rows)} cases in {time.perf_counter() - t0:.0f} s", "",
             "| Area | Case | What was checked | Result |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['area']} | `{r['case']}` | {r['checked'] or '-'} | {r['result']} |")
    write_text(args.out, "\n".join(lines) + "\n")
    print(f"wrote {args.out} ({len(rows)} cases)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
