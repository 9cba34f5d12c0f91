"""The run folder's two torch files.

* ``checkpoint.pt``: everything needed to continue bit for bit (method state with model,
  optimisers and strategy statistics, RNG states, view orders, iteration, training
  clock, curve), written atomically every ``checkpoint_every_s`` seconds, on SIGINT /
  SIGTERM and at the end;
* ``model.pt``: the trained model for ``eval`` / ``render`` / ``export``: the method name,
  its configuration, the scene path, the training cameras, ``model.state()`` and the
  method's extras (DIBR-GS: the per-anchor IBR features, frozen, so rendering needs no
  encoder).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..camera.pinhole import Camera
from ..camera.serialize import camera_from_dict, camera_to_dict
from ..common.errors import InputError
from ..common.fileio import atomic_path
from ..models.base import GaussianModel
from ..models.factory import model_from_state
from .config import TrainConfig
from .methods import TrainingMethod

CHECKPOINT = "checkpoint.pt"
MODEL = "model.pt"


def save_torch(path: Path, obj: dict[str, Any]) -> None:
    """``torch.save`` to a temporary name, then rename (readers never see half a file). A failed
    write (a full disk) is the operating system's ``OSError``, not torch's bare RuntimeError."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            out = _Writes(f)
            try:
                torch.save(obj, out)
            except RuntimeError:
                if out.error is not None:
                    raise out.error from None
                raise


class _Writes:
    """A file's ``write`` that keeps the ``OSError`` it raised (torch's writer turns it into a RuntimeError)."""

    def __init__(self, f: Any) -> None:
        self.f = f
        self.error: OSError | None = None

    def write(self, b: Any) -> int:
        try:
            return self.f.write(b)
        except OSError as e:
            self.error = e
            raise

    def flush(self) -> None:
        self.f.flush()


def save_model(path: Path, method: TrainingMethod, cfg: TrainConfig, scene_root: Path,
               train_cameras: list[Camera], origin: np.ndarray | None = None) -> Path:
    """Write ``model.pt`` for a trained method (``origin``: the scene's ``Scene.origin``, from which
    the model's positions and ``train_cameras`` are expressed)."""
    save_torch(path, {"method": cfg.method, "config": cfg.to_dict(), "scene": str(scene_root.resolve()),
                      **method.model.state(), **method.model_file_extras(),
                      "train_cameras": [camera_to_dict(c) for c in train_cameras],
                      "scene_origin": [0.0, 0.0, 0.0] if origin is None else [float(v) for v in origin]})
    return path


@dataclass
class StoredModel:
    """A trained model read back: the model (ready to render), its run configuration, the scene
    folder it was trained on and its training cameras."""

    model: GaussianModel
    cfg: TrainConfig
    scene: str
    train_cameras: list[Camera]
    origin: np.ndarray  # the scene's Scene.origin (zeros for model files from before it was stored)


def _read(path: Path, what: str, todo: str) -> dict[str, Any]:
    """``torch.load`` of a run file; ``InputError`` naming it when it is empty, truncated or not ours."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputError(path, f"{what} not found") from None
    if size == 0:
        raise InputError(path, f"{what} is empty (0 bytes); {todo}")
    try:
        st = torch.load(path, map_location="cpu", weights_only=False)
    except OSError:
        raise
    except Exception as e:  # torch raises many types for truncated or foreign files
        first = (str(e).splitlines() or [""])[0][:200]  # some carry no message (a MemoryError)
        raise InputError(path, f"unreadable {what} ({type(e).__name__}{': ' + first if first else ''}); "
                               f"{todo}") from None
    if not isinstance(st, dict):
        raise InputError(path, f"not a DIBR-GS {what} (a {type(st).__name__}); {todo}")
    return st


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read ``checkpoint.pt`` for ``--resume`` (``InputError`` naming it when it cannot be used)."""
    path = Path(path)
    todo = "delete it to start afresh (drop --resume), or restore a good copy"
    ck = _read(path, "checkpoint", todo)
    missing = [k for k in ("iteration", "config", "method", "rng", "report") if k not in ck]
    if missing:
        raise InputError(path, f"not a DIBR-GS checkpoint (no {', '.join(missing)}); {todo}")
    if not isinstance(ck["iteration"], int) or isinstance(ck["iteration"], bool) or ck["iteration"] < 0:
        raise InputError(path, f"checkpoint iteration {ck['iteration']!r} is not a count of iterations; {todo}")
    try:
        TrainConfig.from_dict(ck["config"])
    except (ValueError, TypeError) as e:
        raise InputError(path, f"checkpoint configuration unreadable ({e}); {todo}") from None
    return ck


def load_model(work: str | Path) -> StoredModel:
    """Read ``WORK/model.pt`` (``InputError`` naming the file when it is missing or unreadable)."""
    path = Path(work) / MODEL
    if not path.exists():
        raise InputError(path, "no trained model here; run `dibrgs train` to completion first "
                               "(an interrupted run continues with `dibrgs train ... --resume`)")
    todo = "train again (dibrgs train), or restore a good copy"
    st = _read(path, "trained model", todo)
    try:
        cfg = TrainConfig.from_dict(st["config"])
        model = model_from_state(st["method"], st, cfg.model)
        if st.get("ibr_feats") is not None:
            model.set_ibr(st["ibr_feats"])
        cams = [camera_from_dict(d, str(path)) for d in st["train_cameras"]]
        scene = str(st["scene"])
        origin = np.asarray(st.get("scene_origin", (0.0, 0.0, 0.0)), np.float64).reshape(3)
    except Exception as e:  # a foreign or damaged file
        raise InputError(path, f"cannot read the trained model ({type(e).__name__}: {e}); {todo}") from None
    model.eval()
    return StoredModel(model, cfg, scene, cams, origin)
