"""qcm-estimate's settings as a structured config: the schema of configs/estimate.yaml and its experiments.

`EstimateSettings` types every key of configs/estimate.yaml (the defaults and the documentation stay
there; fields here carry no defaults of their own, so there is one source of each value). It is
registered with Hydra's ConfigStore as ``schema/estimate`` (estimate.yaml's defaults list names it,
``optional``: a config composed before this module is imported is checked by `check` alone), so Hydra
refuses an unknown key or a wrongly typed value while it composes. The apps report those in one line:

    check_overrides(args)   the command line, before Hydra composes (Hydra's own message is a page)
    check(cfg)              the composed config: keys added with `+key=`, and any config not composed
                            against the schema (a test's or the Python API's)

Typed: switches (bool), counts (int), numbers (float; an int is taken), names (str), lists of them;
`Optional` where null means off or all. `Any`: keys of several kinds (n_steps: a number or max; delay:
null, auto, estimate or ms; input_margin: auto or [before, after]; init.equation_error: true, false or,
for a half / full car, seats), the free-form GN stage list and the config groups of their own schema
(paths, solver, sensor, trainer). Allowed values of a name (dynamics, hold, ...) are checked where
they are used, with the run's context.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from omegaconf import MISSING

from hybridqcm.config import check_overrides_against, check_settings_against
from hybridqcm.errors import ConfigError

# Optional[...] rather than `X | None`: OmegaConf reads the annotations (it knows typing.Optional).
# ruff: noqa: UP045


@dataclass
class DataSettings:
    path: str = MISSING
    split: str = MISSING


@dataclass
class SkipWindowsSettings:
    min_std: float = MISSING
    clip_samples: Optional[int] = MISSING


@dataclass
class IntervalSettings:
    covariance: str = MISSING
    band: int = MISSING
    student_t: bool = MISSING
    jackknife_test: Optional[float] = MISSING


@dataclass
class VehiclePriorSettings:
    params: list[str] = MISSING
    rel_std: Optional[float] = MISSING


@dataclass
class InitSettings:
    relative_sigma: float = MISSING
    cnn: bool = MISSING
    cnn_prior_rel_std: Optional[float] = MISSING
    cnn_prior: Optional[str] = MISSING
    cnn_prior_scale: float = MISSING
    equation_error: Any = MISSING  # true | false; a half / full car also takes seats (checked in `check`)


@dataclass
class RestartSettings:
    count: int = MISSING
    threshold: float = MISSING
    sigma: float = MISSING
    mass_factors: list[float] = MISSING
    batch: int = MISSING
    failed: int = MISSING
    far_from_start: Optional[float] = MISSING
    around: str = MISSING


@dataclass
class OccupantSettings:
    models: list[str] = MISSING
    interval_weight: float = MISSING
    body_prior: bool = MISSING
    profile: bool = MISSING
    rigid_prior: float = MISSING
    boundary_hold: bool = MISSING
    workers: Any = MISSING  # auto | an integer >= 1 (plan_occupant checks it)


@dataclass
class DriveSettings:
    statuses: list[str] = MISSING
    weights: str = MISSING
    scale: str = MISSING
    alpha: float = MISSING
    min_windows: int = MISSING
    outlier_alpha: float = MISSING
    neighbours: int = MISSING
    per_window: list[str] = MISSING
    joint: str = MISSING
    split: str = MISSING
    space: str = MISSING
    prior: str = MISSING
    prior_from: str = MISSING
    plots: int = MISSING


@dataclass
class EstimateSettings:
    """configs/estimate.yaml, key by key (the comments there say what each one does)."""

    # config groups with schemas of their own (solver_settings, build_sensor, check_trainer_settings)
    paths: Any = MISSING
    solver: Any = MISSING
    sensor: Any = MISSING
    trainer: Any = MISSING
    task_name: str = MISSING
    experiment_name: str = MISSING
    data: DataSettings = field(default_factory=DataSettings)
    dynamics: str = MISSING
    initial_state: str = MISSING
    hold: str = MISSING
    substeps: int = MISSING
    spline_degree: int = MISSING
    input_margin: Any = MISSING  # auto | [before, after]
    x0_start: str = MISSING
    min_window_unknown_state: int = MISSING
    misfit_peer_factor: Optional[float] = MISSING
    n_steps: Any = MISSING  # a number of samples | max
    n_samples: Optional[int] = MISSING
    skip_windows: SkipWindowsSettings = field(default_factory=SkipWindowsSettings)
    seed: int = MISSING
    noise_sigma: float = MISSING
    noise_weighting: bool = MISSING
    residual_weighting: Any = MISSING  # auto | spectral | true | false
    intervals: IntervalSettings = field(default_factory=IntervalSettings)
    vehicle_prior: VehiclePriorSettings = field(default_factory=VehiclePriorSettings)
    cnn_ckpt: Optional[str] = MISSING
    unet_ckpt: Optional[str] = MISSING
    cae_ckpt: Optional[str] = MISSING
    observed: list[str] = MISSING
    known: list[str] = MISSING
    base_excitation: Optional[str] = MISSING
    vehicle_model: str = MISSING
    seat: Optional[str] = MISSING
    known_source: str = MISSING
    pu_known: bool = MISSING
    cnn_a2_from_file: bool = MISSING
    init: InitSettings = field(default_factory=InitSettings)
    stages: list[Any] = MISSING  # {name, channels, n_steps, guard, any solver field}: checked stage by stage
    restarts: RestartSettings = field(default_factory=RestartSettings)
    vehicle: dict[str, float] = MISSING
    occupant: OccupantSettings = field(default_factory=OccupantSettings)
    delay: Any = MISSING  # null | auto | estimate | a number of ms
    delay_max_ms: int = MISSING
    delay_prior_ms: Optional[float] = MISSING
    K3: float = MISSING
    seat_file: Optional[str] = MISSING
    aggregate: Optional[str] = MISSING
    drive: DriveSettings = field(default_factory=DriveSettings)
    overwrite: bool = MISSING
    batch_size: int = MISSING
    block_samples: Optional[int] = MISSING
    gn_device: str = MISSING  # cpu | accelerator
    keep_shards: bool = MISSING
    plots: bool = MISSING
    tensorboard: bool = MISSING
    progress: bool = MISSING


def register() -> None:
    """Store the schema as Hydra's ``schema/estimate`` (configs/estimate.yaml's defaults list takes it)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group="schema", name="estimate", node=EstimateSettings, package="_global_")


register()


def check_overrides(args) -> None:
    """The command line's `key=value` overrides against the schema, before Hydra composes: an unknown key
    (without `+`) or a value of the wrong type is one ConfigError line naming the key and value."""
    check_overrides_against(EstimateSettings, args, "estimate")


def check(cfg) -> None:
    """The composed config against the schema: unknown keys (also those added with `+key=`) and wrongly
    typed values, one ConfigError line naming the key and value; then init.equation_error, which the
    quarter car takes as true or false (a half / full car also as seats: its plan checks that)."""
    check_settings_against(EstimateSettings, cfg, "estimate")
    if str(cfg.get("vehicle_model", "quarter_car")) == "quarter_car":
        value = (cfg.get("init") or {}).get("equation_error", False)
        if not isinstance(value, bool):
            raise ConfigError(f"init.equation_error={value!r}: give true or false")


__all__ = ["EstimateSettings", "check", "check_overrides", "register"]
