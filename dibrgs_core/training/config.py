"""Training configuration: dataclasses holding the paper's defaults, and named presets.

Every schedule is a *fraction of training* so that a shorter run (the ``cpu`` and
``test`` presets) keeps the paper's proportions. With the paper's 30,000 iterations:

* anchor growth every 100 its (1/300 of training) from 1,500 (5%) to 15,000 (50%);
  gradient statistics start at 500 (1/60), as in Scaffold-GS;
* pseudo-view supervision every 50 its (1/600) from 3,000 (10%) to 20,000 (2/3);
* the IBR projection P (AdamW, lr 1e-4) is frozen after 20,000 its (2/3);
* learning rates decay exponentially over the whole run (Scaffold-GS schedules).

Scaffold-GS facts used (city-super/Scaffold-GS ``arguments/__init__.py``,
``scene/gaussian_model.py``): feat_dim 32, n_offsets 10 (its default; the paper
also uses k = 10), update_depth 3, update_init_factor 16, update_hierachy_factor 4,
densify_grad_threshold 2e-4, min_opacity 0.005, success_threshold 0.8, learning
rates offset 1e-2 -> 1e-4, anchor_feat 7.5e-3, scaling 7e-3, mlp_opacity 2e-3 -> 2e-5,
mlp_cov 4e-3 (constant), mlp_color 8e-3 -> 5e-5, volume regulariser weight 0.01.

This module imports only the standard library (and the standard-library-only model config).
"""
from __future__ import annotations

import dataclasses
import numbers
import types
import typing
from dataclasses import asdict, dataclass, field
from typing import Any

from ..common.modes import DepthPrior, IbrEncoder, MethodName, PresetName, Switch, choices
from ..models.config import ModelConfig


def at_fraction(frac: float, iterations: int, minimum: int = 0) -> int:
    """The iteration at ``frac`` of ``iterations`` (rounded), at least ``minimum``."""
    return max(minimum, int(round(frac * iterations)))


@dataclass
class GrowthConfig:
    """Scaffold-GS anchor growing and pruning, with the paper's height veto."""

    update_depth: int = 3
    update_init_factor: int = 16
    update_hierarchy_factor: int = 4
    grad_threshold: float = 0.0002   # NDC-space gradient norm, as in 3DGS / Scaffold-GS
    min_opacity: float = 0.005       # per visit
    success_threshold: float = 0.8
    stat_start: float = 500 / 30000
    densify_from: float = 0.05
    densify_until: float = 0.5
    densify_every: float = 100 / 30000
    # Floor on the growth interval of short runs, so that the averaged gradients
    # and per-visit opacities still average over several views.
    min_every: int = 10
    # Cap on the number of anchors (None = none, as in the paper). Short runs
    # start growing while the model is still far from converged, when most
    # gradients pass the threshold; a CPU budget needs a ceiling.
    max_anchors: int | None = None


@dataclass
class LRConfig:
    """Learning rates (initial, final) and the IBR projection's optimiser."""

    offset: tuple[float, float] = (0.01, 0.0001)
    anchor_feat: float = 0.0075
    scaling: float = 0.007
    mlp_opacity: tuple[float, float] = (0.002, 0.00002)
    mlp_cov: tuple[float, float] = (0.004, 0.004)
    mlp_color: tuple[float, float] = (0.008, 0.00005)
    # E_ref / E_mod are decoders like the Scaffold-GS MLPs; the paper gives no
    # number, so they follow mlp_opacity's schedule.
    ibr_fusion: tuple[float, float] = (0.002, 0.00002)
    projection: float = 1e-4          # AdamW, paper
    projection_freeze: float = 2 / 3  # paper: frozen after 20k of 30k


