"""qcm-estimate's plan for the half car and the full car (experiment=hcm_full_observation | fcm_full_observation):
every setting and input checked before any work (:func:`validate_vehicle`, one line per bad input), the
file's blocks (:class:`VehicleBlocks`) and the GN stages on them (:func:`build_vehicle_refinement`). The
run itself is estimation/vehicle_runner.py.

The model is physics/vehicle_model.VehicleModel of the file's own layout (its seats, tyre damping),
every acceleration observed and every wheel's road known; θ = (the physical parameters, x0).
``known`` names parameters held at their values (known_source: the file's truth or the reference
sedan); a base name (k3) holds it for every seat.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hybridqcm import config
from hybridqcm.data.hdf5 import dataset_info, read_split
from hybridqcm.data.vehicle_files import (
    apply_sensor,
    check_vehicle_physical,
    sensor_std,
    uniform_sensor,
    vehicle_layout,
    vehicle_of,
)
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation import settings as estimate_settings
from hybridqcm.estimation.draws import NormalStream
from hybridqcm.estimation.hold import HOLDS
from hybridqcm.estimation.plan_settings import check_spline_degree, interval_settings, solver_settings
from hybridqcm.estimation.refinement import GaussNewtonStage, RefinementSettings
from hybridqcm.estimation.response import ExactResponse
from hybridqcm.estimation.restarts import Restarts
from hybridqcm.estimation.shards import BlockRefinement
from hybridqcm.estimation.solver import build_solver
from hybridqcm.estimation.weighting import NoiseWeighting
from hybridqcm.physics.sedan import reference_physical
from hybridqcm.physics.vehicle_geometry import VehicleLayout
from hybridqcm.physics.vehicle_model import VehicleModel

INPUT_MARGIN = (4, 8)  # input samples before and after the GN window (the spline hold's edges)


def _known_names(cfg, layout: VehicleLayout, model: VehicleModel) -> list[str]:
    """The model parameters named by ``known`` (a seat quantity's base name, e.g. k3, names every seat's)."""
    out = []
    for name in [str(n) for n in (cfg.get("known") or [])]:
        matches = [
            n
            for n in model.param_names
            if n == name or (n.startswith(name + "_") and name in ("m3", "k3", "c3", "x_s", "y_s"))
        ]
        if not matches:
            raise ConfigError(
                f"known: {name!r} is not a parameter of the file's {layout.kind}; its parameters are {list(model.param_names)}"
            )
        out += [n for n in matches if n not in out]
    if len(out) == len(model.param_names):
        raise ConfigError(f"known lists all {len(out)} parameters of the {layout.kind}: nothing left to estimate")
    if not any(n not in layout.signed_names and not n.startswith(("l_", "w_")) for n in out):
        # docs/design/vehicles.md, "What the data identify": M, C, K, F times one factor leave every acceleration
        raise ConfigError(
            f"known={out}: one common factor of every mass, inertia, stiffness and damping is not in the data; "
            f"hold one of them known (the experiments hold the seats' k3: known=[k3])"
        )
    return out


def _check_settings(cfg) -> tuple[str, str, int, str]:
    """The settings alone, before the file is opened: (vehicle kind, experiment name, spline degree, initial_state)."""
    estimate_settings.check(cfg)  # init.equation_error: true, false or seats, checked below
    config.check_trainer_settings(cfg.get("trainer"))
    config.check_task_name(cfg.get("task_name", "estimate"))
    kind = str(cfg.vehicle_model)
    if kind not in ("half_car", "full_car"):
        raise ConfigError(f"vehicle_model={kind!r}: choose quarter_car, half_car or full_car")
    name = cfg.get("experiment_name", "custom")
    for key in ("cnn_ckpt", "unet_ckpt", "cae_ckpt"):
        if cfg.get(key):
            raise ConfigError(f"{key}={cfg[key]!r}: the {kind} is fully observed; no network is used (drop {key})")
    if cfg.get("base_excitation") is not None:
        raise ConfigError(
            f"base_excitation={cfg.base_excitation!r} with vehicle_model={kind}: the road-free seat estimate on a "
            f"{kind} file is experiment=occupant_roadfree seat=<name>"
        )
    if float(cfg.noise_sigma) != 0:
        raise ConfigError(f"noise_sigma={cfg.noise_sigma}: the {kind} takes sensor=additive|multiplicative instead")
    if str(cfg.dynamics) == "euler":
        raise ConfigError(f"dynamics=euler: the {kind} is fitted by its exact continuous-time model only")
    if cfg.get("seat") is not None:
        raise ConfigError(f"seat={cfg.seat!r}: {name} fits every seat of the {kind} at once (drop seat=)")
    models = (cfg.get("occupant") or {}).get("models", ["rigid"])
    if models is None or isinstance(models, str) or [str(m) for m in models] != ["rigid"]:
        raise ConfigError(
            f"occupant.models={models}: the {kind}'s model seats rigid occupants; a seated person's body modes are "
            f"fitted per seat without the road (experiment=occupant_roadfree seat=<name>)"
        )
    delay = cfg.get("delay", None)
    if delay is not None:
        raise ConfigError(
            f"delay={delay!r}: the {kind} is fitted on one clock; the channel delay is estimated per seat without "
            f"the road (experiment=occupant_roadfree seat=<name>)"
        )
    if cfg.known_source not in ("file", "reference"):
        raise ConfigError(f"known_source={cfg.known_source!r}: choose file or reference")
    if cfg.n_samples is not None and int(cfg.n_samples) < 1:
        raise ConfigError(f"n_samples must be >= 1 (or null for all), got {cfg.n_samples}")
    if int(cfg.batch_size) < 1:
        raise ConfigError(f"batch_size must be >= 1, got {cfg.batch_size}")
    if str(cfg.hold) not in HOLDS or int(cfg.substeps) < 1:
        raise ConfigError(f"hold={cfg.hold!r}, substeps={cfg.substeps}: hold is spline, foh or zoh and substeps >= 1")
    degree = check_spline_degree(cfg)
    if cfg.init.get("equation_error", False) not in (False, True, "seats"):
        raise ConfigError(f"init.equation_error={cfg.init.equation_error!r}: choose false, true (every row) or seats")
    initial = str(cfg.initial_state)
    if initial not in ("auto", "unknown", "rest"):
        raise ConfigError(f"initial_state={initial!r}: choose auto, unknown or rest")
    return kind, name, degree, initial


def _check_file(cfg, kind: str, name: str) -> dict:
    """The file against the settings: its vehicle, layout, arrays and size; the known parameters. Returns
    the plan's entries path, split, info, layout, model, has_truth, known, n_samples and the stored steps."""
    path = Path(str(cfg.data.path))
    info = dataset_info(path)
    split = str(cfg.data.split)
    if split not in info["splits"]:
        raise DatasetError(f"{path}: split {split!r} not found; available splits: {sorted(info['splits'])}")
    held = vehicle_of(info)
    if held != kind:
        raise DatasetError(
            f"{path}: attribute vehicle = {held!r} (a {held.replace('_', ' ')} file), but experiment {name} "
            f"estimates a {kind} (vehicle_model={kind})"
        )
    layout = vehicle_layout(path, split, info)  # the dofs / wheels / names of its arrays checked too
    model = VehicleModel(layout)
    keys = info["splits"][split]["keys"]
    needed = ["accel", "road"] + (["road_vel"] if layout.tyre_damping else [])
    missing = [k for k in needed if k not in keys]
    if missing:
        raise DatasetError(
            f"{path}: /{split} lacks {missing}, which the {kind}'s full observation needs (it has {keys})"
        )
    n_total = int(info["splits"][split]["n_samples"])
    stored = int(info["splits"][split]["n_steps"] or 0)
    if n_total == 0:
        raise DatasetError(f"{path}: /{split} is empty (0 samples); nothing to estimate")
    if cfg.n_samples is not None and int(cfg.n_samples) > n_total:
        raise ConfigError(f"n_samples={cfg.n_samples} but {path} /{split} holds {n_total} samples")
    n_samples = n_total if cfg.n_samples is None else int(cfg.n_samples)
    has_truth = "physical" in keys
    if has_truth:
        physical = read_split(path, split, ("physical",), index=slice(0, n_samples))["physical"]
        check_vehicle_physical(path, split, layout, physical)
    known = _known_names(cfg, layout, model)
    if known and cfg.known_source == "file" and not has_truth:
        raise DatasetError(
            f"{path}: /{split} has no 'physical', so the known {known} cannot come from the file; "
            f"set known_source=reference to take them from the reference sedan"
        )
    return {
        "path": path,
        "split": split,
        "info": info,
        "layout": layout,
        "model": model,
        "has_truth": has_truth,
        "known": known,
        "n_samples": n_samples,
        "stored": stored,
    }


