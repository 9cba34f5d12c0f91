"""The ``dibrgs`` command. Each sub-command lives in ``dibrgs_core/commands/<name>.py``
and exposes ``register(subparsers)``; those modules import torch lazily so
``dibrgs --help`` and ``dibrgs info`` stay fast.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

# OpenMP threads that spin while waiting make torch 3-4x slower on a shared
# 2-core machine; must be set before torch is first imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .errors import InputError

COMMANDS = ["demo", "info", "init", "train", "eval", "render", "export", "check"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dibrgs", description="DIBR-GS: sparse-view novel view synthesis "
                                "for remote-sensing scenes with neural Gaussians.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f".commands.{name}", __package__)
        except ModuleNotFoundError as e:
            if e.name == f"{__package__}.commands.{name}":
                continue  # command not built yet
            raise
        mod.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        rc = args.func(args)
    except InputError as e:
        print(f"dibrgs {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dibrgs {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
