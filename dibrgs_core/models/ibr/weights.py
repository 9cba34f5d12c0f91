"""Loading backbone checkpoints from local files (nothing is downloaded), with strict key and
shape checks and an :class:`~dibrgs_core.common.errors.InputError` naming a bad file."""
from __future__ import annotations

import logging
from pathlib import Path

import torch
import torch.nn as nn

from ...common.errors import InputError

log = logging.getLogger("dibrgs.ibr_features")


def _unwrap(obj: object) -> object:
    """Accept a bare state dict or DINO's training checkpoints ({'teacher': ...})."""
    if isinstance(obj, dict):
        for key in ("teacher", "state_dict", "model"):
            if key in obj and isinstance(obj[key], dict):
                return obj[key]
    return obj


def load_backbone_weights(module: nn.Module, path: str | Path, what: str) -> None:
    """Load a checkpoint into ``module`` with strict key and shape matching.

    Prefixes ``module.`` and ``backbone.`` (DINO training checkpoints) are
    stripped and classifier/projection heads (``fc.*``, ``head.*``) dropped, as
    neither is used. BatchNorm ``num_batches_tracked`` counters may be absent
    (unused in eval mode). Anything else that does not match raises
    :class:`InputError` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, f"{what} weights not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for corrupt files
        raise InputError(path, f"cannot read {what} weights as a torch checkpoint ({e})") from None
    sd = _unwrap(obj)
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise InputError(path, f"{what} weights: expected a state dict of tensors")
    clean: dict[str, torch.Tensor] = {}
    for k, v in sd.items():
        for pre in ("module.", "backbone."):
            if k.startswith(pre):
                k = k[len(pre):]
        if k.startswith(("fc.", "head.")):
            continue
        clean[k] = v
    own = module.state_dict()
    missing = sorted(k for k in own if k not in clean and not k.endswith("num_batches_tracked"))
    unexpected = sorted(k for k in clean if k not in own)
    bad_shape = sorted(k for k in clean if k in own and tuple(clean[k].shape) != tuple(own[k].shape))
    if missing or unexpected or bad_shape:
        parts = []
        for name, keys in (("missing keys", missing), ("unexpected keys", unexpected),
                           ("shape mismatches", bad_shape)):
            if keys:
                parts.append(f"{len(keys)} {name} (e.g. {', '.join(keys[:4])})")
        raise InputError(path, f"not a {what} checkpoint: " + "; ".join(parts))
    module.load_state_dict(clean, strict=False)
    log.info("loaded %s weights from %s (%d tensors)", what, path, len(clean))