@dataclass
class PseudoConfig:
    """Pseudo-view supervision through progressive DIBR."""

    mode: Switch = "auto"       # auto: skip with >= dense_views training views
    n_views: int = 24           # poses sampled once along the training cameras' trajectory, cached
    start: float = 0.1
    until: float = 2 / 3
    every: float = 50 / 30000
    min_every: int = 2          # short runs: at most every other step is a pseudo view
    dense_views: int = 10       # auto: skip when the training views are this dense
    # Loss weight of padded pixels (filled by padding, no source view saw them)
    # relative to warped ones; 0 masks them out.
    padded_weight: float = 1.0
    # Large holes in pseudo-view depth: auto = rasterise a height field of the
    # cloud when the views are near-nadir (surface.applies), else the nearest
    # valid pixel; on / off force it.
    surface: Switch = "auto"
    # Leave out of supervision warped pixels that two training views see in
    # colours further apart than this (mean |RGB| in [0,1]); 0 keeps all. With
    # the height field, the same check picks per pixel between its depth and
    # the completed cloud's.
    consistency_tol: float = 0.1

    def dense_reason(self, n_train: int) -> str | None:
        """Why ``auto`` leaves pseudo views out for ``n_train`` training views, or None when it
        uses them (training's decision; the add-on says it at import)."""
        if self.mode == "auto" and n_train >= self.dense_views:
            return f"{n_train} training views are dense enough (>= {self.dense_views})"
        return None


@dataclass
class GS3DConfig:
    """Vanilla 3DGS baseline (graphdeco-inria/gaussian-splatting defaults)."""

    sh_degree: int = 3
    sh_every: float = 1000 / 30000
    position_lr: tuple[float, float] = (0.00016, 0.0000016)
    feature_lr: float = 0.0025
    opacity_lr: float = 0.025
    scaling_lr: float = 0.005
    rotation_lr: float = 0.001
    densify_from: float = 500 / 30000
    densify_until: float = 0.5
    densify_every: float = 100 / 30000
    min_every: int = 10                 # floor on the densification interval of short runs
    opacity_reset_every: float = 3000 / 30000
    # Floor on the opacity-reset interval, in iterations: 3DGS's own 3,000. After a reset to
    # 0.01 the opacities need many iterations to come back (logit -4.6 at lr 0.025, and only
    # in the views that see a Gaussian), a number of iterations rather than a share of the
    # run; 3DGS leaves 3,000 between resets and 18,000 after the last. Runs shorter than
    # 6,000 iterations (the cpu preset's 2,000) therefore never reset: a single reset at 500
    # of 2,000 cost 3DGS 0.7-1.6 dB held out on five generated cases and did not help on the
    # real flight (docs/benchmarks.md, "An honest baseline").
    min_reset_every: int = 3000
    grad_threshold: float = 0.0002
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    max_screen_size: float = 20.0
    max_gaussians: int | None = None
    # Fewer SfM points than this (sparse views often give none): add random points
    # in the viewed volume, as 3DGS does for scenes without SfM.
    min_sfm_points: int = 100
    random_points: int = 10000


@dataclass
class ColourConfig:
    """Per-training-view colour transforms (:mod:`.appearance`): a 3x3 matrix and an offset
    applied to the render before the loss on that view, centred so that the median view's is
    the identity, which renders new views."""

    # auto: with two or more training views. Off by default: on three views with one photo
    # 50 % over-exposed the transforms found that photo's gain but held-out PSNR fell from
    # 21.3 to 18.1 dB (tests/training/test_appearance.py), so they are not yet a net gain.
    mode: Switch = "off"
    lr: tuple[float, float] = (0.005, 0.0005)   # Adam, exponential decay over the run
    # Fraction of training before the transforms learn: a model that has not yet fitted the
    # photos' colours would hand its own errors to them.
    start: float = 0.0
    # Weight of |A - I|^2 + |b|^2 of the iteration's view, beside the photometric loss.
    weight: float = 0.01


