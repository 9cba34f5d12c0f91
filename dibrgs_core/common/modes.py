"""Every mode a user can choose, each written once as a ``Literal`` type (standard library only:
the Blender add-on and the command line read these without torch).

``choices(T)`` gives the allowed values of a mode type, for argument parsers and checks.
"""
from __future__ import annotations

from typing import Literal, get_args

#: Named training presets (:func:`dibrgs_core.training.config.preset`).
PresetName = Literal["paper", "cpu", "test"]
#: Training methods: the paper's, and vanilla 3DGS as the baseline.
MethodName = Literal["dibrgs", "3dgs"]
#: A stage that decides from the scene (``auto``) or is forced on or off.
Switch = Literal["auto", "on", "off"]
#: IBR encoders: ``auto`` = ``dino`` with both DINO weight files, else ``pyramid``.
IbrEncoder = Literal["auto", "dino", "pyramid", "none"]
#: Dense depth priors: ``auto`` = Depth Anything V2 with a local model, else ``mvs``; ``gt`` = oracle.
DepthPrior = Literal["auto", "mvs", "depth-anything-v2", "gt"]
#: Disparity-to-depth map of a monocular prior before alignment (``inv`` = 1/disparity, the paper's).
DepthMap = Literal["inv", "neg"]
#: Dense-cloud refinement (the paper's "Refine" column): ``no-ovlp`` is the paper's.
Refine = Literal["no-ovlp", "reproject", "none"]
#: Plane family of the plane sweep: horizontal ``height`` planes, ``fronto``-parallel, or ``auto``.
SweepPlanes = Literal["auto", "height", "fronto"]
#: Kinds of generated scenes.
SceneKind = Literal["city", "mountain", "village", "stadium"]


def choices(mode: object) -> tuple[str, ...]:
    """The values a ``Literal`` mode type allows."""
    return get_args(mode)
