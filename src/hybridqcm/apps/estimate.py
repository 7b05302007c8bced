"""qcm-estimate: Gauss-Newton (and hybrid) parameter estimation on an HDF5 dataset (SPEC §7 exps 5-10).

    qcm-estimate experiment=exp5_random_init data.path=FILE [n_samples=2000 noise_sigma=0.05 seed=0]
    qcm-estimate experiment=exp10_hybrid data.path=FILE cnn_ckpt=CKPT unet_ckpt=CKPT hydra.run.dir=DIR

Every bad input (unknown or non-estimation experiment, missing/wrong-kind checkpoint, a key or
channel the pipeline needs but the file lacks, NaN, a window longer than the stored steps) is
reported in one line naming the file, key and value, before any work is done.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from hybridqcm.apps import common, runfolder
from hybridqcm.apps.common import CONFIG_DIR, ConfigError, fail, print_table
from hybridqcm.atomic import atomic_write_csv, atomic_write_text
from hybridqcm.errors import HybridQCMError

PARAM_NAMES = tuple(f"p{i}" for i in range(1, 11))
CHANNELS = ("a3", "a2", "a1")
MODELS = ("auto", "exact", "euler")
INITIAL_STATES = ("auto", "unknown", "rest")


def resolve_model(cfg, info: Mapping) -> tuple[str, str]:
    """(model, initial_state) for this file: ``auto`` follows the file's ``physics`` attribute.

    Files from our Euler generator keep the source's model (from rest, as the reproduction, or with
    the initial state estimated for windows cut mid-drive); everything else — continuous-time
    simulations, files from other producers and real loggers — gets the exact model with the
    initial state estimated.
    """
    model, initial = str(cfg.dynamics), str(cfg.initial_state)
    if model not in MODELS:
        raise ConfigError(f"dynamics={model!r}: choose one of {list(MODELS)}")
    if initial not in INITIAL_STATES:
        raise ConfigError(f"initial_state={initial!r}: choose one of {list(INITIAL_STATES)}")
    physics, file_initial = info["physics"], info["initial_state"]  # rest | mid-drive | unknown
    if model == "auto":
        model = "euler" if physics == "euler" else "exact"
    if initial == "auto":
        initial = "rest" if (model == "euler" and file_initial == "rest") else "unknown"
    return model, initial


def check_experiment_overrides(args: Sequence[str], config_dir: Path = CONFIG_DIR) -> None:
    """Fail early (before Hydra composes: a training experiment would fail there obscurely)."""
    common.check_experiment_overrides(args, "estimate", config_dir)


def _param_index(names: Sequence[str], key: str) -> list[int]:
    out = []
    for name in names:
        if str(name) not in PARAM_NAMES:
            raise ConfigError(f"{key}: {name!r} is not a parameter name (p1..p10)")
        out.append(PARAM_NAMES.index(str(name)))
    return out


def solver_settings(cfg, overrides: Mapping | None = None) -> tuple[str, dict]:
    """(method, SolverConfig kwargs) from the solver group plus per-stage overrides."""
    from dataclasses import fields

    from omegaconf import OmegaConf

    from hybridqcm.estimation.solver import SOLVERS, SolverConfig

    base = OmegaConf.to_container(cfg.solver, resolve=True)
    base.update(dict(overrides or {}))
    method = base.pop("method", "gauss_newton")
    if method not in SOLVERS:
        raise ConfigError(f"solver.method={method!r} is unknown; choose one of {sorted(SOLVERS)}")
    allowed = {f.name for f in fields(SolverConfig)}
    unknown = sorted(set(base) - allowed)
    if unknown:
        raise ConfigError(f"unknown solver setting(s) {unknown}; valid: {sorted(allowed)}")
    if int(base.get("max_iterations", 1)) < 0:
        raise ConfigError(f"solver.max_iterations must be >= 0, got {base['max_iterations']}")
    if float(base.get("initial_step", 1.0)) <= 0:
        raise ConfigError(f"solver.initial_step must be > 0, got {base['initial_step']}")
    return method, base


def coverage_95(estimate: torch.Tensor, truth: torch.Tensor, std: torch.Tensor, failed: torch.Tensor) -> float:
    """Fraction of samples [M] whose truth lies in estimate ± 1.96 std; failed or non-finite ones count as not covered."""
    ok = ~failed & torch.isfinite(estimate) & torch.isfinite(std)
    inside = ok & ((estimate - truth).abs() <= 1.96 * std)
    return float(inside.double().mean())


def check_positive_params(path: Path, split: str, params, n: int) -> None:
    """The file's true parameters must be finite and > 0 (errors are relative to them); DatasetError otherwise."""
    from hybridqcm.data.hdf5 import DatasetError

    values = np.asarray(params[:n], dtype=np.float64)
    if values.ndim != 2 or values.shape[1] != 10:
        raise DatasetError(f"{path}: /{split}/params has shape {values.shape}, expected [M, 10]")
    bad = np.argwhere(~(np.isfinite(values) & (values > 0)))
    if bad.size:
        i, j = (int(x) for x in bad[0])
        raise DatasetError(
            f"{path}: /{split}/params[{i}, {j}] ({PARAM_NAMES[j]}) = {float(values[i, j])!r}; parameters "
            f"must be finite and > 0 ({len(bad)} such values)"
        )


