"""The one place that maps a method name to its model class (for loading stored models)."""
from __future__ import annotations

from typing import Any

from .base import GaussianModel
from .config import ModelConfig
from .gs3d import Gaussians3D
from .scaffold import NeuralGaussians

MODELS: dict[str, type] = {cls.kind: cls for cls in (NeuralGaussians, Gaussians3D)}


def model_from_state(kind: str, state: dict[str, Any], cfg: ModelConfig) -> GaussianModel:
    """Rebuild a model of method ``kind`` from its ``state()`` (``ValueError`` for an unknown kind)."""
    try:
        cls = MODELS[kind]
    except KeyError:
        raise ValueError(f"unknown model kind {kind!r}; expected one of {', '.join(MODELS)}") from None
    return cls.from_state(state, cfg)