@dataclass
class TrainConfig:
    """Everything a run needs. ``preset`` names the origin of the numbers."""

    preset: PresetName = "paper"
    method: MethodName = "dibrgs"
    iterations: int = 30000
    # Images are resized by this factor; None = to the pixel budget ``max_long_side`` when
    # one is set, else full resolution. The run records the factor it used.
    resolution_scale: float | None = None
    max_long_side: int | None = None    # pixel budget: long side of the largest image
    seed: int = 0
    lambda_dssim: float = 0.2
    lambda_volume: float = 0.01
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Ablations / auto decisions
    dense_init: bool = True
    depth_prior: DepthPrior = "auto"    # gt = oracle depth (ablation)
    ibr: IbrEncoder = "auto"
    dino_resnet: str | None = None
    dino_vit: str | None = None
    height: Switch = "auto"             # the height constraint on anchor growth
    pseudo_path: str | None = None
    # Book-keeping
    checkpoint_every_s: float = 300.0
    curve_every_s: float = 60.0         # training wall-clock seconds between curve points
    # Held-out views a curve point evaluates (evenly spread, the same at every point; None = all);
    # the last point evaluates all of them.
    curve_max_views: int | None = 4
    progress_every: int = 10
    model: ModelConfig = field(default_factory=ModelConfig)
    growth: GrowthConfig = field(default_factory=GrowthConfig)
    lr: LRConfig = field(default_factory=LRConfig)
    pseudo: PseudoConfig = field(default_factory=PseudoConfig)
    gs3d: GS3DConfig = field(default_factory=GS3DConfig)
    colour: ColourConfig = field(default_factory=ColourConfig)

    # -- schedules in iterations ------------------------------------------------
    def it(self, frac: float, minimum: int = 0) -> int:
        return at_fraction(frac, self.iterations, minimum)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "TrainConfig":
        """The configuration ``to_dict`` gave (JSON lists back to tuples, whole numbers where a
        float goes to floats); ``ValueError`` names any key, top-level or nested, that no field
        has or whose value is not of the field's type (a damaged or hand-edited file)."""
        kw: dict[str, Any] = {}
        hints = typing.get_type_hints(TrainConfig)
        for k, v in d.items():
            if k not in hints:
                raise ValueError(f"unknown config key {k!r}")
            sub = hints[k]
            if dataclasses.is_dataclass(sub):  # a nested table: model, growth, lr, ...
                if not isinstance(v, dict):
                    raise ValueError(f"config key {k!r}: {v!r} is not a table of {sub.__name__}'s fields")
                sub_hints = typing.get_type_hints(sub)
                unknown = sorted(set(v) - set(sub_hints))
                if unknown:
                    raise ValueError(f"unknown config key{'s' if len(unknown) > 1 else ''} "
                                     + ", ".join(f"{k}.{u}" for u in unknown))
                kw[k] = sub(**{kk: _typed(f"{k}.{kk}", sub_hints[kk], vv) for kk, vv in v.items()})
            else:
                kw[k] = _typed(k, hints[k], v)
        return TrainConfig(**kw)


