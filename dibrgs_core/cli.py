"""The ``dibrgs`` command. Each sub-command lives in ``dibrgs_core/commands/<name>.py``
and exposes ``register(subparsers)``; those modules import torch lazily so
``dibrgs --help`` and ``dibrgs info`` stay fast.

Every error a user can act on ends the command with one line on stderr naming the file or
option and what to do, and a non-zero exit (:mod:`dibrgs_core.common.errors`: 2 bad input or
option, 1 the operating system refused, 75 the run folder is busy, 130 interrupted, 143
terminated by SIGTERM outside training, which checkpoints and stops instead); a bug gives one line
too, and ``--debug`` shows the traceback of either.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
import traceback

from .common.allocator import keep_freed_memory
from .common.errors import EXIT_INPUT, EXIT_TERMINATED, Terminated, explain, exit_code
from .common.openmp import set_wait_policy

COMMANDS = ["demo", "info", "init", "train", "eval", "render", "export", "check"]


class Parser(argparse.ArgumentParser):
    """argparse with a one-line error: ``dibrgs train: error: argument --x: ... (see --help)``."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(EXIT_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="dibrgs", description="DIBR-GS: sparse-view novel view synthesis "
               "for remote-sensing scenes with neural Gaussians.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = p.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f".commands.{name}", __package__).register(sub)
    for sp in sub.choices.values():  # also after the command: dibrgs train ... --debug
        sp.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show the traceback of an error")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if "torch" not in sys.modules:  # libgomp reads its wait policy once, when torch loads it
        set_wait_policy()
    keep_freed_memory()
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    with _sigterm_raises():
        try:
            rc = args.func(args)
        except KeyboardInterrupt:
            print(f"dibrgs {args.command}: interrupted", file=sys.stderr)
            return 130
        except Terminated:
            print(f"dibrgs {args.command}: terminated (SIGTERM)", file=sys.stderr)
            return EXIT_TERMINATED
        except BrokenPipeError:  # `dibrgs info ... | head`: the reader left, nothing to report
            with contextlib.suppress(OSError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 141
        except Exception as e:  # the one path from an exception to a message
            return report_error(f"dibrgs {args.command}", e, args.debug)
    return int(rc or 0)


@contextlib.contextmanager
def _sigterm_raises():
    """While inside, SIGTERM raises :class:`Terminated` in the main thread (as Ctrl-C raises
    KeyboardInterrupt); the previous handler afterwards (``main`` may be called in-process)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum: int, frame: object) -> None:
        raise Terminated()

    old = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old if old is not None else signal.SIG_DFL)


def report_error(prefix: str, exc: BaseException, debug: bool = False) -> int:
    """Print ``exc`` as one line (with its traceback first under ``debug``); returns the exit code."""
    if debug:
        traceback.print_exception(exc, file=sys.stderr)
    msg = explain(exc)
    if msg is None:
        msg = f"internal error: {type(exc).__name__}: {exc}" + ("" if debug else " (run with --debug for the traceback)")
    print(f"{prefix}: error: {msg}", file=sys.stderr)
    return exit_code(exc)


if __name__ == "__main__":
    sys.exit(main())
