"""qcm-estimate's plan: every setting and input checked before any work, resolved once.

``validate(cfg)`` reads the config, the dataset's layout and the checkpoints (once, through the
safe loader) and returns the plan dict the run is built from: file, split, rows, window, model,
initial state, stages, sensor and input margins. Every bad input (unknown or non-estimation
experiment, missing/wrong-kind checkpoint, a key or channel the pipeline needs but the file lacks,
a window longer than the stored steps) is one ConfigError/DatasetError line naming the file, key
and value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from hybridqcm import config
from hybridqcm.config import CONFIG_DIR
from hybridqcm.errors import ConfigError

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
    config.check_experiment_overrides(args, "estimate", config_dir)


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
    tol = base.get("decrement_tol")
    if tol is not None and not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol >= 0):
        raise ConfigError(f"solver.decrement_tol must be null or a finite number >= 0, got {tol!r}")
    return method, base


def interval_settings(cfg) -> dict:
    """SolverConfig fields from the ``intervals`` group of configs/estimate.yaml (empty when absent)."""
    from hybridqcm.estimation.solver import COVARIANCES

    intervals = cfg.get("intervals")
    if intervals is None:
        return {}
    covariance = intervals.get("covariance", "model")
    if covariance not in ("auto", *COVARIANCES):
        raise ConfigError(f"intervals.covariance={covariance!r}: choose one of {['auto', *COVARIANCES]}")
    band = intervals.get("band", 1)
    if isinstance(band, bool) or not isinstance(band, int) or band < 1:
        raise ConfigError(f"intervals.band={band!r}: must be an integer >= 1")
    student_t = intervals.get("student_t", True)
    if not isinstance(student_t, bool):
        raise ConfigError(f"intervals.student_t={student_t!r}: must be true or false")
    return {"covariance": covariance, "covariance_band": band, "covariance_dof": student_t}


def resolve_covariance(cfg, model: str, base_excitation: str | None) -> str:
    """``intervals.covariance: auto`` for this run: ``model`` where the whitened residual is white noise
    — a road-driven exact model (the input known, not measured) fitted with a noise model — and
    ``robust_jackknife`` elsewhere: a measured driving acceleration (errors in variables), or the Euler
    model without a noise model (its residual is discretisation error, the source's noise multiplicative)."""
    weighting = str(cfg.get("residual_weighting", "auto")).lower()
    whitened = weighting in ("spectral", "true") or (weighting == "auto" and model == "exact")
    return "model" if base_excitation is None and model == "exact" and whitened else "robust_jackknife"


def vehicle_prior_settings(cfg) -> dict | None:
    """The ``vehicle_prior`` group: {"params": [names], "rel_std": float}, or None when it is off."""
    prior = cfg.get("vehicle_prior")
    if prior is None or prior.get("rel_std") is None or not list(prior.get("params") or []):
        return None
    rel = prior.get("rel_std")
    if isinstance(rel, bool) or not isinstance(rel, int | float) or not (math.isfinite(rel) and rel > 0):
        raise ConfigError(f"vehicle_prior.rel_std={rel!r}: must be null or a finite number > 0")
    names = [str(n) for n in prior.params]
    _param_index(names, "vehicle_prior.params")
    return {"params": names, "rel_std": float(rel)}


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
    for group in ("paths", "hydra", "solver", "experiment", "sensor", "trainer"):
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


def check_spline_degree(cfg) -> int:
    """spline_degree (configs/estimate.yaml): 3, 5 or 7; ConfigError otherwise."""
    from hybridqcm.estimation.exact import SPLINE_DEGREES

    degree = cfg.get("spline_degree", 5)
    if isinstance(degree, bool) or not isinstance(degree, int) or degree not in SPLINE_DEGREES:
        raise ConfigError(f"spline_degree={degree!r}: choose one of {list(SPLINE_DEGREES)}")
    return int(degree)


def window_check_settings(cfg):
    """skip_windows.{min_std, clip_samples} as an estimation.window_check.WindowCheck; ConfigError naming key and value."""
    from hybridqcm.estimation.window_check import WindowCheck

    group = cfg.get("skip_windows") or {}
    try:
        return WindowCheck(min_std=group.get("min_std", 0.0), clip_samples=group.get("clip_samples", 5))
    except ValueError as error:
        raise ConfigError(f"skip_windows: {error}") from None


_NULLABLE = ("misfit_peer_factor", "skip_windows.clip_samples", "vehicle_prior.rel_std")


def _setting_types() -> dict[str, set[str]]:
    """{dotted key: type names of its values} in estimate.yaml and the estimation experiments."""
    import yaml

    types: dict[str, set[str]] = {"n_samples": {"int", "NoneType"}}  # null by default: all samples
    for key in _NULLABLE:  # documented "null: off" with a number by default
        types.setdefault(key, set()).add("NoneType")

    def walk(data, prefix: str = "") -> None:
        for key, value in (data or {}).items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}.")
            else:
                types.setdefault(f"{prefix}{key}", set()).add(type(value).__name__)

    walk(yaml.safe_load((CONFIG_DIR / "estimate.yaml").read_text()))
    for path in sorted((CONFIG_DIR / "experiment").glob("*.yaml")):
        data = yaml.safe_load(path.read_text()) or {}
        if isinstance(data, dict) and data.get("task") == "estimate":
            walk(data)
    return types


