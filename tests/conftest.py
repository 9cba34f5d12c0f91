"""Shared fixtures. bpy is imported headless in tests (the real module, no mocks)."""
from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads: tests share the cores (dibrgs_core.common.openmp)

import pytest

#: Memory one test process may need at its peak (bpy, torch and a training run: 1.7 GiB measured on the full suite).
WORKER_MEMORY_BYTES = 3 << 30


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto`` (pyproject's addopts): one test process per CPU this process may run on, as few
    as the memory holds. Most tests are one thread of Python, so two processes on two cores take
    about 0.6 of one's time; ``-n 0`` runs them in this process (for ``--pdb``)."""
    from dibrgs_core.commands.options import available_cores  # no torch: the wait policy above still applies

    cpus = available_cores()
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return cpus
    return max(1, min(cpus, memory // WORKER_MEMORY_BYTES))


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 64x64 generated city scene in LEVIR-NVS layout (rendered once per session)."""
    from dibrgs_core.synth.writer import make_scene

    out = tmp_path_factory.mktemp("scenes") / "city64"
    make_scene(kind="city", resolution=64, seed=0, out=out)
    return out


# -- run folders for the fault and resume tests (helpers in tests/run_synth.py) ------------
@pytest.fixture(scope="session")
def scene24(tmp_path_factory) -> Path:
    """The 24x24 synthetic scene (21 views, LEVIR layout, depth maps)."""
    from train_synth import make_synth_scene

    return make_synth_scene(tmp_path_factory.mktemp("scenes") / "s24", resolution=24)


@pytest.fixture(scope="session")
def synth(tmp_path_factory) -> Path:
    """The 32x32 synthetic scene (21 views, LEVIR layout, depth maps): training tests."""
    from train_synth import make_synth_scene

    return make_synth_scene(tmp_path_factory.mktemp("scenes") / "s32", resolution=32)


@pytest.fixture(scope="session")
def other_scene24(tmp_path_factory) -> Path:
    """Another scene of the same layout and size (another seed)."""
    from train_synth import make_synth_scene

    return make_synth_scene(tmp_path_factory.mktemp("scenes") / "other24", resolution=24, seed=1)


@pytest.fixture(scope="session")
def finished_run(scene24, tmp_path_factory) -> Path:
    """A run trained to the end through the command line (6 iterations), with its caches and model."""
    from run_synth import QUICK, dibrgs

    work = tmp_path_factory.mktemp("runs") / "done"
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "6")
    assert rc == 0, err
    return work
