"""Model configuration (standard library only, so presets load without torch)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ModelConfig:
    """Neural Gaussian model (Scaffold-GS anchors + IBR fusion)."""

    feat_dim: int = 32
    n_offsets: int = 10
    # Anchor voxel in the paper's (LEVIR-NVS) units; converted with the scene's
    # scale (scene units per paper unit, as in init.py).
    anchor_voxel: float = 0.03
    # Budget on initial anchors (None = no budget). When the voxelised cloud has
    # more anchors, the voxel grows by this factor until it fits; the report says so.
    max_init_anchors: int | None = None
    anchor_voxel_growth: float = 2.0
    # IBR fusion: channels of the reference feature (C_r) and initial gate bias
    # (sigmoid(-5) = 0.007, "initialised to produce small values").
    ibr_channels: int = 32
    gate_bias_init: float = -5.0
