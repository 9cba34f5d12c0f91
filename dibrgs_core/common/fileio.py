"""Atomic file output: write to a temporary name beside the target, then rename.

* A run killed half-way never leaves a half-written file under the final name; a failed write
  (no space, permission) leaves the old file as it was and no temporary file behind.
* A symbolic link is followed: the file it points to is replaced, the link stays a link.
* Only regular files are replaced: a folder, FIFO, socket or device at the target is refused
  (``InputError`` naming it) - renaming over ``/dev/full`` would replace the device.
* A new file gets the mode the umask gives (``0o666 & ~umask``, as ``open()`` would); a replaced
  file keeps its mode. ``mkstemp``'s 0600 would hide generated scenes and renders from other users.
* JSON is strict (RFC 8259): NaN and infinities are written as ``null``, never as ``NaN`` /
  ``Infinity``; callers that can say why a value is undefined record the reason beside it.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import stat
import tempfile
from pathlib import Path
from typing import Any, Iterator

from .errors import InputError


def umask() -> int:
    """The process's umask (read from /proc where possible: setting it to read it is not thread-safe)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def resolve_target(path: str | Path) -> Path:
    """The file a write to ``path`` must replace: symbolic links followed (also dangling ones);
    ``InputError`` when something other than a regular file is there."""
    path = Path(path)
    real = Path(os.path.realpath(path))
    try:
        st = os.stat(real)
    except FileNotFoundError:
        return real
    if not stat.S_ISREG(st.st_mode):
        kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode)
                else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        shown = path if real == path.absolute() else f"{path} (-> {real})"
        raise InputError(shown, f"is {kind}, not a regular file; give the name of a file to write")
    return real


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it over the target on success.

    The temporary name keeps the final suffix so libraries that pick a format from the
    extension (PIL, tifffile, trimesh) still work.
    """
    target = resolve_target(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        mode = stat.S_IMODE(os.stat(target).st_mode)
    except FileNotFoundError:
        mode = 0o666 & ~umask()
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=target.parent)
    except OSError as e:
        raise _naming(e, target) from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, mode)
        os.replace(tmp_path, target)
    except OSError as e:
        # the user knows the target, not the temporary name (writers to file objects name none)
        raise _naming(e, target) if e.filename in (None, tmp, str(tmp_path)) else e from None
    finally:
        with contextlib.suppress(OSError):
            tmp_path.unlink()


def _naming(e: OSError, target: Path) -> OSError:
    """The same error naming ``target``."""
    return type(e)(e.errno, e.strerror, str(target)) if e.errno is not None else e


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def strict_json(obj: Any) -> Any:
    """``obj`` with every non-finite float (Python or NumPy) replaced by None, numpy arrays and
    scalars as lists and numbers, paths as strings: what :func:`json.dumps` writes as strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, str) else k: strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    import numpy as np

    if isinstance(obj, np.ndarray):
        return strict_json(obj.tolist())
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return strict_json(obj.item())
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def dumps(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` (see :func:`strict_json`)."""
    return json.dumps(strict_json(obj), indent=indent, allow_nan=False)


def write_json(path: str | Path, obj: Any) -> None:
    write_text(path, dumps(obj) + "\n")
