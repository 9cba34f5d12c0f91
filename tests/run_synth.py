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

import pytest

from train_synth import make_synth_scene

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
                      **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([*prefix, sys.executable, "-m", "dibrgs_core", *map(str, argv)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=REPO, **kw)


def copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return dst


@pytest.fixture(scope="session")
def scene24(tmp_path_factory) -> Path:
    """The 24x24 synthetic scene (21 views, LEVIR layout, depth maps)."""
    return make_synth_scene(tmp_path_factory.mktemp("scenes") / "s24", resolution=24)


@pytest.fixture(scope="session")
def other_scene24(tmp_path_factory) -> Path:
    """Another scene of the same layout and size (another seed)."""
    return make_synth_scene(tmp_path_factory.mktemp("scenes") / "other24", resolution=24, seed=1)


@pytest.fixture(scope="session")
def finished_run(scene24, tmp_path_factory) -> Path:
    """A run trained to the end through the command line (6 iterations), with its caches and model."""
    work = tmp_path_factory.mktemp("runs") / "done"
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "6")
    assert rc == 0, err
    return work
