"""``dibrgs check``: is this Python ready to train? Imports every runtime dependency and
builds the C++ rasterizer (the first time about 2 minutes; cached afterwards, shared by the
command line and Blender), then reports each item as OK or what is missing and the command
that fixes it. Exit code 0 when everything required is there, 1 otherwise.

``--json`` prints one JSON object per line instead (the Blender add-on's "Set up / Check"
reads them): ``{"check": NAME, "ok", "required", "detail", "fix", "note", "index", "total"}``
per item, ``{"stage": ...}`` before the rasterizer build and finally ``{"result": {"ok",
"missing", "fix"}}``.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import shlex
import shutil
import sys
import time
from dataclasses import dataclass

PYTHON_VERSION = (3, 11)
COMPILER_FIX = ("install a C++ compiler (Debian/Ubuntu: sudo apt install g++; Fedora: sudo dnf install gcc-c++; "
                "macOS: xcode-select --install); or train on the torch path, about 100x slower: --rasterizer reference "
                "(DIBRGS_RASTERIZER=reference)")


@dataclass(frozen=True)
class Dependency:
    """A module the training interpreter imports, the pip requirement that provides it, what it is for."""

    module: str
    requirement: str
    purpose: str
    required: bool = True


#: Every runtime dependency of pyproject.toml (tests check they agree), torch first: it is the slowest.
DEPENDENCIES = (
    Dependency("torch", "torch==2.13.0", "training and rendering"),
    Dependency("numpy", "numpy", "everything"),
    Dependency("scipy", "scipy", "geometry (KD-trees, filters)"),
    Dependency("PIL", "pillow", "reading and writing images"),
    Dependency("pycolmap", "pycolmap", "SfM with known poses, COLMAP scenes"),
    Dependency("tifffile", "tifffile", "depth maps (.tiff)"),
    Dependency("OpenEXR", "OpenEXR", "depth maps (.exr)"),
    Dependency("trimesh", "trimesh", "point clouds (.ply)"),
    Dependency("skimage", "scikit-image", "SSIM"),
    Dependency("diptest", "diptest", "the dip test of the geometry stage"),
    Dependency("tqdm", "tqdm", "progress bars"),
    Dependency("threadpoolctl", "threadpoolctl", "numpy's BLAS on one thread (without it: slower pseudo views)",
               required=False),
    Dependency("matplotlib", "matplotlib", "curve plots"),
    Dependency("ninja", "ninja", "building the C++ rasterizer"),
    Dependency("transformers", "transformers", "Depth Anything V2 with local weights (optional)", required=False),
    Dependency("bpy", "bpy==5.0.1", "generated scenes and `dibrgs demo` (optional)", required=False),
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="check that this Python can train; build the rasterizer",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", action="store_true", help="JSON lines on stdout (for the Blender add-on)")
    p.add_argument("--no-build", action="store_true", help="do not build the C++ rasterizer")
    p.set_defaults(func=run)


def pip_fix(requirements: list[str]) -> str:
    return f"{shlex.quote(sys.executable)} -m pip install " + " ".join(shlex.quote(r) for r in requirements)


def _import(dep: Dependency) -> dict:
    if dep.module == "bpy":  # importing bpy starts Blender: only look for it
        from importlib.util import find_spec

        found = find_spec("bpy") is not None
        return {"ok": found, "detail": "installed" if found else "not installed"}
    t0 = time.perf_counter()
    try:
        mod = importlib.import_module(dep.module)
    except Exception as e:  # ImportError, or a broken install raising anything
        return {"ok": False, "detail": f"{type(e).__name__}: {e}".splitlines()[0][:300]}
    version = getattr(mod, "__version__", None) or getattr(mod, "VERSION", None) or ""
    out = {"ok": True, "detail": f"{version} ({time.perf_counter() - t0:.1f} s)".strip()}
    pin = dep.requirement.partition("==")[2]
    if pin and str(version).split("+")[0] != pin:
        out["note"] = f"version {version}; the project pins {pin}"
    return out


def _compiler() -> dict:
    cxx = os.environ.get("CXX") or next((c for c in ("c++", "g++", "clang++") if shutil.which(c)), None)
    if cxx and shutil.which(cxx):
        return {"ok": True, "detail": shutil.which(cxx)}
    return {"ok": False, "detail": "no C++ compiler on PATH", "fix": COMPILER_FIX}


def _rasterizer(emit) -> dict:
    from ..render import fast

    is_built = getattr(fast, "is_built", None)
    if is_built is None:  # a library without the build cache query: say both
        emit({"stage": "loading the rasterizer (compiled on first use, about 2 minutes)"})
    elif not is_built():
        emit({"stage": "compiling the rasterizer (first run, about 2 minutes)"})
    t0 = time.perf_counter()
    try:
        fast.available(required=True)
    except RuntimeError as e:
        return {"ok": False, "detail": str(e).splitlines()[0][:300], "fix": COMPILER_FIX}
    return {"ok": True, "detail": f"ready ({time.perf_counter() - t0:.0f} s)"}


def _python() -> dict:
    out = {"ok": True, "detail": f"{sys.version.split()[0]} ({sys.executable})"}
    if sys.version_info[:2] != PYTHON_VERSION:
        out["note"] = "the project is tested with Python %d.%d" % PYTHON_VERSION
    return out


def _core() -> dict:
    import dibrgs_core

    return {"ok": True, "detail": os.path.dirname(dibrgs_core.__file__)}


def run(args: argparse.Namespace) -> int:
    def emit(obj: dict) -> None:
        if args.json:
            print(json.dumps(obj), flush=True)
        elif "stage" in obj:
            print(f"... {obj['stage']}", flush=True)

    deps = {d.module: d for d in DEPENDENCIES}
    missing: list[str] = []
    # (name, required, check) in the order they run; the rasterizer needs torch.
    items = [("python", True, _python), ("dibrgs_core", True, _core)]
    items += [(d.module, d.required, lambda d=d: _import(d)) for d in DEPENDENCIES]
    items.append(("c++ compiler", True, _compiler))
    if not args.no_build:
        items.append(("rasterizer", True, lambda: _rasterizer(emit) if "torch" not in missing
                      else {"ok": False, "detail": "needs torch"}))
    failed_required = False
    for k, (name, required, fn) in enumerate(items):
        res = fn()
        if not res["ok"] and name in deps:
            missing.append(name)
            res.setdefault("fix", pip_fix([deps[name].requirement]))
        failed_required |= required and not res["ok"]
        item = {"check": name, "ok": res["ok"], "required": required, "detail": res.get("detail", ""),
                "fix": res.get("fix"), "note": res.get("note"), "index": k + 1, "total": len(items)}
        if args.json:
            emit(item)
        else:
            status = "OK" if res["ok"] else ("MISSING" if required else "optional")
            print(f"  {status:8s} {name}: {item['detail']}", flush=True)
            for key in ("note", "fix"):
                if item[key] and (key == "note" or not res["ok"]):
                    print(f"           {key}: {item[key]}", flush=True)
    needed = [deps[m].requirement for m in missing if deps[m].required]
    result = {"ok": not failed_required, "missing": missing, "fix": pip_fix(needed) if needed else None}
    if args.json:
        emit({"result": result})
    else:
        print("ready to train" if result["ok"] else
              "not ready" + (f"; install the missing packages with:\n  {result['fix']}" if result["fix"] else ""))
    return 0 if result["ok"] else 1
