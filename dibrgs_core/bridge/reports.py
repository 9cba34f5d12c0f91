"""Reading a run's JSON outputs for display: stage decisions and summary metrics."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from ..common.errors import InputError


def read_json(path: str | Path) -> Any:
    """Parsed JSON; InputError naming the file when it is missing or malformed."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except (OSError, ValueError) as e:
        raise InputError(path, f"not readable JSON ({e})") from None


def decisions(report: dict[str, Any]) -> list[dict[str, Any]]:
    """``report.json`` decisions as ``{"stage", "step", "applied", "reason"}`` dicts, in order."""
    out = []
    for d in report.get("decisions", []) if isinstance(report, dict) else []:
        if isinstance(d, dict) and "step" in d:
            out.append({"stage": str(d.get("stage", "")), "step": str(d["step"]),
                        "applied": bool(d.get("applied", False)), "reason": str(d.get("reason", ""))})
    return out


def scene_origin(report: dict[str, Any]) -> tuple[float, float, float]:
    """Where a run's positions have their (0, 0, 0) in the world frame of the scene's files
    (``scene_origin`` of ``init_report.json`` / ``report.json``; the origin itself when absent)."""
    v = report.get("values", {}).get("scene_origin") if isinstance(report, dict) else None
    try:
        o = tuple(float(x) for x in v)
    except (TypeError, ValueError):
        return (0.0, 0.0, 0.0)
    return o if len(o) == 3 and all(math.isfinite(x) for x in o) else (0.0, 0.0, 0.0)


def summary_metrics(metrics: Any, prefix: str = "", depth: int = 2) -> dict[str, float]:
    """Finite scalar metrics of ``metrics.json``: top-level numbers and numbers in nested dicts.

    Nested keys are joined with ``/`` (``{"mean": {"psnr": 25}}`` -> ``mean/psnr``); lists (per-view
    values) are left out. Non-finite values (e.g. LPIPS unavailable as NaN) are skipped.
    """
    out: dict[str, float] = {}
    if not isinstance(metrics, dict) or depth < 1:
        return out
    for k, v in metrics.items():
        key = f"{prefix}{k}"
        if isinstance(v, bool):
            continue
        if isinstance(v, (int, float)):
            if math.isfinite(float(v)):
                out[key] = float(v)
        elif isinstance(v, dict):
            out.update(summary_metrics(v, key + "/", depth - 1))
    return out
