"""Training configuration: nested frozen dataclasses, loaded from JSON or TOML.

Defaults are the GaussianAvatars recipe (ShenhanQian/GaussianAvatars ``arguments/__init__.py``:
600k iterations, densification every 2k iterations from 10k, opacity reset every 60k, the
bound-to-mesh learning rates of :class:`~avatar_core.train.optim.GaussianLR`) with MVFGA's
additions: an LPIPS term (gamma 0.04), FLAME/MANO fusion of the tracked parameters and
fine-tuning of transl / expression / body_pose at the paper's rates. ``preset("quick")`` and
``preset("test")`` shrink the schedule for CPU runs and unit tests.

A config file is a JSON object or a TOML table with the same nesting as :class:`TrainConfig`;
missing keys keep their defaults, an optional top-level ``preset = "quick"`` picks the base
values, and an unknown key is an error naming it (``densify.intervall``), so a typo never
trains silently with a default::

    preset = "quick"
    iterations = 5000
    [data]
    crop_to_subject = true
    [densify]
    interval = 500

:func:`config_to_dict` gives the resolved config as plain JSON types (written next to the
checkpoints and into the avatar package); :func:`config_from_dict` reads it back exactly.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from .optim import DEFAULT_PARAM_LRS, GaussianLR

__all__ = ["ConfigError", "DataConfig", "DensifyConfig", "FineTuneConfig", "LossConfig",
           "PRESETS", "TrainConfig", "config_from_dict", "config_to_dict", "load_config",
           "preset", "save_config"]


class ConfigError(ValueError):
    """A config file or dict that cannot be used; the message names the key."""


LOWER_BODY_MODES = ("ignore", "background")


@dataclass(frozen=True)
class DataConfig:
    """Which views, at what size, on what background."""

    split: str = "train"
    scale: float = 1.0                  # image scale factor (0.5: half width and height)
    target_size: int | None = None      # longest image side in px; overrides scale
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # GT composited on it
    crop_to_subject: bool = True        # render and score only the subject's box
    crop_margin: int = 16               # px around the box, at training resolution
    cache_views: int = 256              # decoded views kept in memory (LRU)
    fusion: bool = True                 # FLAME/MANO fusion when params.npz has those keys
    # Lower-body pixels (legs, hips): "ignore" weighs them 0; "background" makes them
    # background in the target, weighted 1, so nothing of the avatar may cover them (it ends
    # at the cut; the hem frays past it otherwise: docs/results.md, demo artefacts).
    lower_body: str = "ignore"
    # A random background colour per iteration (the target re-composited on it) instead of
    # ``background`` (measured on the demo: fewer floaters early, 8x more after the opacity
    # reset; off in every preset, docs/results.md).
    random_background: bool = False

    def __post_init__(self) -> None:
        _require(0 < self.scale <= 1, "data.scale", "must be in (0, 1]", self.scale)
        _require(self.lower_body in LOWER_BODY_MODES, "data.lower_body",
                 f"must be one of {list(LOWER_BODY_MODES)}", self.lower_body)
        _require(self.target_size is None or self.target_size >= 16, "data.target_size",
                 "must be >= 16 px", self.target_size)
        _require(len(self.background) == 3 and all(0 <= c <= 1 for c in self.background),
                 "data.background", "must be three values in [0, 1]", self.background)
        _require(self.crop_margin >= 0, "data.crop_margin", "must be >= 0", self.crop_margin)
        _require(self.cache_views >= 1, "data.cache_views", "must be >= 1", self.cache_views)


@dataclass(frozen=True)
class LossConfig:
    """(1 - l_dssim) L1 + l_dssim (1 - SSIM) + gamma LPIPS + position / scaling hinges."""

    lambda_dssim: float = 0.2    # 3DGS / GaussianAvatars
    lambda_lpips: float = 0.04   # MVFGA's gamma
    lpips: bool = True           # used only when LPIPS can run offline (logged at start)
    lpips_net: str = "alex"
    lambda_pos: float = 0.01     # GaussianAvatars lambda_xyz
    eps_pos: float = 1.0         # threshold_xyz
    lambda_scale: float = 1.0    # lambda_scale
    eps_scale: float = 0.6       # threshold_scale
    # L1 between the rendered alpha and the view's mask (0: off; enrollment's masks): keeps
    # Gaussians off the background where the colour alone would let them blend in.
    lambda_mask: float = 0.0

    def __post_init__(self) -> None:
        _require(0 <= self.lambda_dssim <= 1, "loss.lambda_dssim", "must be in [0, 1]",
                 self.lambda_dssim)
        for name in ("lambda_lpips", "lambda_pos", "eps_pos", "lambda_scale", "eps_scale",
                     "lambda_mask"):
            v = getattr(self, name)
            _require(math.isfinite(v) and v >= 0, f"loss.{name}", "must be >= 0", v)


@dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control (3DGS as GaussianAvatars schedules it)."""

    enabled: bool = True
    from_iter: int = 10_000          # 3DGS: 500
    until_iter: int = 600_000        # 3DGS: 15_000
    interval: int = 2_000            # 3DGS: 100
    grad_threshold: float = 2e-4     # NDC units, as 3DGS
    percent_dense: float = 0.01
    extent: float | None = None      # world units; None: 1.1 x the cameras' radius (3DGS)
    opacity_reset_interval: int = 60_000  # 3DGS: 3_000
    min_opacity: float = 0.005
    max_screen_size: float | None = 20.0  # px, applied after the first opacity reset
    max_gaussians: int | None = 200_000

    def __post_init__(self) -> None:
        for name in ("from_iter", "until_iter"):
            _require(getattr(self, name) >= 0, f"densify.{name}", "must be >= 0",
                     getattr(self, name))
        for name in ("interval", "opacity_reset_interval"):
            _require(getattr(self, name) >= 1, f"densify.{name}", "must be >= 1",
                     getattr(self, name))
        _require(self.grad_threshold > 0, "densify.grad_threshold", "must be > 0",
                 self.grad_threshold)
        _require(0 <= self.min_opacity < 1, "densify.min_opacity", "must be in [0, 1)",
                 self.min_opacity)
        _require(self.extent is None or self.extent > 0, "densify.extent", "must be > 0",
                 self.extent)
        _require(self.max_gaussians is None or self.max_gaussians >= 1,
                 "densify.max_gaussians", "must be >= 1", self.max_gaussians)


