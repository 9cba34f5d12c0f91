"""Stage decisions: every stage says whether it applies to the scene, and why.

Decisions are logged as they are made and saved in a JSON report, so a user
can see what was left out of a run and for which reason.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .fileio import write_json

log = logging.getLogger("dibrgs")


@dataclass
class Decision:
    stage: str
    step: str
    applied: bool
    reason: str
    details: dict[str, Any] = field(default_factory=dict)


@dataclass
class Report:
    """Collects decisions and measurements of one command."""

    decisions: list[Decision] = field(default_factory=list)
    values: dict[str, Any] = field(default_factory=dict)

    def decide(self, stage: str, step: str, applied: bool, reason: str, **details: Any) -> bool:
        """Record (and log) whether ``step`` of ``stage`` runs; returns ``applied``."""
        self.decisions.append(Decision(stage, step, bool(applied), reason, details))
        log.info("[%s] %s: %s (%s)", stage, step, "applied" if applied else "skipped", reason)
        return bool(applied)

    def applied(self, step: str) -> bool | None:
        for d in reversed(self.decisions):
            if d.step == step:
                return d.applied
        return None

    def to_dict(self) -> dict[str, Any]:
        return {"decisions": [asdict(d) for d in self.decisions], "values": self.values}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "Report":
        """The report :meth:`to_dict` (or a saved report file) describes."""
        return Report([Decision(**x) for x in d.get("decisions", [])], dict(d.get("values", {})))

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_dict())