def _known_key_tree() -> dict:
    """Keys qcm-estimate understands: configs/estimate.yaml plus what its experiments and solvers set."""
    import yaml

    def merge(into: dict, data) -> None:
        for k, v in (data or {}).items():
            if isinstance(v, dict) and isinstance(into.get(k, {}), dict):
                merge(into.setdefault(k, {}), v)
            else:
                into.setdefault(k, None)

    tree: dict = {}
    merge(tree, yaml.safe_load((CONFIG_DIR / "estimate.yaml").read_text()))
    for path in sorted((CONFIG_DIR / "experiment").glob("*.yaml")):
        data = yaml.safe_load(path.read_text()) or {}
        if isinstance(data, dict) and data.get("task") == "estimate":
            merge(tree, data)
    for group in ("paths", "hydra", "solver", "experiment", "sensor"):
        tree[group] = None  # groups: their own schemas (checked by solver_settings and build_sensor)
    return tree


# Mappings whose entries are free-form (GN stage lists, vehicle constants are checked where used).
_OPEN_KEYS = ("stages", "vehicle", "defaults")


def check_known_keys(cfg) -> None:
    """Refuse keys qcm-estimate does not know (e.g. `+data.pathh=x`, which would otherwise be ignored)."""
    from omegaconf import DictConfig

    def walk(node, tree, prefix: str) -> None:
        for key in node.keys():
            name = f"{prefix}{key}"
            if key not in tree:
                raise ConfigError(
                    f"unknown setting {name}={node[key]!r} (qcm-estimate does not use it); "
                    f"known under {prefix or 'the top level'}: {sorted(tree)}"
                )
            sub = tree[key]
            if isinstance(sub, dict) and key not in _OPEN_KEYS and isinstance(node[key], DictConfig):
                walk(node[key], sub, f"{name}.")

    walk(cfg, _known_key_tree(), "")


