"""Content digests: what a cache or a run depends on, as one hex string.

A cache (the geometry initialisation, SfM points, undistorted photos) stores the digest of its
inputs and is used only when the digest of the current inputs is the same, so a run never picks
up another scene's, another split's or another option's results. Paths are never part of a
digest (a copied scene or run folder keeps its caches); contents are. Standard library and
numpy only.
"""
from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np


class Digest:
    """An incremental SHA-256 over typed parts (arrays by dtype, shape and bytes; JSON by canonical text)."""

    def __init__(self, kind: str) -> None:
        self._h = hashlib.sha256(kind.encode())

    def array(self, a: Any) -> "Digest":
        a = np.ascontiguousarray(a)
        self._h.update(f"|a{a.dtype.str}{a.shape}|".encode())
        self._h.update(a.data if a.size else b"")
        return self

    def json(self, obj: Any) -> "Digest":
        self._h.update(b"|j")
        self._h.update(json.dumps(obj, sort_keys=True, default=str, separators=(",", ":")).encode())
        return self

    def text(self, s: str) -> "Digest":
        self._h.update(b"|t" + s.encode())
        return self

    def bytes(self, b: bytes) -> "Digest":
        self._h.update(f"|b{len(b)}|".encode())
        self._h.update(b)
        return self

    def hex(self, n: int = 24) -> str:
        """The first ``n`` hex digits (96 bits by default: no accidental collisions between caches)."""
        return self._h.hexdigest()[:n]


def file_digest(path: Any, chunk: int = 1 << 20) -> str:
    """SHA-256 (24 hex digits) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()[:24]