FINETUNE_SCHEDULES = ("fixed", "budget")


@dataclass(frozen=True)
class FineTuneConfig:
    """Per-frame SMPL-X deltas optimised with the Gaussians.

    ``schedule = "fixed"``: the rates below throughout (MVFGA's; they assume ~600k
    iterations). ``"budget"``: the rates follow from the run's length instead (see
    :meth:`lrs_at`): Adam moves a parameter by about its rate per update, and a frame's delta
    is updated only when one of its views is drawn, ``iterations / frames`` times in all, so
    each rate is set so that its delta can travel ``reach_*`` over the run: nothing for the
    first ``start`` of the run (the Gaussians settle first), then decaying log-linearly to
    ``final`` x the first rate at the end."""

    enabled: bool = True
    transl: float = DEFAULT_PARAM_LRS["transl"]
    expression: float = DEFAULT_PARAM_LRS["expression"]
    body_pose: float = DEFAULT_PARAM_LRS["body_pose"]
    schedule: str = "fixed"
    # The reach should match the trackers' per-joint error: Adam moves a delta by about its
    # rate per update whatever the gradient's size, so a larger reach becomes a random walk
    # that, summed down the arm chain, misposes the hands (docs/results.md, noisy-tracker
    # benchmark: 5 deg cost the avatar 6 dB; 1 deg gained 0.8-1.8 dB on the held-out take).
    reach_transl: float = 0.005         # m
    reach_expression: float = 0.1       # expression units (the library's reach about 1)
    reach_body_pose_deg: float = 1.0    # per axis, per joint
    start: float = 0.2                  # fraction of the run before the deltas move
    final: float = 0.1                  # last rate / first rate

    def lrs(self) -> dict[str, float]:
        return {"transl": self.transl, "expression": self.expression,
                "body_pose": self.body_pose}

    def reach(self) -> dict[str, float]:
        return {"transl": self.reach_transl, "expression": self.reach_expression,
                "body_pose": math.radians(self.reach_body_pose_deg)}

    def lrs_at(self, iteration: int, iterations: int, frames: int) -> dict[str, float]:
        """Rates at ``iteration`` (1-based) of a run of ``iterations`` over ``frames``
        training frames (all sequences together)."""
        if self.schedule == "fixed":
            return self.lrs()
        if frames < 1 or iterations < 1:
            raise ValueError(f"frames and iterations must be >= 1, got {frames}, {iterations}")
        first = math.floor(self.start * iterations)
        if iteration <= first:
            return dict.fromkeys(self.lrs(), 0.0)
        active = iterations - first
        t = min((iteration - first - 1) / max(active - 1, 1), 1.0)
        # mean of final**t over t in [0, 1]: the sum of the rates is reach
        mean = 1.0 if self.final == 1 else (1 - self.final) / -math.log(self.final)
        updates = max(active / frames, 1.0)
        return {k: r / (updates * mean) * self.final ** t for k, r in self.reach().items()}

    def __post_init__(self) -> None:
        for name, v in (*self.lrs().items(), *self.reach().items()):
            _require(math.isfinite(v) and v >= 0, f"finetune.{name}", "must be >= 0", v)
        _require(self.schedule in FINETUNE_SCHEDULES, "finetune.schedule",
                 f"must be one of {list(FINETUNE_SCHEDULES)}", self.schedule)
        _require(0 <= self.start < 1, "finetune.start", "must be in [0, 1)", self.start)
        _require(0 < self.final <= 1, "finetune.final", "must be in (0, 1]", self.final)


