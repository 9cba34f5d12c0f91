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
    """``torch.save`` to a temporary name, then rename (readers never see half a file)."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def save_model(path: Path, method: TrainingMethod, cfg: TrainConfig, scene_root: Path,
               train_cameras: list[Camera]) -> Path:
    """Write ``model.pt`` for a trained method."""
    save_torch(path, {"method": cfg.method, "config": cfg.to_dict(), "scene": str(scene_root.resolve()),
                      **method.model.state(), **method.model_file_extras(),
                      "train_cameras": [camera_to_dict(c) for c in train_cameras]})
    return path


@dataclass
class StoredModel:
    """A trained model read back: the model (ready to render), its run configuration, the scene
    folder it was trained on and its training cameras."""

    model: GaussianModel
    cfg: TrainConfig
    scene: str
    train_cameras: list[Camera]


def load_model(work: str | Path) -> StoredModel:
    """Read ``WORK/model.pt`` (``InputError`` naming the file when it is missing or unreadable)."""
    path = Path(work) / MODEL
    if not path.exists():
        raise InputError(path, "no trained model here; run `dibrgs train` to completion first "
                               "(an interrupted run continues with `dibrgs train ... --resume`)")
    try:
        st = torch.load(path, map_location="cpu", weights_only=False)
        cfg = TrainConfig.from_dict(st["config"])
        model = model_from_state(st["method"], st, cfg.model)
    except Exception as e:  # a corrupt or foreign file
        raise InputError(path, f"cannot read the trained model ({e})") from None
    if st.get("ibr_feats") is not None:
        model.set_ibr(st["ibr_feats"])
    model.eval()
    cams = [camera_from_dict(d, str(path)) for d in st["train_cameras"]]
    return StoredModel(model, cfg, st["scene"], cams)
