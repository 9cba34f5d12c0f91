"""The run folder's identity and what a new command may do with an earlier run in it.

A run is identified by the digest of its scene's content (:meth:`Scene.digest`: every view's
name, camera and image) and its split, both recorded in ``WORK/config.json`` and, through the
report, in ``checkpoint.pt``.

* ``--resume`` continues only a run of the same scene and split, and compares the requested
  configuration with the checkpoint's (:func:`compare_configs`): equal goes on; safe changes
  (more iterations, book-keeping intervals, settings the run's method never reads) are applied
  and logged; any other change is refused with the list of differences unless forced
  (``--force-config``, recorded in the report);
  changes that no checkpoint can follow (the method, the model's shapes) are always refused.
* A fresh run replaces an earlier run's outputs (:data:`RUN_OUTPUTS`) so readers never see a mix
  of two runs; when the earlier run was of another scene, it says so and also drops the caches.
  Only files this project writes are removed, never anything else in the folder.
"""
from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..common.errors import InputError
from ..common.report import Report
from .checkpoint import CHECKPOINT, MODEL
from .config import TrainConfig

log = logging.getLogger("dibrgs.train")

CONFIG = "config.json"
#: Report value holding the digest of the user's pseudo-view path's cameras (:func:`~dibrgs_core.data.load.cameras_digest`).
PSEUDO_PATH_DIGEST = "pseudo_path_sha256"
#: Files and folders one training run writes (its outputs), removed when a fresh run starts.
RUN_OUTPUTS = (CHECKPOINT, MODEL, CONFIG, "report.json", "train.log", "curve.csv", "curve.png", "metrics.json",
               "renders")
#: Caches keyed by their inputs; dropped with another scene's run.
CACHES = ("init", "pseudo")

#: Settings a resumed run may change without changing what it computes.
SAFE_CHANGES = ("checkpoint_every_s", "curve_every_s", "curve_max_views", "progress_every")
#: Sections of the configuration a method never reads (by method): a change there (a new default
#: of the other method's schedule, say) does not change what a resumed run computes.
UNREAD = {"dibrgs": ("gs3d.",)}
#: Settings no checkpoint can follow: its state was built for them.
FIXED = ("method", "model.feat_dim", "model.n_offsets", "model.ibr_channels", "ibr", "dense_init",
         "dino_resnet", "dino_vit")


@dataclass
class Identity:
    """What a run folder says about its run (None when it does not say)."""

    scene: str | None
    digest: str | None
    train: list[str] | None
    test: list[str] | None

    @staticmethod
    def of(values: dict[str, Any]) -> "Identity":
        return Identity(values.get("root") or values.get("scene"), values.get("digest"), values.get("train"),
                        values.get("test"))