@dataclass(frozen=True)
class TrainConfig:
    iterations: int = 600_000
    seed: int = 0
    device: str = "auto"             # "auto": cuda when available, else cpu
    sh_degree: int = 3
    sh_interval: int = 1_000         # +1 active SH degree every this many iterations (3DGS)
    init_color: str = "project"      # "project": sampled from the training views; "grey"
    # triangles no view saw at init: "neighbours" (their coloured neighbours' mean) or "grey"
    # (measured: no change to the demo's armpits, whose Gaussians leave grey anyway)
    init_unseen: str = "grey"
    checkpoint_interval: int = 10_000
    progress_interval: int = 10      # iterations between progress events
    data: DataConfig = field(default_factory=DataConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    lr: GaussianLR = field(default_factory=GaussianLR)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    finetune: FineTuneConfig = field(default_factory=FineTuneConfig)

    def __post_init__(self) -> None:
        _require(self.iterations >= 1, "iterations", "must be >= 1", self.iterations)
        _require(0 <= self.sh_degree <= 3, "sh_degree", "must be in 0..3", self.sh_degree)
        for name in ("sh_interval", "checkpoint_interval", "progress_interval"):
            _require(getattr(self, name) >= 1, name, "must be >= 1", getattr(self, name))
        _require(self.init_color in ("project", "grey"), "init_color",
                 "must be 'project' or 'grey'", self.init_color)
        _require(self.init_unseen in ("neighbours", "grey"), "init_unseen",
                 "must be 'neighbours' or 'grey'", self.init_unseen)
        _require(self.device == "auto" or self.device.split(":")[0] in ("cpu", "cuda", "mps"),
                 "device", "must be 'auto', 'cpu', 'cuda[:N]' or 'mps'", self.device)

    def active_sh_degree(self, iteration: int) -> int:
        """SH degree rendered at ``iteration`` (1-based): 0 first, +1 every sh_interval."""
        return min(self.sh_degree, max(iteration, 0) // self.sh_interval)


def _require(ok: bool, key: str, what: str, value: Any) -> None:
    if not ok:
        raise ConfigError(f"{key} {what}, got {value!r}")


# -- presets ----------------------------------------------------------------------------


def _quick() -> TrainConfig:
    """A few thousand iterations: a usable avatar on CPU in minutes (3DGS-like pacing)."""
    return TrainConfig(
        iterations=5_000, checkpoint_interval=1_000, sh_interval=1_000,
        lr=GaussianLR(position_max_steps=5_000),
        densify=DensifyConfig(from_iter=500, until_iter=4_000, interval=250,
                              opacity_reset_interval=2_000, max_gaussians=60_000))


def _demo() -> TrainConfig:
    """The demo avatar of ``make run`` (avatar_core.demo): the quick schedule compressed to
    2,000 iterations (the benchmark's full model scores 33.6 dB novel-view PSNR there), so
    that capture + training stay well within 10 minutes on 2 CPU cores, even shared."""
    return TrainConfig(
        iterations=2_000, checkpoint_interval=500, sh_interval=400,
        # the demo's artefacts (docs/results.md): the hem frayed past the cut (legs ignored),
        # and armpit smudges: the opacity reset at 1,000 left the Gaussians that no later
        # view sees (the armpits) nearly clear for good, so no reset within the run
        data=DataConfig(lower_body="background"),
        lr=GaussianLR(position_max_steps=2_000),
        densify=DensifyConfig(from_iter=300, until_iter=1_600, interval=150,
                              opacity_reset_interval=10_000, max_gaussians=60_000))


def _test() -> TrainConfig:
    """Unit tests: a few hundred iterations on ~64 px images, no LPIPS, densify early. The
    loss is a mean over pixels, so at 64 px each pixel weighs ~60x what it does at 512 px
    and so do the view-space gradients: the threshold is 5x 3DGS's, or the first
    densification would clone a third of the avatar (which then overfits the few views)."""
    return TrainConfig(
        iterations=300, checkpoint_interval=100, sh_interval=100, sh_degree=1,
        data=DataConfig(crop_margin=4, cache_views=64),
        loss=LossConfig(lpips=False),
        lr=GaussianLR(position_max_steps=300),
        densify=DensifyConfig(from_iter=50, until_iter=250, interval=50, grad_threshold=1e-3,
                              opacity_reset_interval=10_000, max_gaussians=30_000))


def _enroll() -> TrainConfig:
    """Enrollment from one video (avatar_core.enroll; ``enroll.training.enroll_config`` scales
    the schedule to the run's length and frame count): monocular, so per-frame parameters are
    fine-tuned on the "budget" schedule (the tracker's per-frame errors are larger than a
    studio's), the mask loss is on (the selfie masks), the position/scaling hinges are 3x
    (parts seen from one side only must not drift off the surface) and the opacity never
    reset (the far side is seen in few frames, a reset would leave it clear, as the demo's
    armpits)."""
    return TrainConfig(
        iterations=3_000, checkpoint_interval=1_000, sh_interval=500, sh_degree=1,
        loss=LossConfig(lambda_mask=0.1, lambda_pos=0.03, lambda_scale=3.0),
        lr=GaussianLR(position_max_steps=3_000),
        densify=DensifyConfig(from_iter=300, until_iter=2_400, interval=150,
                              opacity_reset_interval=1_000_000, max_gaussians=60_000),
        finetune=FineTuneConfig(schedule="budget"))


PRESETS = types.MappingProxyType({"default": TrainConfig, "quick": _quick, "demo": _demo,
                                  "test": _test, "enroll": _enroll})


def preset(name: str) -> TrainConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; presets: {sorted(PRESETS)}")
    return PRESETS[name]()


# -- dict / file round trip -------------------------------------------------------------


def config_to_dict(config: Any) -> dict[str, Any]:
    """Plain JSON types (tuples become lists), nested like the dataclasses."""
    out: dict[str, Any] = {}
    for f in fields(config):
        v = getattr(config, f.name)
        if dataclasses.is_dataclass(v):
            v = config_to_dict(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


def _coerce(value: Any, hint: Any, key: str) -> Any:
    """``value`` checked against the annotation ``hint`` (bool, int, float, str, a tuple of
    floats, ``X | None``, a nested dataclass); raises ConfigError naming ``key``."""
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigError(f"{key} must be a table/object, got {value!r}")
        return _build(hint, value, f"{key}.")
    args = typing.get_args(hint)
    if type(hint) is types.UnionType or typing.get_origin(hint) is typing.Union:
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], key)
    if typing.get_origin(hint) is tuple:
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ConfigError(f"{key} must be a list of {len(args)} numbers, got {value!r}")
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(
            zip(value, args, strict=True)))
    if hint is bool:
        ok = isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif hint is str:
        ok = isinstance(value, str)
    else:  # pragma: no cover - a field type this loader does not know
        raise ConfigError(f"{key}: unsupported field type {hint!r}")
    if not ok:
        raise ConfigError(f"{key} must be {getattr(hint, '__name__', hint)}, got {value!r}")
    return value


