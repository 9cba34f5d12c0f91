"""Progress of a ``dibrgs train --progress-json`` run, as the add-on shows it.

The training prints one JSON object per line on stdout:
``{"iteration", "total", "loss", "eta_s", "elapsed_s"}`` while it runs and
``{"done": true, "work": ...}`` at the end. Any other line (a log line that
slipped onto stdout) is not progress and is ignored here.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any


def parse_progress_line(line: str) -> dict[str, Any] | None:
    """The JSON object on a progress line, or None for any other line."""
    s = line.strip()
    if not (s.startswith("{") and s.endswith("}")):
        return None
    try:
        obj = json.loads(s)
    except ValueError:
        return None
    return obj if isinstance(obj, dict) else None


def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def format_duration(seconds: float | None) -> str:
    """``h:mm:ss`` or ``m:ss``; ``--:--`` when unknown (None, NaN, negative)."""
    s = _finite(seconds)
    if s is None or s < 0:
        return "--:--"
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


@dataclass
class Progress:
    """Latest known state of a training run (all times in seconds)."""

    iteration: int = 0
    total: int = 0
    loss: float | None = None
    eta_s: float | None = None
    elapsed_s: float | None = None
    done: bool = False
    work: str | None = None

    def update(self, event: dict[str, Any]) -> None:
        """Fold one progress event in; unknown or malformed fields are ignored."""
        if event.get("done"):
            self.done = True
            self.work = str(event["work"]) if event.get("work") is not None else self.work
            if self.total:
                self.iteration = self.total
            self.eta_s = 0.0
            return
        it, tot = _finite(event.get("iteration")), _finite(event.get("total"))
        if it is not None:
            self.iteration = max(0, int(it))
        if tot is not None and tot > 0:
            self.total = int(tot)
        for key in ("loss", "eta_s", "elapsed_s"):
            if key in event:
                setattr(self, key, _finite(event[key]))

    @property
    def fraction(self) -> float:
        """Completed fraction in [0, 1] (1 once done)."""
        if self.done:
            return 1.0
        if self.total <= 0:
            return 0.0
        return min(max(self.iteration / self.total, 0.0), 1.0)

    def text(self) -> str:
        """One line for the panel, e.g. ``it 120/300  loss 0.0412  ETA 0:42``."""
        if self.done:
            return "done"
        parts = [f"it {self.iteration}/{self.total or '?'}"]
        if self.loss is not None:
            parts.append(f"loss {self.loss:.4g}")
        parts.append(f"ETA {format_duration(self.eta_s)}")
        return "  ".join(parts)
