"""qcm-estimate's plan: every setting and input checked before any work, resolved once.

``validate(cfg)`` reads the config, the dataset's layout and the checkpoints (once, through the
safe loader) and returns the EstimationPlan the run is built from: file, split, rows, window, model,
initial state, stages, sensor and input margins. Every bad input (unknown or non-estimation
experiment, missing/wrong-kind checkpoint, a key or channel the pipeline needs but the file lacks,
a window longer than the stored steps) is one ConfigError/DatasetError line naming the file, key
and value.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, TypedDict

from hybridqcm import config
from hybridqcm.errors import ConfigError
from hybridqcm.estimation import settings as estimate_settings
from hybridqcm.estimation.hold import HOLDS
from hybridqcm.estimation.plan_networks import network_plan, network_windows
from hybridqcm.estimation.plan_settings import (
    check_positive_params,
    check_spline_degree,
    interval_settings,
    param_index,
    resolve_covariance,
    resolve_model,
    solver_settings,
    vehicle_prior_settings,
    window_check_settings,
)
from hybridqcm.physics.parameters import CHANNELS, PARAM_NAMES


# --------------------------------------------------------------------------------------------------
class EstimationPlan(TypedDict):
    """The resolved run (``validate``'s result): what every later step reads instead of the config.

    path, split: the dataset and split; n_samples recordings of n_steps steps at period h [s], each read
    with input_margin (before, after) steps around the window (n_read_steps in all, the CNN's window
    included); has_params: the file holds the true p [M, 10]; observed: the measured channels (of
    CHANNELS); known: indices into PARAM_NAMES held fixed; n_params: the model's parameter count (10,
    fewer for the road-free models of base_excitation); model (exact | euler) and initial_state (rest |
    unknown) resolved for this file; x0_start; stages: GN stages {name, channels, method, settings
    (SolverConfig fields, the last with the intervals'), n_steps, guard}; completes: a U-Net completes
    a2, a1; windows: the networks' windows by checkpoint key; vehicle_prior (vehicle_prior_settings);
    restarts_around (start | reference); occupant (plan_occupant.occupant_plan, None: one rigid
    model); seat: a seat of a half / full car file (plan_seat) or None; sensor: the data.sensor model.
    """

    path: Path
    split: str
    has_params: bool
    known: list[int]
    observed: list[str]
    stages: list[dict]
    n_read_steps: int
    n_samples: int
    h: float
    completes: bool
    windows: dict[str, int]
    model: str
    initial_state: str
    x0_start: str
    vehicle_prior: dict | None
    restarts_around: str
    base_excitation: str | None
    n_params: int
    occupant: dict | None
    seat: str | None
    sensor: Any
    input_margin: tuple[int, int]
    n_steps: int


def validate(cfg, layout: dict | None = None) -> EstimationPlan:
    """Check every input before any work; returns the resolved plan. Raises ConfigError/DatasetError.

    The sections in the order a run meets them (the first bad input is the one reported): the run's
    settings, channels and known parameters, the road-free model, blocks and restarts, the GN stages,
    the checkpoints, the dataset, the networks against the file, the window and its input margins.
    ``layout``: recordings in memory instead of cfg.data's file (dataset_plan's dict: arrays.array_layout)."""
    n_steps, longest, sigma = run_settings(cfg)
    observed, known = channel_plan(cfg)
    base, n_params = base_excitation_plan(cfg, observed, known)
    around = restart_settings(cfg)
    stages = stage_plans(cfg)
    networks, completes = network_plan(cfg, observed, stages)
    data = dataset_plan(cfg, base, known) if layout is None else layout
    windows, needed = network_windows(cfg, networks, data, n_steps)
    window = window_plan(cfg, data, base, n_steps, longest, sigma, needed)
    model, initial_state = window["model"], window["initial_state"]
    if around == "auto":  # the exact model is for real recordings; Euler keeps the source's protocol
        around = "reference" if model == "exact" else "start"
    stages = _resolve_stages(cfg, stages, model, base, initial_state)
    x0_start = _check_model_settings(cfg, window["occupant"])
    return {
        "path": data["path"],
        "split": data["split"],
        "has_params": data["has_params"],
        "known": known,
        "observed": observed,
        "stages": stages,
        "n_read_steps": window["needed"],
        "n_samples": window["n_samples"],
        "h": data["h"] or 0.01,
        "completes": completes,
        "windows": windows,
        "model": model,
        "initial_state": initial_state,
        "x0_start": x0_start,
        "vehicle_prior": vehicle_prior_settings(cfg),
        "restarts_around": around,
        "base_excitation": base,
        "n_params": n_params,
        "occupant": window["occupant"],
        "seat": None if data["seat_view"] is None else data["seat_view"]["seat"],
        "sensor": window["sensor"],
        "input_margin": window["margin"],
        "n_steps": window["n_steps"],
    }


def run_settings(cfg) -> tuple[int, bool, float]:
    """The settings of the run as a whole (known keys and their types, trainer, window check,
    window length, weighting, noise, sample count) -> (n_steps, longest: n_steps=max, noise_sigma)."""
    estimate_settings.check(cfg)
    config.check_trainer_settings(cfg.get("trainer"))
    window_check_settings(cfg)
    config.check_task_name(cfg.get("task_name", "estimate"))
    longest = str(cfg.n_steps) == "max"  # the longest window the file holds, resolved by window_plan
    try:
        n_steps = 2 if longest else int(cfg.n_steps)
    except (TypeError, ValueError):
        raise ConfigError(f"n_steps={cfg.n_steps!r}: give a number of samples >= 2 or max") from None
    if n_steps < 2:
        raise ConfigError(f"n_steps must be >= 2, got {cfg.n_steps}")
    if str(cfg.get("residual_weighting", "auto")) not in ("auto", "spectral", "True", "False", "true", "false"):
        raise ConfigError(f"residual_weighting={cfg.residual_weighting!r}: choose auto, spectral, true or false")
    sigma = float(cfg.noise_sigma)
    if not math.isfinite(sigma) or sigma < 0:
        raise ConfigError(f"noise_sigma must be a finite value >= 0, got {cfg.noise_sigma}")
    if cfg.n_samples is not None and int(cfg.n_samples) < 1:
        raise ConfigError(f"n_samples must be >= 1 (or null for all), got {cfg.n_samples}")
    return n_steps, longest, sigma


def channel_plan(cfg) -> tuple[list[str], list[int]]:
    """(observed channels, indices of the known parameters), checked."""
    observed = [str(c) for c in cfg.observed]
    bad = [c for c in observed if c not in CHANNELS]
    if bad or not observed:
        raise ConfigError(f"observed={observed}: channels must be a non-empty subset of {list(CHANNELS)}")
    known = param_index(cfg.known, "known")
    if len(known) == 10:
        raise ConfigError("known lists all 10 parameters: nothing left to estimate")
    return observed, known


def base_excitation_plan(cfg, observed: list[str], known: list[int]) -> tuple[str | None, int]:
    """(base_excitation, n_params): the road-free model driven by a measured channel (seat, sprung) and
    its parameter count, or (None, 10) for the road-driven quarter car."""
    base = cfg.get("base_excitation")
    if base is None:
        return None, 10
    from hybridqcm.estimation.front import BASE_EXCITATION

    if base not in BASE_EXCITATION:
        raise ConfigError(f"base_excitation={base!r}: choose one of {sorted(BASE_EXCITATION)} or null (road-driven)")
    driver, outputs, n_params = BASE_EXCITATION[base]
    missing = [c for c in (driver, *outputs) if c not in observed]
    if missing:
        raise ConfigError(
            f"base_excitation={base} is driven by the measured {driver} and fits {list(outputs)}: "
            f"observed={observed} lacks {missing}"
        )
    if any(j >= n_params for j in known):
        raise ConfigError(f"known={list(cfg.known)}: the {base} model holds only p1..p{n_params}")
    if str(cfg.dynamics) == "euler":
        raise ConfigError(
            f"base_excitation={base} uses the exact continuous-time model: dynamics=euler is not available"
        )
    if str(cfg.initial_state) == "rest":
        raise ConfigError(
            f"base_excitation={base}: the initial relative state is always estimated (initial_state=unknown)"
        )
    return base, n_params


def restart_settings(cfg) -> str:
    """known_source, the blocks (batch_size, block_samples) and the restarts group checked; returns
    restarts.around (auto | start | reference; auto is resolved with the model)."""
    if cfg.known_source not in ("file", "reference"):
        raise ConfigError(f"known_source={cfg.known_source!r}: choose file or reference")
    if int(cfg.batch_size) < 1:
        raise ConfigError(f"batch_size must be >= 1, got {cfg.batch_size}")
    block_samples = cfg.get("block_samples")
    if block_samples is not None and (
        isinstance(block_samples, bool) or not isinstance(block_samples, int) or block_samples < 1
    ):
        raise ConfigError(
            f"block_samples must be an integer >= 1 (time steps per block) or null, got {block_samples!r}"
        )
    restart_batch = cfg.restarts.get("batch", 64)
    if isinstance(restart_batch, bool) or not isinstance(restart_batch, int) or restart_batch < 1:
        raise ConfigError(f"restarts.batch must be an integer >= 1, got {restart_batch!r}")
    restart_failed = cfg.restarts.get("failed", 0)
    if isinstance(restart_failed, bool) or not isinstance(restart_failed, int) or restart_failed < 0:
        raise ConfigError(f"restarts.failed must be an integer >= 0, got {restart_failed!r}")
    far = cfg.restarts.get("far_from_start")
    if far is not None and (isinstance(far, bool) or not isinstance(far, int | float) or not far > 0):
        raise ConfigError(f"restarts.far_from_start must be null or a number > 0, got {far!r}")
    around = str(cfg.restarts.get("around", "start"))
    if around not in ("auto", "start", "reference"):
        raise ConfigError(f"restarts.around={around!r}: choose auto, start or reference")
    return around


def stage_plans(cfg) -> list[dict]:
    """The GN stages: {name, channels, method, settings, n_steps, guard} each, the solver group with the
    stage's overrides (solver_settings); the last stage also carries the intervals' settings."""
    stages = []
    for i, stage in enumerate(cfg.stages):
        stage = dict(stage)
        name = str(stage.pop("name", f"stage{i}"))
        channels = stage.pop("channels", "all")
        window = stage.pop("n_steps", None)
        guard = bool(stage.pop("guard", False))
        if window is not None and not 2 <= int(window):
            raise ConfigError(f"stages[{i}].n_steps must be >= 2 (or null for n_steps), got {window}")
        method, settings = solver_settings(cfg, stage)
        if i == len(cfg.stages) - 1:  # only the last stage's intervals are reported
            settings = {**interval_settings(cfg), **settings}
        stages.append(
            {
                "name": name,
                "channels": channels if isinstance(channels, str) else list(channels),
                "method": method,
                "settings": settings,
                "n_steps": None if window is None else int(window),
                "guard": guard,
            }
        )
    if not stages:
        raise ConfigError("stages is empty: give at least one GN stage")
    return stages


def dataset_plan(cfg, base: str | None, known: list[int]) -> dict:
    """The dataset's split, keys and accel layout (NaNs are checked when reading: read_split names the
    index) -> {path, split, info, seat_view, has_params, stored (steps), n_total (recordings), h (or None)}."""
    import h5py

    from hybridqcm.data.hdf5 import dataset_info
    from hybridqcm.errors import DatasetError
    from hybridqcm.estimation.plan_seat import seat_view_plan

    path = Path(str(cfg.data.path))
    info = dataset_info(path)
    split = str(cfg.data.split)
    if split not in info["splits"]:
        raise DatasetError(f"{path}: split {split!r} not found; available splits: {sorted(info['splits'])}")
    seat_view = seat_view_plan(cfg, path, split, info, base)  # a seat of a half / full car file (issue 30)
    keys = info["splits"][split]["keys"] if seat_view is None else seat_view["keys"]
    for key in ("accel",) + (("road",) if base is None else ()):
        if key not in keys:
            raise DatasetError(f"{path}: /{split} lacks dataset {key!r}, which GN needs (it has {keys})")
    has_params = "params" in keys
    if not has_params and known and cfg.known_source == "file":
        raise DatasetError(
            f"{path}: /{split} has no 'params', so the known parameters {[PARAM_NAMES[i] for i in known]} "
            f"cannot come from the file; set known_source=reference to take them from the vehicle config"
        )
    with h5py.File(path, "r") as handle:
        accel = handle[split]["accel"]
        if not isinstance(accel, h5py.Dataset) or accel.ndim != 3:
            raise DatasetError(
                f"{path}: /{split}/accel is a {type(accel).__name__}"
                f"{'' if not isinstance(accel, h5py.Dataset) else f' of shape {accel.shape}'}, "
                f"not an array [M, n_steps, 3]"
            )
        stored = int(accel.shape[1])
        n_total = int(accel.shape[0])
        h_file = float(handle.attrs["h"]) if "h" in handle.attrs else None
        if n_total == 0:
            raise DatasetError(f"{path}: /{split} is empty (0 samples); nothing to estimate")
        if cfg.n_samples is not None and int(cfg.n_samples) > n_total:
            raise ConfigError(
                f"n_samples={cfg.n_samples} but {path} /{split} holds {n_total} samples "
                f"(use n_samples<={n_total} or null for all)"
            )
        if has_params and seat_view is None:  # a seat view's p1, p2 come from checked physical parameters
            check_positive_params(
                path, split, handle[split]["params"], n_total if cfg.n_samples is None else int(cfg.n_samples)
            )
    return {
        "path": path,
        "split": split,
        "info": info,
        "seat_view": seat_view,
        "has_params": has_params,
        "stored": stored,
        "n_total": n_total,
        "h": h_file,
    }


def window_plan(cfg, data: dict, base: str | None, n_steps: int, longest: bool, sigma: float, needed: int) -> dict:
    """The model for this file, the sensor, the occupant plan and the window with its input margins
    (the exact model interpolates the input: it reads the file around the window) ->
    {n_samples, model, initial_state, sensor, occupant, n_steps, margin, needed (steps read)}."""
    from hybridqcm.data.sensor import build_sensor
    from hybridqcm.estimation.plan_occupant import delay_margin, occupant_plan

    n_samples = data["n_total"] if cfg.n_samples is None else int(cfg.n_samples)
    model, initial_state = resolve_model(cfg, data["info"])
    try:
        sensor = build_sensor(cfg.get("sensor"))
    except ValueError as error:
        raise ConfigError(str(error)) from None
    if sensor.active and sigma > 0:
        raise ConfigError(
            f"noise_sigma={sigma} (the source's multiplicative noise) and sensor={sensor.kind}: choose one"
        )
    occupant = occupant_plan(cfg, base, model)
    # a channel delay reads the input that far beyond the window's ends too
    lead = max(4, delay_margin(cfg, data["h"] or 0.01)) if occupant is not None else 4
    n_steps, margin = _input_margin(cfg, data, base, model, n_steps, longest, lead)
    if occupant is not None and occupant["delay"] is not None and min(margin) < 1:
        stored = data["stored"]
        raise ConfigError(
            f"{data['path']}: delay={cfg.get('delay')!r} reads the input beyond the window's ends, and n_steps={n_steps} "
            f"of the {stored} stored steps leaves input_margin={list(margin)}: give n_steps <= {stored - 2 * lead} or "
            f"delay=null"
        )
    needed = max(needed, min(data["stored"], margin[0] + n_steps + margin[1]))
    if base is not None:  # the road-free models are continuous-time, with their initial state estimated
        model, initial_state = "exact", "unknown"
    return {
        "n_samples": n_samples,
        "model": model,
        "initial_state": initial_state,
        "sensor": sensor,
        "occupant": occupant,
        "n_steps": n_steps,
        "margin": margin,
        "needed": needed,
    }


def _input_margin(cfg, data: dict, base, model: str, n_steps: int, longest: bool, lead: int) -> tuple:
    """(n_steps, (before, after)): n_steps=max resolved to every stored step less the margins;
    input_margin=auto: up to ``lead`` steps before and max(8, lead) after the window, as the file holds."""
    from hybridqcm.errors import DatasetError

    path, stored, margin = data["path"], data["stored"], cfg.get("input_margin", "auto")
    tail = max(8, lead)
    if longest:  # every stored step, less the exact model's input margins
        exact = base is not None or model == "exact"
        n_steps = stored - (lead + tail if exact and str(margin) == "auto" and stored >= lead + tail + 2 else 0)
        if str(margin) != "auto":
            n_steps = stored - sum(int(m) for m in margin)
        if n_steps < 2:
            raise DatasetError(f"{path}: n_steps=max leaves {n_steps} steps of the {stored} stored")
    if str(margin) == "auto":  # the exact model interpolates the input: give it what the file holds around the window
        margin = (
            (0, 0)  # the Euler recursion reads no input beyond its window; the road-free models are exact
            if model == "euler" and base is None
            else (min(lead, stored - n_steps), max(0, min(tail, stored - n_steps - lead)))
        )
    try:
        margin = tuple(int(m) for m in margin)
    except (TypeError, ValueError):
        raise ConfigError(f"input_margin={margin!r}: give auto or [before, after] sample counts") from None
    if len(margin) != 2 or min(margin) < 0:
        raise ConfigError(f"input_margin={list(margin)}: give auto or [before, after] sample counts >= 0")
    if margin[0] + n_steps > stored:
        raise DatasetError(
            f"{path}: input_margin before = {margin[0]} + n_steps = {n_steps} exceed the {stored} stored steps"
        )
    return n_steps, margin


def _resolve_stages(cfg, stages: list[dict], model: str, base: str | None, initial_state: str) -> list[dict]:
    """intervals.covariance=auto resolved for the model; with the initial state unknown, the
    continuation stages too short to pin it down dropped."""
    for stage in stages:  # only the last stage carries the intervals' settings
        if stage["settings"].get("covariance") == "auto":
            stage["settings"]["covariance"] = resolve_covariance(cfg, model, base)
    if initial_state == "unknown":
        # With x0 unknown a short continuation window has up to 6 more unknowns than it can pin
        # down (diverging or stopping in local minima): such stages are skipped.
        shortest = int(cfg.get("min_window_unknown_state", 30))
        stages = [s for s in stages if s["n_steps"] is None or s["n_steps"] >= shortest] or stages[-1:]
    return stages


def _check_model_settings(cfg, occupant: dict | None) -> str:
    """x0_start, the hold and its substeps, the spline degree checked; returns x0_start."""
    from hybridqcm.estimation.initial_state import X0_STARTS

    x0_start = str(cfg.get("x0_start", "rest"))
    if x0_start not in X0_STARTS:
        raise ConfigError(f"x0_start={x0_start!r}: choose one of {list(X0_STARTS)}")
    if str(cfg.hold) not in HOLDS or int(cfg.substeps) < 1:
        raise ConfigError(f"hold={cfg.hold!r}, substeps={cfg.substeps}: hold is spline, foh or zoh and substeps >= 1")
    if check_spline_degree(cfg) != 5 and occupant is not None:  # plan_occupant builds its own (quintic) models
        raise ConfigError(
            f"spline_degree={cfg.spline_degree}: the occupant models and the channel delay use the quintic hold; "
            f"leave spline_degree=5"
        )
    return x0_start


__all__ = [
    "EstimationPlan",
    "base_excitation_plan",
    "channel_plan",
    "dataset_plan",
    "restart_settings",
    "run_settings",
    "stage_plans",
    "validate",
    "window_plan",
]