# --------------------------------------------------------------------------------------------------
def validate(cfg) -> dict:
    """Check every input before any work; returns the resolved plan. Raises ConfigError/DatasetError."""
    from hybridqcm.data.hdf5 import DatasetError, dataset_info
    from hybridqcm.estimation.fusion import check_cnn_prior
    from hybridqcm.estimation.hybrid import CheckpointKindError, check_networks, load_network

    check_known_keys(cfg)
    common.check_task_name(cfg.get("task_name", "estimate"))
    if cfg.get("task") != "estimate":
        raise ConfigError(f"task={cfg.get('task')!r}: qcm-estimate runs estimation experiments (task: estimate)")
    longest = str(cfg.n_steps) == "max"  # the longest window the file holds, resolved below
    try:
        n_steps = 2 if longest else int(cfg.n_steps)
    except (TypeError, ValueError):
        raise ConfigError(f"n_steps={cfg.n_steps!r}: give a number of samples >= 2 or max") from None
    if n_steps < 2:
        raise ConfigError(f"n_steps must be >= 2, got {cfg.n_steps}")
    sigma = float(cfg.noise_sigma)
    if not math.isfinite(sigma) or sigma < 0:
        raise ConfigError(f"noise_sigma must be a finite value >= 0, got {cfg.noise_sigma}")
    if cfg.n_samples is not None and int(cfg.n_samples) < 1:
        raise ConfigError(f"n_samples must be >= 1 (or null for all), got {cfg.n_samples}")
    observed = [str(c) for c in cfg.observed]
    bad = [c for c in observed if c not in CHANNELS]
    if bad or not observed:
        raise ConfigError(f"observed={observed}: channels must be a non-empty subset of {list(CHANNELS)}")
    known = _param_index(cfg.known, "known")
    if len(known) == 10:
        raise ConfigError("known lists all 10 parameters: nothing left to estimate")
    base = cfg.get("base_excitation")
    n_params = 10
    if base is not None:
        from hybridqcm.estimation.hybrid import BASE_EXCITATION

        if base not in BASE_EXCITATION:
            raise ConfigError(
                f"base_excitation={base!r}: choose one of {sorted(BASE_EXCITATION)} or null (road-driven)"
            )
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
    if cfg.known_source not in ("file", "reference"):
        raise ConfigError(f"known_source={cfg.known_source!r}: choose file or reference")
    if int(cfg.batch_size) < 1:
        raise ConfigError(f"batch_size must be >= 1, got {cfg.batch_size}")

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

    # Checkpoints: present, readable, of the right kind — and the ones the experiment needs.
    # Loaded once, through the one safe loader (models.checkpoint): weights_only, allow-list, strict keys.
    kinds = {"cnn_ckpt": "cnn", "unet_ckpt": "unet", "cae_ckpt": "cae"}
    networks = {}
    for key, kind in kinds.items():
        if cfg.get(key):
            try:
                networks[key] = load_network(cfg[key], kind, key)
            except CheckpointKindError as error:
                raise ConfigError(str(error)) from None
    if cfg.init.cnn and not cfg.cnn_ckpt:
        raise ConfigError(
            f"experiment {cfg.experiment_name} initialises p1, p2 with the CNN: give cnn_ckpt=PATH "
            f"(or init.cnn=false for a random init)"
        )
    completes = bool(cfg.unet_ckpt) and not {"a2", "a1"} <= set(observed)
    if cfg.init.equation_error and not (completes or set(observed) == set(CHANNELS)):
        raise ConfigError(
            f"init.equation_error needs all three accelerations: observe them or give unet_ckpt=PATH "
            f"(observed={observed})"
        )
    for stage in stages:  # explicit channel lists must be measured or completed
        if not isinstance(stage["channels"], str):
            available = set(observed) | ({"a2", "a1"} if completes else set())
            missing = [c for c in stage["channels"] if c not in available]
            if missing:
                raise ConfigError(
                    f"stage {stage['name']!r} uses channels {missing}, which are neither observed "
                    f"(observed={observed}) nor completed by a U-Net"
                )
        elif stage["channels"] not in ("all", "observed"):
            raise ConfigError(f"stage {stage['name']!r}: channels={stage['channels']!r}; use all, observed or a list")
    if cfg.init.cnn and "a2" not in observed and not completes and not cfg.cnn_a2_from_file:
        raise ConfigError(
            "the CNN initialiser reads a2, which is not observed: give unet_ckpt=PATH to complete it "
            "(or cnn_a2_from_file=true to use the file's a2 for the initial guess only)"
        )
    if cfg.cae_ckpt and "a2" not in observed and not completes:
        raise ConfigError("cae_ckpt denoises (a3, a2) but a2 is neither observed nor completed (give unet_ckpt)")

    # Dataset: split, keys, window; NaNs are checked when reading (read_split names the index).
    path = Path(str(cfg.data.path))
    info = dataset_info(path)
    split = str(cfg.data.split)
    if split not in info["splits"]:
        raise DatasetError(f"{path}: split {split!r} not found; available splits: {sorted(info['splits'])}")
    keys = info["splits"][split]["keys"]
    for key in ("accel",) + (("road",) if base is None else ()):
        if key not in keys:
            raise DatasetError(f"{path}: /{split} lacks dataset {key!r}, which GN needs (it has {keys})")
    has_params = "params" in keys
    if not has_params and known and cfg.known_source == "file":
        raise DatasetError(
            f"{path}: /{split} has no 'params', so the known parameters {[PARAM_NAMES[i] for i in known]} "
            f"cannot come from the file; set known_source=reference to take them from the vehicle config"
        )
    import h5py

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
        if has_params:
            check_positive_params(
                path, split, handle[split]["params"], n_total if cfg.n_samples is None else int(cfg.n_samples)
            )
    try:
        check_networks(
            networks.get("cnn_ckpt") if cfg.init.cnn else None,
            networks.get("unet_ckpt"),
            networks.get("cae_ckpt"),
            h_file or 0.01,
        )
    except CheckpointKindError as error:
        raise ConfigError(str(error)) from None
    try:  # init.cnn_prior=network: the CNN must predict its variance (estimation/fusion.py)
        check_cnn_prior(
            cfg.init.get("cnn_prior"),
            networks.get("cnn_ckpt") if cfg.init.cnn else None,
            cfg.init.get("cnn_prior_rel_std"),
        )
    except ValueError as error:
        raise ConfigError(str(error)) from None
    needed = n_steps
    windows = {}
    for key in ("cnn_ckpt", "unet_ckpt", "cae_ckpt"):
        if key in networks and (key != "cnn_ckpt" or cfg.init.cnn):
            windows[key] = int(networks[key].hparams.window)
    if cfg.init.cnn:
        needed = max(needed, windows.get("cnn_ckpt", n_steps))
    if needed > stored:
        what = "n_steps" if needed == n_steps else f"the CNN window ({needed})"
        raise DatasetError(f"{path}: {what} = {needed} steps but /{split}/accel stores {stored} steps")
    n_samples = n_total if cfg.n_samples is None else int(cfg.n_samples)
    model, initial_state = resolve_model(cfg, info)
    from hybridqcm.data.sensor import build_sensor

    try:
        sensor = build_sensor(cfg.get("sensor"))
    except ValueError as error:
        raise ConfigError(str(error)) from None
    if sensor.active and sigma > 0:
        raise ConfigError(
            f"noise_sigma={sigma} (the source's multiplicative noise) and sensor={sensor.kind}: choose one"
        )
    margin = cfg.get("input_margin", "auto")
    if longest:  # every stored step, less the exact model's input margins
        exact = base is not None or model == "exact"
        n_steps = stored - (12 if exact and str(margin) == "auto" and stored >= 14 else 0)
        if str(margin) != "auto":
            n_steps = stored - sum(int(m) for m in margin)
        if n_steps < 2:
            raise DatasetError(f"{path}: n_steps=max leaves {n_steps} steps of the {stored} stored")
    if str(margin) == "auto":  # the exact model interpolates the input: give it what the file holds around the window
        margin = (0, 0) if model == "euler" else (min(4, stored - n_steps), max(0, min(8, stored - n_steps - 4)))
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
    needed = max(needed, min(stored, margin[0] + n_steps + margin[1]))
    if base is not None:  # the road-free models are continuous-time, with their initial state estimated
        model, initial_state = "exact", "unknown"
    if initial_state == "unknown":
        # With x0 unknown a short continuation window has up to 6 more unknowns than it can pin
        # down (diverging or stopping in local minima): such stages are skipped.
        shortest = int(cfg.get("min_window_unknown_state", 30))
        stages = [s for s in stages if s["n_steps"] is None or s["n_steps"] >= shortest] or stages[-1:]
    if str(cfg.hold) not in ("spline", "foh", "zoh") or int(cfg.substeps) < 1:
        raise ConfigError(f"hold={cfg.hold!r}, substeps={cfg.substeps}: hold is spline, foh or zoh and substeps >= 1")
    return {
        "path": path,
        "split": split,
        "has_params": has_params,
        "known": known,
        "observed": observed,
        "stages": stages,
        "n_read_steps": needed,
        "n_samples": n_samples,
        "h": h_file or 0.01,
        "completes": completes,
        "windows": windows,
        "model": model,
        "initial_state": initial_state,
        "base_excitation": base,
        "n_params": n_params,
        "sensor": sensor,
        "input_margin": margin,
        "n_steps": n_steps,
    }


