"""User-facing errors and the one place that turns any of them into a one-line message.

* :class:`InputError` - bad input (a scene file, an option value, a run folder): names the path
  or option and what is wrong;
* :class:`RunFolderBusy` - another process writes into the run folder (see :mod:`.lock`);
* ``OSError`` from the operating system (permission, no space, read-only file system, not a
  directory, is a directory, ...) - :func:`explain` names the path and says what to do.

The ``dibrgs`` command, ``scripts/run.py`` and the Blender add-on print :func:`explain`'s line and
exit with :func:`exit_code`; tracebacks only with ``--debug``. Standard library only (Blender).
"""
from __future__ import annotations

import errno
from pathlib import Path

#: Exit codes of the ``dibrgs`` command.
EXIT_INPUT = 2      # bad input or option (InputError)
EXIT_OS = 1         # the operating system refused (OSError) or an internal error
EXIT_BUSY = 75      # the run folder is in use by another process (EX_TEMPFAIL: try again later)
EXIT_TERMINATED = 143  # SIGTERM outside training's checkpointing stop (128 + 15, as the shell reports it)


class InputError(Exception):
    """Bad input: names the offending file (or option, with ``path=None``) and what is wrong with it."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class Terminated(BaseException):
    """SIGTERM arrived (a scheduler's time limit, ``timeout``, ``kill``): unwinds like Ctrl-C, so
    temporary files are removed and locks released; not an ``Exception``, so nothing catches it
    as an error."""


class RunFolderBusy(InputError):
    """Another live process holds the run folder's lock; the message names it (pid, host, command)."""


# errno -> (what happened, what to do); the path comes from the exception.
_OS_ADVICE: dict[int, tuple[str, str]] = {
    errno.EACCES: ("permission denied", "choose a folder you can write (or read), or change its permissions"),
    errno.EPERM: ("operation not permitted", "choose a folder you own, or change its permissions"),
    errno.ENOSPC: ("no space left on the device", "free some space or choose a folder on another disk"),
    errno.EDQUOT: ("disk quota exceeded", "free some space or choose a folder on another disk"),
    errno.EFBIG: ("file too large for this file system or limit", "choose a folder on another file system"),
    errno.EROFS: ("read-only file system", "choose a folder on a writable file system"),
    errno.ENOTDIR: ("a part of this path is a file, not a folder", "give a path whose parents are folders"),
    errno.EISDIR: ("is a folder, not a file", "give a file name"),
    errno.EEXIST: ("already exists and is not a folder", "give a folder, or remove that file"),
    errno.ENOENT: ("no such file or folder", "check the path"),
    errno.ENAMETOOLONG: ("file name too long", "choose a shorter path"),
    errno.ELOOP: ("too many levels of symbolic links", "fix the symbolic links on this path"),
    errno.EMFILE: ("too many open files", "raise the open-file limit (ulimit -n)"),
    errno.ENXIO: ("no such device", "give a regular file"),
    errno.EIO: ("input/output error", "check the disk"),
}


def explain(exc: BaseException) -> str | None:
    """One line for an error a user can act on, or None for an internal error (a bug).

    ``InputError`` (and an exception class marked ``user_error = True``, such as the
    rasterizer's ``BuildError``) gives its own message; an ``OSError`` names its path(s), what happened
    and what to do.
    """
    if isinstance(exc, InputError) or getattr(exc, "user_error", False):
        return str(exc)
    if isinstance(exc, OSError):
        what, todo = _OS_ADVICE.get(exc.errno or -1, (exc.strerror or type(exc).__name__, ""))
        where = exc.filename if exc.filename is not None else None
        if where is not None and getattr(exc, "filename2", None):
            where = f"{where} -> {exc.filename2}"
        line = f"{where}: {what}" if where is not None else what
        return line + (f"; {todo}" if todo else "")
    if isinstance(exc, MemoryError):
        return "out of memory; use a smaller --resolution-scale or a lighter --preset"
    return None


def exit_code(exc: BaseException) -> int:
    """The exit status for ``exc`` (see the ``EXIT_*`` constants)."""
    if isinstance(exc, RunFolderBusy):
        return EXIT_BUSY
    if isinstance(exc, InputError):
        return EXIT_INPUT
    return EXIT_OS
