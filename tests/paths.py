"""Where the tests find the repository and the project's shared/ data (imported by name:
``from paths import REPO, shared_file``)."""
from __future__ import annotations

import os
from pathlib import Path

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
