"""Run folders for the fault and resume tests: a tiny synthetic scene, one finished `test`-preset run
made through the real command line, copies of it, and the command line called in this process.

``dibrgs(...)`` runs ``dibrgs_core.cli.main`` in-process (the same parser, commands and error path
as the installed command, without a torch import per call) and returns its exit code and stderr;
``dibrgs_subprocess(...)`` runs ``python -m dibrgs_core`` for what needs a separate process
(locks held by another process, signals, a changed user or mount).
"""
from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
import sys
from pathlib import Path



REPO = Path(__file__).resolve().parents[1]
#: Fast training options: the test preset, a handful of iterations, one torch thread.
QUICK = ("--preset", "test", "--threads", "1")


def dibrgs(*argv: str | Path) -> tuple[int, str]:
    """``dibrgs ARGV`` in this process: (exit code, stderr)."""
    from dibrgs_core.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as e:  # argparse
            rc = int(e.code or 0)
    return rc, err.getvalue()


def dibrgs_subprocess(*argv: str | Path, prefix: tuple[str, ...] = (), timeout: float = 600,
                      env: dict[str, str] | None = None, **kw) -> subprocess.CompletedProcess:
    base = dict(os.environ if env is None else env)
    env = dict(base, PYTHONPATH=str(REPO) + os.pathsep + base.get("PYTHONPATH", ""))
    return subprocess.run([*prefix, sys.executable, "-m", "dibrgs_core", *map(str, argv)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=REPO, **kw)


def copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return dst