# --------------------------------------------------------------------------------------------------
def build_inputs(cfg, plan: Mapping) -> dict:
    """Read data, draw the random init (seed) and the measurement noise (seed + 1)."""
    from hybridqcm.data.hdf5 import read_split
    from hybridqcm.physics.parameters import PhysicalConstants

    road_free = plan["base_excitation"] is not None
    keys = ["accel"] + ([] if road_free else ["road"]) + (["params"] if plan["has_params"] else [])
    arrays = read_split(
        plan["path"], plan["split"], keys, n_steps=plan["n_read_steps"], index=slice(0, plan["n_samples"])
    )
    accel = torch.from_numpy(np.asarray(arrays["accel"], dtype=np.float64))
    for c in plan["observed"]:  # unrecorded channels may be NaN in a file; the ones used may not
        column = accel[:, :, CHANNELS.index(c)]
        if not bool(torch.isfinite(column).all()):
            bad = int((~torch.isfinite(column)).any(1).nonzero()[0])
            raise ConfigError(
                f"{plan['path']}: /{plan['split']}/accel channel {c} has NaN/inf (sample {bad}); "
                f"it is in observed={plan['observed']}"
            )
    road = (
        torch.zeros(accel.shape[:2], dtype=torch.float64)
        if road_free
        else torch.from_numpy(np.asarray(arrays["road"], dtype=np.float64))
    )
    m = accel.shape[0]
    vehicle = PhysicalConstants(**{k: float(v) for k, v in cfg.vehicle.items()})
    p_ref = vehicle.to_params()
    true = torch.from_numpy(np.asarray(arrays["params"], dtype=np.float64)) if plan["has_params"] else None

    # The same δ for every experiment: drawn first, for the whole file prefix, from `seed`.
    init_gen = torch.Generator().manual_seed(int(cfg.seed))
    delta = float(cfg.init.relative_sigma) * torch.randn(m, 10, generator=init_gen, dtype=torch.float64)
    init = p_ref * (1.0 + delta)
    init = torch.where(init > 0, init, p_ref.expand_as(init))  # a δ < -1 would start outside the domain
    known_values = true if (true is not None and cfg.known_source == "file") else p_ref.expand(m, 10)
    for j in plan["known"]:
        init[:, j] = known_values[:, j]
    if cfg.pu_known:
        pu = (
            (known_values[:, 9] - known_values[:, 8])
            if (true is not None and cfg.known_source == "file")
            else torch.full((m,), float(p_ref[9] - p_ref[8]), dtype=torch.float64)
        )
    else:
        pu = torch.full((m,), float(p_ref[9] - p_ref[8]), dtype=torch.float64)  # only the U-Net would read it

    sigma = float(cfg.noise_sigma)
    if sigma > 0:
        noise_gen = torch.Generator().manual_seed(int(cfg.seed) + 1)
        accel = accel * (1.0 + sigma * torch.randn(accel.shape, generator=noise_gen, dtype=torch.float64))
    sensor = plan["sensor"]
    out = {"accel": accel, "road": road, "pu": pu, "init": init, "true": true, "index": torch.arange(m)}
    if sensor.active:
        out["accel"] = sensor.apply(accel, torch.arange(m))
        if cfg.noise_weighting:  # the user knows the sensor: weight each channel by 1/σ_c
            out["noise_std"] = sensor.noise_std(accel).clamp_min(1e-12)
    if sigma > 0 and cfg.noise_weighting:
        out["noise_sigma"] = torch.full((m,), sigma, dtype=torch.float64)
    return out


