"""Shared fixtures. bpy is imported headless in tests (the real module, no mocks)."""
from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported (see dibrgs_core.cli)

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_dir() -> Path:
    """The project's shared/ folder: $DIBRGS_SHARED, else ../shared beside the repo."""
    return Path(os.environ.get("DIBRGS_SHARED", REPO.parent / "shared"))


def shared_file(rel: str) -> Path:
    """A file from shared/, or skip the test with the reason when it is absent."""
    p = shared_dir() / rel
    if not p.exists():
        pytest.skip(f"shared file {p} not found (set DIBRGS_SHARED to the shared/ folder)")
    return p


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 64x64 generated city scene in LEVIR-NVS layout (rendered once per session)."""
    from dibrgs_core.synth.writer import make_scene

    out = tmp_path_factory.mktemp("scenes") / "city64"
    make_scene(kind="city", resolution=64, seed=0, out=out)
    return out