def stored_identity(work: Path) -> Identity | None:
    """The identity ``WORK/config.json`` records (None when there is no readable one)."""
    try:
        d = json.loads((work / CONFIG).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(d, dict):
        return None
    run = d.get("run") if isinstance(d.get("run"), dict) else {}
    return Identity(d.get("scene"), run.get("digest"), run.get("train"), run.get("test"))


def has_run(work: Path) -> bool:
    return any((work / name).exists() for name in RUN_OUTPUTS)


def clear(work: Path, caches: bool) -> list[str]:
    """Remove the run outputs (and the caches) from ``work``; returns what was removed."""
    gone = []
    for name in RUN_OUTPUTS + (CACHES if caches else ()):
        p = work / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
        else:
            continue
        gone.append(name)
    return gone


def replace_earlier_run(work: Path, digest: str, split: tuple[list[str], list[str]], what: str) -> None:
    """Before a fresh run (or ``init``) writes into ``work``: an earlier run of another scene is
    reported and replaced with its caches; an earlier run of the same scene loses its outputs
    (``what`` = the command, for the log)."""
    if not has_run(work):
        return
    old = stored_identity(work)
    if old is not None and old.digest is not None and old.digest != digest:
        gone = clear(work, caches=True)
        log.warning("%s held a run of another scene (%s, digest %s); replacing it (removed %s)", work,
                    old.scene, old.digest, ", ".join(gone))
        return
    if what != "train":
        return  # init into the folder of a run of the same scene keeps that run
    gone = clear(work, caches=False)
    if gone:
        same = old is not None and (old.train, old.test) == (list(split[0]), list(split[1]))
        log.info("%s: starting afresh (no --resume); the earlier run's %s replaced%s", work, ", ".join(gone),
                 "" if same or old is None else " (it had another split)")


def check_resumable(ck_path: Path, saved: Identity, digest: str, split: tuple[list[str], list[str]]) -> None:
    """``InputError`` unless the checkpoint's run is of this scene and split."""
    if saved.digest is not None and saved.digest != digest:
        raise InputError(ck_path, f"the run here is of another scene ({saved.scene}, digest {saved.digest}; "
                                  f"asked: digest {digest}); refusing to --resume it: choose another --out, "
                                  "or drop --resume to replace it")
    diffs = []
    if saved.train is not None and list(saved.train) != list(split[0]):
        diffs.append(f"train {saved.train} -> {list(split[0])}")
    if saved.test is not None and list(saved.test) != list(split[1]):
        diffs.append(f"test {saved.test} -> {list(split[1])}")
    if diffs:
        raise InputError(ck_path, "the run here has another split (" + "; ".join(diffs) + "); refusing to "
                                  "--resume it: use its split (--train/--test) or drop --resume to start afresh")


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = list(v) if isinstance(v, tuple) else v
    return out


@dataclass
class ConfigChanges:
    """Differences between a checkpoint's configuration and a requested one, by kind."""

    safe: list[tuple[str, Any, Any]]
    unsafe: list[tuple[str, Any, Any]]
    fixed: list[tuple[str, Any, Any]]

    @staticmethod
    def describe(items: list[tuple[str, Any, Any]], limit: int = 12) -> str:
        parts = [f"{k}: {a!r} -> {b!r}" for k, a, b in items[:limit]]
        if len(items) > limit:
            parts.append(f"... and {len(items) - limit} more")
        return "; ".join(parts)


def _same_cameras(path: str | None, digest: str | None) -> bool:
    """Whether ``path`` holds the cameras whose :func:`~dibrgs_core.data.load.cameras_digest` is ``digest``."""
    from ..data.load import cameras_digest, read_any_cameras

    try:
        return bool(path and digest) and cameras_digest(read_any_cameras(path)) == digest
    except (InputError, OSError):
        return False


def compare_configs(saved: dict[str, Any], requested: dict[str, Any], done: int,
                    same_content: frozenset[str] = frozenset()) -> ConfigChanges:
    """Sort the differences between ``saved`` and ``requested`` (``TrainConfig.to_dict()`` forms);
    ``done`` is the checkpoint's iteration. More iterations are safe; fewer are not, and fewer than
    ``done`` cannot be forced. Keys in ``same_content`` name files whose paths differ but whose
    content is the checkpoint's (a run folder copied or moved), and keys of sections the saved
    run's method never reads (:data:`UNREAD`): safe."""
    a, b = _flat(saved), _flat(requested)
    unread = UNREAD.get(str(saved.get("method")), ())
    safe, unsafe, fixed = [], [], []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if va == vb:
            continue
        item = (k, va, vb)
        if k in FIXED or (k == "iterations" and isinstance(vb, int) and vb < done):
            fixed.append(item)
        elif k in SAFE_CHANGES or k in same_content or k.startswith(unread) or (
                k == "iterations" and isinstance(vb, int) and vb >= max(int(va), done)):
            safe.append(item)
        else:
            unsafe.append(item)
    return ConfigChanges(safe, unsafe, fixed)


def resumed_config(ck_path: Path, ckpt: dict[str, Any], requested: TrainConfig, force: bool,
                   report: Report) -> TrainConfig:
    """The configuration a resumed run continues with: ``requested`` when it differs from the
    checkpoint's only in safe ways (or ``force``); else ``InputError`` listing the differences.
    The changes go into ``report`` (``resume_changes``; forced ones, with earlier legs', ``forced_config``)."""
    saved = TrainConfig.from_dict(ckpt["config"])
    done = int(ckpt["iteration"])
    values = ckpt["report"].get("values", {})
    same = frozenset({"pseudo_path"}) if _same_cameras(requested.pseudo_path, values.get(PSEUDO_PATH_DIGEST)) \
        else frozenset()
    ch = compare_configs(saved.to_dict(), requested.to_dict(), done, same)
    if ch.fixed:
        raise InputError(ck_path, f"cannot resume with {ConfigChanges.describe(ch.fixed)}: the checkpoint "
                                  f"(iteration {done}) was built for its own; drop --resume to start afresh")
    if ch.unsafe and not force:
        raise InputError(ck_path, "--resume asks for another configuration than the checkpoint's ("
                                  f"{ConfigChanges.describe(ch.unsafe)}); give the run's own options, "
                                  "--force-config to accept the changes, or drop --resume to start afresh")
    vals = report.values
    vals["resumed_from"] = done
    if ch.safe:
        log.info("resuming with changed %s", ConfigChanges.describe(ch.safe))
        vals["resume_changes"] = [list(x) for x in ch.safe]
    forced = list(ckpt["report"].get("values", {}).get("forced_config", []))
    if ch.unsafe:
        log.warning("--force-config: resuming iteration %d with %s", done, ConfigChanges.describe(ch.unsafe))
        forced.append({"iteration": done, "changes": [list(x) for x in ch.unsafe]})
    if forced:
        vals["forced_config"] = forced
    log.info("resuming %s from iteration %d", ck_path, done)
    return requested
