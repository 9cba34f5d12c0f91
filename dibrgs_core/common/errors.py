"""Errors raised for bad user input. The CLI prints them and exits non-zero."""
from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad input: names the offending file and what is wrong with it."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)
