"""One writer per run folder: an advisory lock file ``FOLDER/.dibrgs.lock``.

The holder's pid, host, command and start time are written into the file, so a second writer
gets a one-line :class:`~.errors.RunFolderBusy` naming the holder. The lock itself is an
operating-system lock on that file (``fcntl.flock``; ``msvcrt.locking`` on Windows), which the
kernel drops when the holder exits, however it exits (``kill -9`` included). A lock file left
behind by a dead process is therefore *stale* by construction: the next writer takes it over and
logs whose it was. On a file system without locks the pid decides: a holder on this host that
no longer runs is stale; one on another host cannot be checked and is reported with the file to
delete. Locks are re-entrant within a process (the CLI and the trainer both take the
run folder's lock). Standard library only.
"""
from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

from .errors import InputError, RunFolderBusy

log = logging.getLogger("dibrgs")

LOCK_NAME = ".dibrgs.lock"

_held: dict[str, tuple[int, int, bool]] = {}   # resolved folder -> (fd, depth, created it) held by this process
_guard = threading.Lock()


def _try_lock(fd: int) -> bool | None:
    """Lock ``fd`` without waiting: True (locked), False (another process holds it), or None when
    the file system has no locks (some network and FUSE file systems)."""
    if sys.platform == "win32":  # pragma: no cover - exercised on Windows only
        import msvcrt

        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
            return True
        except OSError:
            return False
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    except OSError as e:
        if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EINVAL, errno.ENOSYS):
            return None
        raise


def _alive(info: dict | None) -> bool:
    """Without file-system locks: whether the lock file's holder may still run (a process on another
    host cannot be checked, so it counts as alive)."""
    if not info or not isinstance(info.get("pid"), int):
        return False
    if info.get("host") != socket.gethostname():
        return True
    if info["pid"] == os.getpid():
        return False
    try:
        os.kill(info["pid"], 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def holder(folder: str | Path) -> dict | None:
    """What the lock file of ``folder`` says about its holder (None when there is none or it is unreadable)."""
    try:
        return json.loads((Path(folder) / LOCK_NAME).read_text() or "null")
    except (OSError, ValueError):
        return None


def describe(info: dict | None) -> str:
    if not info:
        return "another process"
    since = info.get("since")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since)) if isinstance(since, (int, float)) else "?"
    return f"pid {info.get('pid')} on {info.get('host')} ({info.get('command', '?')}, since {when})"


def _prepare(folder: Path) -> bool:
    """Make ``folder`` when missing; returns whether it did."""
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, "is a file, not a folder; give a folder for the outputs")
    if folder.is_dir():
        return False
    folder.mkdir(parents=True, exist_ok=True)
    return True


def acquire(folder: str | Path, command: str) -> int:
    """Take the lock of ``folder`` (created when missing) for ``command``; returns its file descriptor.

    Raises :class:`RunFolderBusy` when a live process holds it, ``InputError`` when ``folder``
    is a file, ``OSError`` when the folder cannot be created or written.
    """
    folder = Path(folder)
    created = _prepare(folder)
    key = os.path.realpath(folder)
    with _guard:
        if key in _held:
            fd, depth, made = _held[key]
            _held[key] = (fd, depth + 1, made)
            return fd
        path = Path(key) / LOCK_NAME
        for _ in range(20):
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            got = _try_lock(fd)
            if got is None:  # no file-system locks here: the pid in the file decides
                info = holder(key)
                got = not _alive(info)
                if not got and info and info.get("host") != socket.gethostname():
                    os.close(fd)
                    raise RunFolderBusy(folder, f"in use by {describe(info)} (this file system has no locks, so "
                                                f"it cannot be checked); if that process is gone, delete {path}")
                log.warning("%s: the file system has no file locks; relying on the pid in %s", folder, LOCK_NAME)
            if not got:
                os.close(fd)
                info = holder(key)
                raise RunFolderBusy(folder, f"in use by {describe(info)}; wait for it to finish, stop it, "
                                            "or choose another folder")
            # The previous holder may have removed the file between our open and lock: retry on the new one.
            try:
                same = os.fstat(fd).st_ino == os.stat(path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        else:  # pragma: no cover - would need 20 lost races in a row
            raise RunFolderBusy(folder, "its lock file keeps changing; another process is taking it")
        old = os.read(fd, 4096)
        if old.strip():
            with contextlib.suppress(ValueError):
                log.info("%s: taking over the stale lock of %s (no longer running)", folder,
                         describe(json.loads(old)))
        info = {"pid": os.getpid(), "host": socket.gethostname(), "command": command, "since": time.time()}
        os.lseek(fd, 0, os.SEEK_SET)
        os.ftruncate(fd, 0)
        os.write(fd, (json.dumps(info) + "\n").encode())
        _held[key] = (fd, 1, created)
        return fd


def release(folder: str | Path) -> None:
    """Release one hold of ``folder``'s lock; the last one removes the lock file (and the folder,
    when :func:`acquire` made it and nothing was written into it)."""
    key = os.path.realpath(folder)
    with _guard:
        if key not in _held:
            return
        fd, depth, created = _held[key]
        if depth > 1:
            _held[key] = (fd, depth - 1, created)
            return
        del _held[key]
        # Unlink while still locked, so a waiting process never locks a file that is gone.
        with contextlib.suppress(OSError):
            os.unlink(Path(key) / LOCK_NAME)
        os.close(fd)
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(key)  # only when empty


@contextlib.contextmanager
def run_folder_lock(folder: str | Path, command: str) -> Iterator[None]:
    """Hold ``folder``'s lock for the ``with`` block (see :func:`acquire`)."""
    acquire(folder, command)
    try:
        yield
    finally:
        release(folder)