class _DictDataset(torch.utils.data.Dataset):
    def __init__(self, tensors: Mapping[str, torch.Tensor]):
        self.tensors = dict(tensors)
        self.n = int(next(iter(self.tensors.values())).shape[0])

    def __len__(self) -> int:
        return self.n

    def __getitems__(self, indices):
        idx = torch.as_tensor(indices)
        return {k: v[idx] for k, v in self.tensors.items()}

    def __getitem__(self, i):
        return {k: v[i] for k, v in self.tensors.items()}


def _identity(batch):
    return batch


# --------------------------------------------------------------------------------------------------
def run(cfg) -> dict:
    import lightning
    from hydra.core.hydra_config import HydraConfig

    from hybridqcm.estimation.hybrid import GaussNewtonRefinement, GaussNewtonStage, HybridEstimator
    from hybridqcm.estimation.response import base_excitation_response, quarter_car_response
    from hybridqcm.estimation.solver import STATUS_LABELS, SolverStatus, build_solver
    from hybridqcm.metrics import error_distribution_rows, write_error_distribution

    t_start = time.perf_counter()
    plan = validate(cfg)
    run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path(".")
    common.check_writable_dir(run_dir)  # a read-only folder is found now, not after all the solving
    runfolder.prepare_run_dir(run_dir, runfolder.ESTIMATE_ARTEFACTS, bool(cfg.get("overwrite", False)))
    inputs = build_inputs(cfg, plan)
    n_params = plan["n_params"]
    known_mask = torch.zeros(n_params, dtype=torch.bool)
    known_mask[plan["known"]] = True

    module = HybridEstimator(
        cnn_ckpt=cfg.cnn_ckpt if cfg.init.cnn else None,
        unet_ckpt=cfg.unet_ckpt,
        cae_ckpt=cfg.cae_ckpt,
        observed=plan["observed"],
        n_steps=plan["n_steps"],
        h=plan["h"],
        cnn_init=bool(cfg.init.cnn),
        equation_error_init=bool(cfg.init.equation_error),
        known=[PARAM_NAMES[j] for j in plan["known"]],
        pu_known=bool(cfg.pu_known),
        cnn_a2_from_data=bool(cfg.cnn_a2_from_file),
        base_excitation=plan["base_excitation"],
        input_margin=plan["input_margin"],
        cnn_prior_rel_std=cfg.init.get("cnn_prior_rel_std"),
        cnn_prior=cfg.init.get("cnn_prior"),
        cnn_prior_scale=float(cfg.init.get("cnn_prior_scale", 1.0)),
    )
    stages = [
        GaussNewtonStage(s["name"], build_solver(s["method"], **s["settings"]), s["channels"], s["n_steps"], s["guard"])
        for s in plan["stages"]
    ]
    sigma = float(cfg.noise_sigma)
    # Restart threshold on L/(½Σa²): noise-free fits end near 1e-15; with noise the floor is ~σ².
    threshold = float(cfg.restarts.threshold) if sigma == 0 else max(float(cfg.restarts.threshold), 4.0 * sigma**2)
    if plan["base_excitation"] is None:
        response = quarter_car_response(
            plan["model"], plan["h"], bool(cfg.pu_known), plan["initial_state"], str(cfg.hold), int(cfg.substeps)
        )
    else:
        response = base_excitation_response(
            plan["base_excitation"], plan["h"], plan["initial_state"], str(cfg.hold), int(cfg.substeps)
        )
    if plan["model"] == "exact":  # the loss floor is the hold's model error: restarts go by status alone
        threshold = math.inf
    reweight = cfg.residual_weighting
    if str(reweight) == "auto":
        reweight = "spectral" if plan["model"] == "exact" else False
    refinement = GaussNewtonRefinement(
        stages,
        known=known_mask,
        pu_known=bool(cfg.pu_known),
        h=plan["h"],
        response=response,
        reweight=reweight,
        peer_factor=cfg.get("misfit_peer_factor", 10.0),
        log_dir=run_dir / "tb" if cfg.tensorboard else None,
        restarts=int(cfg.restarts.count),
        restart_threshold=threshold,
        restart_sigma=float(cfg.restarts.sigma),
        seed=int(cfg.seed),
        restart_mass_factors=list(cfg.restarts.get("mass_factors") or []),
    )
    loader = torch.utils.data.DataLoader(
        _DictDataset({k: v for k, v in inputs.items() if k != "true"}),
        batch_size=int(cfg.batch_size),
        shuffle=False,
        collate_fn=_identity,
        num_workers=0,
    )
    trainer = lightning.Trainer(
        accelerator="cpu",
        devices=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=bool(cfg.progress),
        enable_model_summary=False,
        callbacks=[refinement],
        default_root_dir=str(run_dir),
        inference_mode=False,
    )
    t_solve = time.perf_counter()
    trainer.predict(module, dataloaders=loader, return_predictions=False)
    solve_seconds = time.perf_counter() - t_solve
    collected = refinement.collect()
    result = collected.result
    # θ = (p1..pP, x0...): the model's parameters first, then the estimated initial state (if any).
    param_names = list(response.theta_names[:n_params])
    params, std = result.params[:, :n_params], result.std[:, :n_params]
    state_names = list(response.theta_names[n_params:])
    x0, x0_std = result.params[:, n_params:], result.std[:, n_params:]
    status = [STATUS_LABELS[int(s)] for s in result.status]
    K3 = float(cfg.K3)
    m3 = K3 / params[:, 1]
    m3_std = K3 / params[:, 1].square() * std[:, 1]
    # The 95 % interval of m3 is the image of p2's (m3 = K3/p2 is monotone): skewed, unlike m3 ± 1.96σ.
    p2_low, p2_high = params[:, 1] - 1.96 * std[:, 1], params[:, 1] + 1.96 * std[:, 1]
    m3_low = K3 / p2_high
    m3_high = torch.where(p2_low > 0, K3 / p2_low.clamp_min(1e-300), torch.full_like(p2_low, math.inf))

    # estimates.csv: index, parameters, status, their std, m3 with std and 95 % interval, x0 and its std
    header = [
        "index",
        *param_names,
        "status",
        *[f"std_{n}" for n in param_names],
        "m3",
        "m3_std",
        "m3_low",
        "m3_high",
        *state_names,
        *[f"std_{n}" for n in state_names],
    ]
    rows = []
    for i in range(params.shape[0]):
        rows.append(
            [
                int(collected.index[i]),
                *[repr(float(x)) for x in params[i]],
                status[i],
                *[repr(float(x)) for x in std[i]],
                repr(float(m3[i])),
                repr(float(m3_std[i])),
                repr(float(m3_low[i])),
                repr(float(m3_high[i])),
                *[repr(float(x)) for x in x0[i]],
                *[repr(float(x)) for x in x0_std[i]],
            ]
        )
    atomic_write_csv(run_dir / "estimates.csv", header, rows)
    status_rows = [
        [
            int(collected.index[i]),
            status[i],
            int(result.iterations[i]),
            repr(float(result.loss[i])),
            repr(float(collected.relative_loss[i])),
            int(collected.restarts[i]),
            repr(float(result.condition_number[i])),
        ]
        for i in range(params.shape[0])
    ]
    for row, rel, white in zip(status_rows, result.relative_residual, result.whiteness):
        row += [repr(float(rel)), repr(float(white))]
    atomic_write_csv(
        run_dir / "status.csv",
        [
            "index",
            "status",
            "iterations",
            "loss",
            "relative_loss",
            "restarts",
            "condition_number",
            "relative_residual",
            "whiteness",
        ],
        status_rows,
    )

    free = [j for j in range(n_params) if j not in plan["known"]]
    free_names = [param_names[j] for j in free]
    table_rows = None
    summary = {
        "experiment": cfg.experiment_name,
        "data": str(plan["path"]),
        "split": plan["split"],
        "n_samples": int(params.shape[0]),
        "n_steps": plan["n_steps"],
        "noise_sigma": float(cfg.noise_sigma),
        "seed": int(cfg.seed),
        "observed": plan["observed"],
        "known": [PARAM_NAMES[j] for j in plan["known"]],
        "model": plan["model"],
        "initial_state": plan["initial_state"],
        "base_excitation": plan["base_excitation"],
        "hold": str(cfg.hold) if plan["model"] == "exact" else None,
        "sensor": {k: v for k, v in vars(plan["sensor"]).items() if not k.startswith("_")},
        "input_margin": list(plan["input_margin"]),
        "status_counts": {k: int(sum(1 for s in status if s == k)) for k in STATUS_LABELS.values()},
        "stages": collected.stage_status,
        "stage_mean_loss": collected.stage_loss,
        "iterations_mean": float(result.iterations.double().mean()),
        "restarted_samples": int((collected.restarts > 0).sum()),
        "seconds_solve": solve_seconds,
    }
    if inputs["true"] is not None:
        true = inputs["true"][:, :n_params]
        table_rows = error_distribution_rows(params[:, free], true[:, free], free_names)
        title = f"{cfg.experiment_name}: {params.shape[0]} samples, N = {plan['n_steps']}, noise σ = {cfg.noise_sigma}"
        write_error_distribution(table_rows, run_dir, title=title)
        # A diverged or non-finite sample counts as failed / not covered, never as a success.
        failed = ~torch.isfinite(params).all(1) | (result.status == int(SolverStatus.DIVERGED))
        err = ((params - true).abs() / true.abs())[:, free]
        err = torch.where(failed[:, None] | ~torch.isfinite(err), torch.full_like(err, math.inf), err)
        summary["failed_samples"] = int(failed.sum())
        summary["all_within_1pct"] = float((err <= 0.01).all(1).double().mean())
        summary["all_within_10pct"] = float((err <= 0.10).all(1).double().mean())
        # calibration: fraction of true values inside the 95 % interval; a failed sample or an infinite
        # interval (diverged, not identifiable) covers nothing: it is a failure, not a success.
        cal_rows = []
        for j, name in zip(free, free_names):
            ok = ~failed & torch.isfinite(std[:, j]) & torch.isfinite(params[:, j])
            cal_rows.append(
                [
                    name,
                    int(params.shape[0]),
                    coverage_95(params[:, j], true[:, j], std[:, j], failed),
                    float(std[:, j][ok].median() / true[:, j][ok].median()) if bool(ok.any()) else math.inf,
                ]
            )
        true_m3 = K3 / true[:, 1]
        m3_ok = ~failed & torch.isfinite(m3_high) & torch.isfinite(m3_low)
        inside = ((true_m3 >= m3_low) & (true_m3 <= m3_high) & m3_ok).double()
        m3_width = (m3_high - m3_low) / true_m3
        cal_rows.append(
            [
                "m3",
                int(params.shape[0]),
                float(inside.mean()),
                float(m3_std[m3_ok].median() / true_m3[m3_ok].median()) if bool(m3_ok.any()) else math.inf,
            ]
        )
        atomic_write_csv(run_dir / "calibration.csv", ["param", "n", "coverage_95", "median_rel_std"], cal_rows)
        m3_err = (m3 - true_m3).abs() / true_m3.abs()
        m3_err = torch.where(torch.isfinite(m3_err), m3_err, torch.full_like(m3_err, math.inf))
        summary["m3_mean_rel_err"] = float(m3_err.mean())
        summary["m3_p95_rel_err"] = float(m3_err.quantile(0.95))
        summary["m3_within_0.5pct"] = float((m3_err <= 0.005).double().mean())
        summary["m3_within_1pct"] = float((m3_err <= 0.01).double().mean())
        summary["m3_within_5pct"] = float((m3_err <= 0.05).double().mean())
        summary["m3_coverage_95"] = float(inside.mean())
        summary["m3_interval_median_rel_width"] = float(m3_width[m3_ok].median()) if bool(m3_ok.any()) else math.inf
        if cfg.plots:
            from hybridqcm.plots import close, plot_sorted_predictions

            for j, name in zip(free, free_names):
                close(
                    plot_sorted_predictions(
                        params[:, j].numpy(),
                        true[:, j].numpy(),
                        name,
                        run_dir / "plots" / f"sorted_{name}.png",
                        title=f"{cfg.experiment_name}: {name}",
                    )
                )
            close(
                plot_sorted_predictions(
                    m3.numpy(),
                    true_m3.numpy(),
                    "m3 [kg]",
                    run_dir / "plots" / "sorted_m3.png",
                    title=f"{cfg.experiment_name}: occupant mass",
                )
            )
        if cfg.tensorboard:  # the table and the plots beside the GN losses, in one TensorBoard run
            from hybridqcm.tracking import log_estimation_to_tensorboard

            log_estimation_to_tensorboard(
                run_dir / "tb", table_rows, sorted((run_dir / "plots").glob("*.png")), title=title
            )
    summary["seconds_total"] = time.perf_counter() - t_start
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2))
    runfolder.write_completion_marker(
        run_dir, "qcm-estimate", runfolder.task_overrides(), [plan["path"], cfg.cnn_ckpt, cfg.unet_ckpt, cfg.cae_ckpt]
    )

    print_table(
        f"{cfg.experiment_name}: status", ["status", "samples"], [[k, v] for k, v in summary["status_counts"].items()]
    )
    if table_rows is not None:
        print_table(
            f"{cfg.experiment_name}: relative error, {params.shape[0]} samples",
            ["param", "max", "mean", "≤1 %", "≤5 %", "≤10 %", "≤25 %", ">25 %"],
            [
                [
                    r["param"],
                    f"{100 * r['max_err']:.3g} %",
                    f"{100 * r['mean_err']:.3g} %",
                    f"{100 * r['within_1pct']:.2f} %",
                    f"{100 * r['within_5pct']:.2f} %",
                    f"{100 * r['within_10pct']:.2f} %",
                    f"{100 * r['within_25pct']:.2f} %",
                    f"{100 * r['over_25pct']:.2f} %",
                ]
                for r in table_rows
            ],
        )
        print(
            f"all estimated parameters within 1 %: {100 * summary['all_within_1pct']:.2f} % of samples; "
            f"GN {summary['seconds_solve']:.1f} s, total {summary['seconds_total']:.1f} s -> {run_dir}"
        )
    else:
        print(f"estimates of {params.shape[0]} samples (no params in the file: no error table) -> {run_dir}")
    return summary


def _hydra_entry(cfg) -> None:
    from hybridqcm.data.hdf5 import DatasetError

    try:
        run(cfg)
    except (HybridQCMError, ConfigError, DatasetError, FileNotFoundError) as error:
        fail(error)


def main() -> None:
    common.run_hydra_app("estimate", "estimate", _hydra_entry)


if __name__ == "__main__":
    main()