def _window(cfg, path: Path, split: str, stored: int) -> tuple[int, tuple[int, int]]:
    """(GN window length n_steps, the input samples read before and after it) within the ``stored`` steps."""
    before, after = INPUT_MARGIN
    if str(cfg.n_steps) == "max":
        n_steps = stored - before - after
    else:
        try:
            n_steps = int(cfg.n_steps)
        except (TypeError, ValueError):
            raise ConfigError(f"n_steps={cfg.n_steps!r}: give a number of samples >= 2 or max") from None
    if n_steps < 2:
        raise ConfigError(f"n_steps must be >= 2, got {n_steps}")
    if n_steps + before > stored:
        raise DatasetError(
            f"{path}: n_steps = {n_steps} (+ {before} input samples before) but /{split} stores {stored}"
        )
    return n_steps, (before, max(0, min(after, stored - n_steps - before)))


def _stages(cfg, initial: str) -> list[dict]:
    """The GN stages {name, method, settings, n_steps}; the last one carries the interval settings."""
    stages = []
    for i, stage in enumerate(cfg.stages):
        stage = dict(stage)
        stage_name = str(stage.pop("name", f"stage{i}"))
        stage.pop("channels", None)  # every acceleration is observed
        window = stage.pop("n_steps", None)
        stage.pop("guard", None)
        method, settings = solver_settings(cfg, stage)
        if i == len(cfg.stages) - 1:
            settings = {**interval_settings(cfg), **settings}
            if settings.get("covariance") == "auto":  # the road is known and the residual whitened: model
                settings["covariance"] = "model"
        if window is not None and int(window) < int(cfg.get("min_window_unknown_state", 30)) and initial != "rest":
            continue  # x0 unknown: short continuation windows hold more unknowns than data (as the quarter car)
        stages.append(
            {
                "name": stage_name,
                "method": method,
                "settings": settings,
                "n_steps": None if window is None else int(window),
            }
        )
    if not stages:
        raise ConfigError("stages is empty: give at least one GN stage")
    return stages


