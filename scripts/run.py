"""Batch mode of the DIBR-GS Blender add-on from a checkout: import, initialise, path, train, results; save a .blend.

    blender -b -P scripts/run.py -- --scene DIR --out DIR [training options]
    python scripts/run.py --scene DIR --out DIR [training options]      # with the bpy module

The batch itself ships inside the extension (``addon/batch.py``); an
installed extension runs it as ``blender -b -c dibrgs --scene DIR --out DIR``.
Exit codes: 0 success, 1 a step failed, 2 bad arguments, 130 interrupted
(SIGINT/SIGTERM: the running step is stopped, the checkpoint kept).
"""
from __future__ import annotations

import signal
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def script_argv() -> list[str]:
    """Arguments meant for this script: after ``--`` inside Blender, else all of them."""
    if "--" in sys.argv:
        return sys.argv[sys.argv.index("--") + 1:]
    return sys.argv[1:] if not Path(sys.argv[0]).name.lower().startswith("blender") else []


def _interrupted_early(signum, _frame) -> None:
    print(f"run.py: interrupted by {signal.Signals(signum).name} before it started", file=sys.stderr)
    sys.exit(130)


def main(argv: list[str]) -> int:
    for s in (signal.SIGINT, signal.SIGTERM):  # the batch installs its own once it runs
        signal.signal(s, _interrupted_early)
    import bpy

    sys.path.insert(0, str(REPO))
    import addon  # top-level package: uses the checkout's dibrgs_core (see addon/_core.py)
    from addon import batch

    bpy.ops.wm.read_factory_settings(use_empty=True)  # no installed copy of the add-on registered beside it
    addon.register()
    try:
        return batch.main(argv, prog="run.py")
    finally:
        addon.unregister()


if __name__ == "__main__":
    sys.exit(main(script_argv()))
