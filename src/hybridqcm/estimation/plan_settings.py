"""qcm-estimate's settings, each checked and resolved on its own: solver, intervals, covariance, vehicle
prior, spline degree, window check, parameter names, the file's true parameters, the model for a file. ConfigError /
DatasetError lines naming key and value; estimation/plan.py composes them into the plan.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from hybridqcm.errors import ConfigError
from hybridqcm.estimation.response import INITIAL_STATES as MODEL_INITIAL_STATES
from hybridqcm.physics.parameters import PARAM_NAMES

# the setting's choices: auto picks one of the model's from the file (resolve_model)
INITIAL_STATES = ("auto", *MODEL_INITIAL_STATES)

MODELS = ("auto", "exact", "euler")


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


def param_index(names: Sequence[str], key: str) -> list[int]:
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
    tol = base.get("outside_tol")
    if tol is not None and (isinstance(tol, bool) or not isinstance(tol, (int, float)) or not 0 <= tol < math.inf):
        raise ConfigError(f"solver.outside_tol must be null or a finite number of nats >= 0, got {tol!r}")
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
    test = intervals.get("jackknife_test", 0.05)
    if test is not None and (isinstance(test, bool) or not isinstance(test, (int, float)) or not 0 < test < 1):
        raise ConfigError(f"intervals.jackknife_test={test!r}: a level in (0, 1), or null")
    return {"covariance": covariance, "covariance_band": band, "covariance_dof": student_t, "jackknife_test": test}


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
    param_index(names, "vehicle_prior.params")
    return {"params": names, "rel_std": float(rel)}


def check_positive_params(path: Path, split: str, params, n: int) -> None:
    """The file's true parameters must be finite and > 0 (errors are relative to them); DatasetError otherwise."""
    from hybridqcm.errors import DatasetError

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


def check_spline_degree(cfg) -> int:
    """spline_degree (configs/estimate.yaml): 3, 5 or 7; ConfigError otherwise."""
    from hybridqcm.estimation.hold import SPLINE_DEGREES

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


__all__ = [
    "INITIAL_STATES",
    "MODELS",
    "resolve_model",
    "check_positive_params",
    "check_spline_degree",
    "interval_settings",
    "param_index",
    "resolve_covariance",
    "solver_settings",
    "vehicle_prior_settings",
    "window_check_settings",
]