def _typed(key: str, hint: Any, v: Any) -> Any:
    """``v`` as a field of type ``hint`` holds it (a list as a tuple, an int as a float where a
    float goes); ``ValueError`` naming ``key`` when it is not of that type."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union):  # X | None
        if v is None and type(None) in args:
            return None
        for a in args:
            if a is not type(None):
                try:
                    return _typed(key, a, v)
                except ValueError:
                    pass
    elif origin is typing.Literal:
        if isinstance(v, str) and v in args:
            return v
    elif origin is tuple:
        if isinstance(v, (list, tuple)) and len(v) == len(args):
            return tuple(_typed(key, a, x) for a, x in zip(args, v))
    elif hint is float:  # numbers.Real: numpy's scalars too (a value computed with numpy)
        if isinstance(v, numbers.Real) and not isinstance(v, bool):
            return float(v)
    elif hint is int:
        if isinstance(v, numbers.Integral) and not isinstance(v, bool):
            return int(v)
    elif hint in (bool, str):
        if isinstance(v, hint):
            return v
    else:  # pragma: no cover - a field of a type this function does not know yet
        raise TypeError(f"config key {key!r}: no check for {hint!r}")
    raise ValueError(f"config key {key!r}: {v!r} is not {_describe(hint)}")


def _describe(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union):
        return " or ".join(_describe(a) for a in args)
    if origin is typing.Literal:
        return "one of " + ", ".join(map(str, args))
    if origin is tuple:
        return f"a list of {len(args)} numbers"
    return {type(None): "null", float: "a number", int: "a whole number", bool: "true or false",
            str: "a text"}.get(hint, str(hint))


PRESETS: tuple[str, ...] = choices(PresetName)
#: One line on each preset, for menus (the Blender add-on); keys are :data:`PRESETS`.
PRESET_SUMMARY: dict[str, str] = {
    "paper": "The paper's schedule: 30,000 iterations at full resolution",
    "cpu": "Scaled for a CPU: 2,000 iterations, images at most 512 px on the long side (minutes on 2 cores)",
    "test": "A few hundred iterations (checks the pipeline end to end)",
}


def preset(name: PresetName) -> TrainConfig:
    """A named preset.

    * ``paper``: the paper's numbers (30k iterations, full resolution).
    * ``cpu``: a 3-view scene in minutes on a 2-core CPU (images at most 512 px on the long side):
      2,000 iterations, at most 3,000 initial anchors (the voxel grows by 2^(1/4) steps to
      fit: doubling it made a scene's anchors jump 2.5-3x at a threshold of the cloud's size,
      and the extra anchors cost time for the same held-out PSNR on average; docs/benchmarks.md
      "Initial anchors") and 20,000 in all; 96 pseudo views on every other iteration from 10%
      to the end (a short run has too few iterations for the paper's every-50th schedule to
      regularise the held-out views; more distinct poses stand in for the paper's
      fresh random ones); anchor growth threshold 4x Scaffold-GS's (growth starts
      at iteration 100, when gradients are still large everywhere, and the extra
      anchors fit the three training views at the held-out views' expense);
      padded pseudo-view pixels (colour copied from the nearest warped pixel, no
      view saw them) at half the loss weight of warped ones; a curve point every
      10 s (a run of one or two minutes had two to four points at 30 s; a point's four
      held-out views take 32-92 ms on two threads at 256x256 and 512x288, under 1 % of the
      run's wall time, outside the training clock); images downscaled to a long side of
      512 px unless a resolution scale is given (a 4000x3000 photo would cost 45x the
      pixels of a 512x512 generated view).
    * ``test``: a 64x64 scene end to end in well under a minute (CI).
    """
    if name == "paper":
        return TrainConfig()
    if name == "cpu":
        c = TrainConfig(preset="cpu", iterations=2000, checkpoint_every_s=120.0, curve_every_s=10.0,
                        max_long_side=512)
        c.model.max_init_anchors = 3000
        c.model.anchor_voxel_growth = 2 ** 0.25
        c.growth.max_anchors = 20000
        c.growth.grad_threshold = 4 * c.growth.grad_threshold
        c.pseudo.n_views = 96
        c.pseudo.padded_weight = 0.5
        c.pseudo.every = 2 / 2000
        c.pseudo.until = 1.0
        c.gs3d.max_gaussians = 60000
        return c
    if name == "test":
        c = TrainConfig(preset="test", iterations=300, checkpoint_every_s=30.0, curve_every_s=10.0,
                        progress_every=25)
        c.model.max_init_anchors = 800
        c.growth.max_anchors = 2000
        c.pseudo.n_views = 4
        c.gs3d.max_gaussians = 8000
        c.gs3d.random_points = 2000
        return c
    raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")


def resolve_resolution(cfg: TrainConfig, sizes: list[tuple[int, int]]) -> tuple[float, bool, str]:
    """The resize factor of a run whose images are ``sizes`` (width, height), whether the pixel
    budget set it, and why.

    An explicit ``resolution_scale`` wins; else a pixel budget ``max_long_side`` shrinks the
    largest image's long side to it (never enlarges); else full resolution.
    """
    if cfg.resolution_scale is not None:
        return float(cfg.resolution_scale), False, f"resolution scale {cfg.resolution_scale:g} as given"
    long_side = max((max(w, h) for w, h in sizes), default=0)
    if cfg.max_long_side is None or long_side <= cfg.max_long_side:
        why = "full resolution" + (f" (long side {long_side} px is within the {cfg.max_long_side} px budget)"
                                   if cfg.max_long_side is not None else "")
        return 1.0, False, why
    s = cfg.max_long_side / long_side
    return s, True, (f"pixel budget of the {cfg.preset} preset: long side {long_side} px -> {cfg.max_long_side} px "
               f"(scale {s:.4g}; --resolution-scale overrides)")


def expon_lr(step: int, total: int, init: float, final: float) -> float:
    """Log-linear decay from ``init`` (step 0) to ``final`` (step ``total``), as 3DGS's
    ``get_expon_lr_func`` without delay steps; 0 when ``init`` is 0."""
    if init <= 0.0:
        return 0.0
    if final <= 0.0:
        final = init
    import math

    t = min(max(step / max(total, 1), 0.0), 1.0)
    return math.exp(math.log(init) * (1.0 - t) + math.log(final) * t)