def _sensor(cfg, kind: str, layout: VehicleLayout):
    """The simulated sensor (sensor=), one law for every channel of the vehicle."""
    from hybridqcm.data.sensor import build_sensor

    try:
        sensor = build_sensor(cfg.get("sensor"))
    except ValueError as error:
        raise ConfigError(str(error)) from None
    reason = uniform_sensor(sensor)
    if reason is not None:
        raise ConfigError(f"{reason}: the {kind}'s {layout.n_dof} channels are not the quarter car's a3, a2, a1")
    return sensor


def validate_vehicle(cfg) -> dict:
    """Every setting and input checked before any work; returns the plan. ConfigError/DatasetError otherwise."""
    kind, name, degree, initial = _check_settings(cfg)
    found = _check_file(cfg, kind, name)
    layout, model, stored = found["layout"], found["model"], found["stored"]
    reference = model.model_params(reference_physical(layout)[None])[0]  # the start's centre (and known_source)
    n_steps, margin = _window(cfg, found["path"], found["split"], stored)
    stages = _stages(cfg, initial)
    sensor = _sensor(cfg, kind, layout)
    return {
        "path": found["path"],
        "split": found["split"],
        "layout": layout,
        "model": model,
        "has_truth": found["has_truth"],
        "known": found["known"],
        "reference": reference,
        "n_samples": found["n_samples"],
        "n_steps": n_steps,
        "n_read_steps": min(stored, margin[0] + n_steps + margin[1]),
        "input_margin": margin,
        "h": float(found["info"]["attrs"].get("h", 0.01)),
        "stages": stages,
        "sensor": sensor,
        "initial_state": "rest" if initial == "rest" else "unknown",
        "spline_degree": degree,
    }


# -------------------------------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class VehicleInputSettings:
    seed: int
    init_sigma: float
    known_source: str
    noise_weighting: bool