def _build(cls: type, values: dict[str, Any], prefix: str = "",
           base: Any = None) -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"unknown config key(s) {[prefix + k for k in unknown]}; "
                          f"{prefix.rstrip('.') or 'the top level'} takes {sorted(names)}")
    base = base if base is not None else cls()
    kwargs = {}
    for name, value in values.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint) and isinstance(value, dict):
            kwargs[name] = _build(hint, value, f"{prefix}{name}.", getattr(base, name))
        else:
            kwargs[name] = _coerce(value, hint, prefix + name)
    try:
        return replace(base, **kwargs)
    except ConfigError:
        raise
    except ValueError as exc:  # GaussianLR's own checks
        raise ConfigError(f"{prefix.rstrip('.') or 'config'}: {exc}") from exc


def config_from_dict(values: dict[str, Any]) -> TrainConfig:
    """A TrainConfig from nested dicts (keys absent keep the preset's / the defaults)."""
    if not isinstance(values, dict):
        raise ConfigError(f"a config must be a table/object, got {type(values).__name__}")
    values = dict(values)
    name = values.pop("preset", "default")
    if not isinstance(name, str):
        raise ConfigError(f"preset must be a name, got {name!r}")
    return _build(TrainConfig, values, base=preset(name))


def load_config(path: str | Path) -> TrainConfig:
    """Read a ``.json`` or ``.toml`` config file."""
    path = Path(path)
    try:
        if path.suffix == ".toml":
            values = tomllib.loads(path.read_text())
        elif path.suffix == ".json":
            values = json.loads(path.read_text())
        else:
            raise ConfigError(f"{path}: config files are .json or .toml")
    except (OSError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{path}: cannot read the config: {exc}") from exc
    try:
        return config_from_dict(values)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def save_config(config: TrainConfig, path: str | Path) -> Path:
    """The resolved config as JSON (readable by :func:`load_config`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(config_to_dict(config), indent=2) + "\n")
    return path