def check_setting_types(cfg, own: tuple[str, ...] = ()) -> None:
    """A number or a switch given as something else (`n_samples=abc`, `plots=maybe`): one line naming
    key and value, before any work. The type is the one every default of the key has; ``own``: keys the
    caller checks itself (the vehicle's init.equation_error also takes `seats`)."""
    from omegaconf import OmegaConf

    for key, names in _setting_types().items():
        if key in own:
            continue
        value = OmegaConf.select(cfg, key, default=None)
        if value is None and "NoneType" in names:
            continue
        kinds = names - {"NoneType"}
        if kinds == {"bool"} and not isinstance(value, bool):
            raise ConfigError(f"{key}={value!r}: give true or false")
        numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
        if kinds == {"int"} and not (numeric and isinstance(value, int)):
            raise ConfigError(f"{key}={value!r}: give a whole number" + (" or null" if "NoneType" in names else ""))
        if kinds and kinds <= {"int", "float"} and not numeric:
            raise ConfigError(f"{key}={value!r}: give a number" + (" or null" if "NoneType" in names else ""))


# --------------------------------------------------------------------------------------------------
def validate(cfg) -> dict:
    """Check every input before any work; returns the resolved plan. Raises ConfigError/DatasetError."""
    from hybridqcm.data.hdf5 import DatasetError, dataset_info
    from hybridqcm.estimation.front import CheckpointKindError, check_networks, load_network
    from hybridqcm.estimation.fusion import check_cnn_prior
    from hybridqcm.estimation.plan_occupant import delay_margin, occupant_plan

    check_known_keys(cfg)
    check_setting_types(cfg)
    config.check_trainer_settings(cfg.get("trainer"))
    window_check_settings(cfg)
    config.check_task_name(cfg.get("task_name", "estimate"))
    if cfg.get("task") != "estimate":
        raise ConfigError(f"task={cfg.get('task')!r}: qcm-estimate runs estimation experiments (task: estimate)")
    longest = str(cfg.n_steps) == "max"  # the longest window the file holds, resolved below
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
        from hybridqcm.estimation.front import BASE_EXCITATION

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
    from hybridqcm.estimation.plan_seat import seat_view_plan

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
        if has_params and seat_view is None:  # a seat view's p1, p2 come from checked physical parameters
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
    occupant = occupant_plan(cfg, base, model)
    # a channel delay reads the input that far beyond the window's ends too
    lead = max(4, delay_margin(cfg, h_file or 0.01)) if occupant is not None else 4
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
    if occupant is not None and occupant["delay"] is not None and min(margin) < 1:
        raise ConfigError(
            f"{path}: delay={cfg.get('delay')!r} reads the input beyond the window's ends, and n_steps={n_steps} of the "
            f"{stored} stored steps leaves input_margin={list(margin)}: give n_steps <= {stored - 2 * lead} or delay=null"
        )
    needed = max(needed, min(stored, margin[0] + n_steps + margin[1]))
    if base is not None:  # the road-free models are continuous-time, with their initial state estimated
        model, initial_state = "exact", "unknown"
    if around == "auto":  # the exact model is for real recordings; Euler keeps the source's protocol
        around = "reference" if model == "exact" else "start"
    for stage in stages:  # only the last stage carries the intervals' settings
        if stage["settings"].get("covariance") == "auto":
            stage["settings"]["covariance"] = resolve_covariance(cfg, model, base)
    if initial_state == "unknown":
        # With x0 unknown a short continuation window has up to 6 more unknowns than it can pin
        # down (diverging or stopping in local minima): such stages are skipped.
        shortest = int(cfg.get("min_window_unknown_state", 30))
        stages = [s for s in stages if s["n_steps"] is None or s["n_steps"] >= shortest] or stages[-1:]
    from hybridqcm.estimation.initial_state import X0_STARTS

    x0_start = str(cfg.get("x0_start", "rest"))
    if x0_start not in X0_STARTS:
        raise ConfigError(f"x0_start={x0_start!r}: choose one of {list(X0_STARTS)}")
    if str(cfg.hold) not in ("spline", "foh", "zoh") or int(cfg.substeps) < 1:
        raise ConfigError(f"hold={cfg.hold!r}, substeps={cfg.substeps}: hold is spline, foh or zoh and substeps >= 1")
    if check_spline_degree(cfg) != 5 and occupant is not None:  # estimate_occupant builds its own (quintic) models
        raise ConfigError(
            f"spline_degree={cfg.spline_degree}: the occupant models and the channel delay use the quintic hold; "
            f"leave spline_degree=5"
        )
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
        "x0_start": x0_start,
        "vehicle_prior": vehicle_prior_settings(cfg),
        "restarts_around": around,
        "base_excitation": base,
        "n_params": n_params,
        "occupant": occupant,
        "seat": None if seat_view is None else seat_view["seat"],
        "sensor": sensor,
        "input_margin": margin,
        "n_steps": n_steps,
    }