class VehicleBlocks(torch.utils.data.Dataset):
    """Item k = block ``blocks[k]`` of the split: {"accel" [b, T, n_dof], "inputs" [b, T, n_in], "init" [b, P],
    "index", "true" [b, P] (with the file's parameters), "noise_std" (known sensor), "block"}.

    Initial guesses p0 = reference (1 + σ δ), δ rows of one seeded draw [M, P] (any block reads its own
    rows: estimation/draws.NormalStream); known parameters at the file's (or the sedan's) values."""

    def __init__(self, settings: VehicleInputSettings, plan: dict, blocks: list[tuple[int, int, int]]):
        self.settings, self.plan, self.blocks = settings, dict(plan), list(blocks)
        self._delta = None

    def __len__(self) -> int:
        return len(self.blocks)

    def __getitem__(self, k: int) -> dict:
        block, start, stop = self.blocks[k]
        plan, settings = self.plan, self.settings
        model: VehicleModel = plan["model"]
        layout: VehicleLayout = plan["layout"]
        P = len(model.param_names)
        if self._delta is None:
            self._delta = NormalStream(settings.seed, int(plan["n_samples"]) * P)
        keys = (
            ["accel", "road"]
            + (["road_vel"] if layout.tyre_damping else [])
            + (["physical"] if plan["has_truth"] else [])
        )
        arrays = read_split(plan["path"], plan["split"], keys, n_steps=plan["n_read_steps"], index=slice(start, stop))
        accel = torch.from_numpy(np.asarray(arrays["accel"], dtype=np.float64))
        inputs = torch.from_numpy(np.asarray(arrays["road"], dtype=np.float64))
        if layout.tyre_damping:
            inputs = torch.cat([inputs, torch.from_numpy(np.asarray(arrays["road_vel"], dtype=np.float64))], -1)
        m = accel.shape[0]
        index = torch.arange(start, stop)
        true = (
            model.model_params(torch.from_numpy(np.asarray(arrays["physical"], dtype=np.float64)))
            if plan["has_truth"]
            else None
        )
        reference = plan["reference"].expand(m, P)
        delta = settings.init_sigma * torch.from_numpy(self._delta.take(start * P, stop * P)).reshape(m, P)
        init = reference * (1.0 + delta)
        positive = torch.tensor([n not in model.signed_params for n in model.param_names])
        init = torch.where(positive & (init <= 0), reference, init)
        known_values = true if (true is not None and settings.known_source == "file") else reference
        for name in plan["known"]:
            j = model.param_names.index(name)
            init[:, j] = known_values[:, j]
        batch = {"accel": accel, "inputs": inputs, "init": init, "index": index, "block": int(block)}
        if true is not None:
            batch["true"] = true
        sensor = plan["sensor"]
        if sensor.active:
            batch["accel"] = apply_sensor(sensor, accel, index)
            if settings.noise_weighting:
                batch["noise_std"] = sensor_std(sensor, accel).clamp_min(1e-12)
        return batch


# -------------------------------------------------------------------------------------------------- refinement
class VehicleRefinement(BlockRefinement):
    """The GN stages on a road-driven vehicle: its inputs (the road) are known exactly, so the spectral
    noise model of the last stage is white output noise per channel only (NoiseWeighting.input_noise=False,
    build_vehicle_refinement)."""


def build_vehicle_refinement(cfg, plan: dict) -> VehicleRefinement:
    model: VehicleModel = plan["model"]
    response = ExactResponse(
        model, plan["h"], str(cfg.hold), int(cfg.substeps), plan["initial_state"], plan["spline_degree"]
    )
    known = torch.tensor([n in plan["known"] for n in model.param_names])
    stages = [
        GaussNewtonStage(s["name"], build_solver(s["method"], **s["settings"]), "all", s["n_steps"])
        for s in plan["stages"]
    ]
    reweight = str(cfg.residual_weighting)
    reweight = (
        "spectral" if reweight == "auto" else (reweight if reweight == "spectral" else reweight.lower() == "true")
    )
    return VehicleRefinement(
        stages,
        RefinementSettings(
            known=known,
            h=plan["h"],
            response=response,
            peer_factor=cfg.get("misfit_peer_factor", 10.0),
            x0_start=str(cfg.get("x0_start", "alternate")),
        ),
        noise=NoiseWeighting(mode=reweight, input_noise=False),
        restarts=Restarts(
            count=int(cfg.restarts.count),
            threshold=math.inf,  # the exact model's loss floor is its hold error: restarts go by status
            sigma=float(cfg.restarts.sigma),
            seed=int(cfg.seed),
            batch=int(cfg.restarts.get("batch", 64)),
            failed=int(cfg.restarts.get("failed", 0)),
        ),
    )


__all__ = [
    "INPUT_MARGIN",
    "validate_vehicle",
    "VehicleInputSettings",
    "VehicleBlocks",
    "VehicleRefinement",
    "build_vehicle_refinement",
]
