"""aggregate=drive's plan: the drive settings checked and the file's drives read before any work, and the
per-window columns the combination needs (issue 32).

The windows of one drive share ``/<split>/profile_id`` (qcm-import window=/stride= cuts a recording into
them) and carry their start time ``/<split>/t_start`` [s]. Each window is estimated as usual (its own
initial state); its shared parameters and their covariance travel beside the block's columns
(:func:`drive_columns`), and after the merge every drive is combined (reports/drive.py, estimation/drive.py).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.drive import SCALES, SPLIT_TESTS
from hybridqcm.estimation.solver import STATUS_LABELS

WEIGHTS = ("reported", "model")
JOINTS = ("none", "final", "progress")
SPACES = ("log", "linear")
PRIORS = ("windows", "once")
PRIOR_SOURCES = ("model", "reported")


@dataclass(frozen=True)
class DrivePlan:
    """Validated drive settings and the file's drive layout: profile_id [M], t_start [M], window length [s]."""

    statuses: tuple[str, ...]
    weights: str
    scale: str
    alpha: float
    min_windows: int
    outlier_alpha: float
    neighbours: int
    plots: int
    per_window: tuple[str, ...]
    profile_id: np.ndarray
    t_start: np.ndarray
    names: tuple[str, ...]
    window_s: float
    joint: str = "none"  # none | final | progress: segments (and their prefixes) by a joint fit (drive_fit.py)
    split: str = "pooled"  # wald | pooled: the change-point test (estimation/drive.segment)
    space: str = "log"  # log | linear: positive parameters combined in their logarithm (estimation/drive.py)
    prior: str = "once"  # once | windows: the body prior counted once (drive_prior.py), or as each window counts it
    prior_from: str = "model"  # model | reported: the covariance the prior is taken out of (drive_prior.py)


def _fraction(settings, key: str) -> float:
    value = settings.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
        raise ConfigError(f"drive.{key}={value!r}: give a probability in (0, 1)")
    return float(value)


def _count(settings, key: str, low: int) -> int:
    value = settings.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"drive.{key}={value!r}: give an integer >= {low}")
    return int(value)


def _names(settings, key: str) -> tuple[str, ...]:
    value = settings.get(key, ["tau"])
    value = [] if value is None else [value] if isinstance(value, str) else list(value)
    if any(str(v) == "p2" for v in value):
        raise ConfigError(f"drive.{key}={value}: p2 (the occupant's static mass) is what the windows share")
    return tuple(str(v) for v in value)


def drive_plan(cfg, plan: Mapping) -> DrivePlan | None:
    """None without aggregate=drive; else the checked settings and the file's profile_id / t_start (read
    once: a few numbers per window). Raises ConfigError / DatasetError (one line) before any work."""
    aggregate = cfg.get("aggregate")
    if aggregate is None:
        return None
    if str(aggregate) != "drive":
        raise ConfigError(f"aggregate={aggregate!r}: give drive (one estimate per drive) or null (per window only)")
    settings = cfg.get("drive") or {}
    statuses = settings.get("statuses", ["converged"])
    statuses = [statuses] if isinstance(statuses, str) else [str(s) for s in statuses]
    bad = [s for s in statuses if s not in STATUS_LABELS.values()]
    if bad or not statuses:
        raise ConfigError(f"drive.statuses={statuses}: {bad or 'empty'}; choose from {list(STATUS_LABELS.values())}")
    weights, scale = str(settings.get("weights", "reported")), str(settings.get("scale", "marginal"))
    if weights not in WEIGHTS:
        raise ConfigError(f"drive.weights={weights!r}: choose one of {list(WEIGHTS)}")
    if scale not in SCALES:
        raise ConfigError(f"drive.scale={scale!r}: choose one of {list(SCALES)}")
    split_test = str(settings.get("split", DrivePlan.split))
    space = str(settings.get("space", DrivePlan.space))
    if space not in SPACES:
        raise ConfigError(f"drive.space={space!r}: choose one of {list(SPACES)}")
    if split_test not in SPLIT_TESTS:
        raise ConfigError(f"drive.split={split_test!r}: choose one of {list(SPLIT_TESTS)}")
    prior, prior_from = (
        str(settings.get("prior", DrivePlan.prior)),
        str(settings.get("prior_from", DrivePlan.prior_from)),
    )
    if prior not in PRIORS:
        raise ConfigError(f"drive.prior={prior!r}: choose one of {list(PRIORS)}")
    if prior_from not in PRIOR_SOURCES:
        raise ConfigError(f"drive.prior_from={prior_from!r}: choose one of {list(PRIOR_SOURCES)}")
    if prior == "once" and weights == "model":
        raise ConfigError(
            "drive.prior=once needs drive.weights=reported (the sandwich's weights keep each prior): "
            "set drive.prior=windows for drive.weights=model"
        )
    joint = str(settings.get("joint", DrivePlan.joint))
    if joint not in JOINTS:
        raise ConfigError(f"drive.joint={joint!r}: choose one of {list(JOINTS)}")
    import h5py

    path, split = Path(plan["path"]), str(plan["split"])
    with h5py.File(path, "r") as handle:
        group = handle[split]
        missing = [k for k in ("profile_id", "t_start") if k not in group]
        if missing:
            raise DatasetError(
                f"{path}: /{split} lacks {missing}, which aggregate=drive needs (the drive of each window and its "
                f"start time [s]; qcm-import window=N writes both)"
            )
        n = int(plan["n_samples"])
        profile_id = np.asarray(group["profile_id"][:n], dtype=np.int64)
        t_start = np.asarray(group["t_start"][:n], dtype=np.float64)
        stored = int(group["accel"].shape[1])
        recordings = handle.attrs.get("recordings")
    if profile_id.shape != (n,) or t_start.shape != (n,):
        raise DatasetError(f"{path}: /{split}/profile_id and t_start must hold one value per window ({n})")
    if not np.isfinite(t_start).all():
        bad_row = int(np.flatnonzero(~np.isfinite(t_start))[0])
        raise DatasetError(f"{path}: /{split}/t_start[{bad_row}] is not a finite time")
    names: list[str] = []
    if recordings is not None:
        try:
            names = [str(x) for x in json.loads(recordings)]
        except (TypeError, ValueError):
            names = []
    if profile_id.size and (profile_id.min() < 0 or (names and profile_id.max() >= len(names))):
        names = []  # ids that do not index the recordings' names: the ids themselves name the drives
    return DrivePlan(
        statuses=tuple(statuses),
        weights=weights,
        scale=scale,
        alpha=_fraction(settings, "alpha"),
        min_windows=_count(settings, "min_windows", 1),
        outlier_alpha=_fraction(settings, "outlier_alpha"),
        neighbours=_count(settings, "neighbours", 1),
        plots=_count(settings, "plots", 0),
        per_window=_names(settings, "per_window"),
        profile_id=profile_id,
        t_start=t_start,
        names=tuple(names),
        window_s=stored * float(plan["h"]),
        joint=joint,
        split=split_test,
        space=space,
        prior=prior,
        prior_from=prior_from,
    )


def drive_columns(tables: Callable, refinement, n_params: int) -> Callable:
    """``tables(record)`` (estimation/tables.block_tables) with what a drive pools added to the block's columns:
    drive_model [b] (each window's own choice, index into :func:`model_names`) and every candidate's estimate
    (:func:`_candidate_columns`; a single model's is its own), the parameter blocks of the covariances (the
    window's initial state marginalised)."""
    names = model_names(refinement)

    def with_drive(record: Mapping) -> tuple[list, list, dict]:
        rows, status_rows, columns = tables(record)
        b = record["params"].shape[0]
        chosen = (record.get("extra") or {}).get("occupant_model")
        columns["drive_model"] = torch.tensor(
            [names.index(c) for c in chosen] if chosen is not None else [0] * b, dtype=torch.long
        )
        columns.update(_candidate_columns(record, names, b, n_params))
        return rows, status_rows, columns

    return with_drive


def _candidate_columns(record: Mapping, names: Sequence[str], b: int, n_params: int) -> dict:
    """Every occupant candidate's estimate per window (an occupant-model selection's ``record["candidates"]``,
    estimation/occupant.py), so that a drive pools its windows under one model: drive_cand_theta [b, C, P],
    drive_cand_cov [b, C, P, P], drive_cand_status [b, C], drive_cand_fits [b, C], drive_cand_logz [b, C]
    (the evidence, model prior included); drive_cand_cov is the reported covariance (the model-based one scaled
    per parameter by the candidate's robust ratio, as its intervals are) and drive_cand_model_cov the model-based
    one, drive_cand_prior_mean and drive_cand_prior_precision [b, C, P] the prior in it (precision 0: none; NaN:
    not known, drive.prior=once then assumes the body prior). A single model: its own estimate and covariances,
    evidence 0, its prior not known."""
    cand = record.get("candidates")
    if cand is None:
        result = record["final"]
        theta = record["params"][:, :n_params].double()
        cov = result.covariance[:, :n_params, :n_params].double()
        std = result.std[:, :n_params].double()
        model_std = result.model_std[:, :n_params].double() if result.model_std is not None else std
        ratio = torch.where((std > 0) & torch.isfinite(std), model_std / std, torch.ones_like(std))
        unknown = torch.full((b, 1, n_params), math.nan, dtype=torch.float64)  # a single model's prior is not kept
        return {
            "drive_cand_prior_mean": unknown,
            "drive_cand_prior_precision": unknown.clone(),
            "drive_cand_theta": theta[:, None],
            "drive_cand_cov": cov[:, None],
            "drive_cand_model_cov": (cov * ratio.unsqueeze(2) * ratio.unsqueeze(1))[:, None],
            "drive_cand_status": result.status.long()[:, None],
            "drive_cand_fits": torch.ones(b, 1, dtype=torch.bool),
            "drive_cand_logz": torch.zeros(b, 1, dtype=torch.float64),
        }
    extra = record.get("extra") or {}
    logz = torch.stack([torch.as_tensor(extra[f"logz_{n}"], dtype=torch.float64) for n in names], 1)
    model_cov = cand["covariance"][:, :, :n_params, :n_params]
    ratio = cand["robust"][:, :, :n_params]
    return {
        "drive_cand_theta": cand["params"][:, :, :n_params],
        "drive_cand_cov": model_cov * ratio.unsqueeze(3) * ratio.unsqueeze(2),
        "drive_cand_model_cov": model_cov,
        "drive_cand_prior_mean": cand["prior_mean"][:, :, :n_params],
        "drive_cand_prior_precision": cand["prior_precision"][:, :, :n_params],
        "drive_cand_status": cand["status"],
        "drive_cand_fits": cand["fits"],
        "drive_cand_logz": logz,
    }


def drive_skipped_columns(skipped_tables: Callable, n_params: int, n_models: int = 1) -> Callable:
    """``skipped_tables(index, status, true)`` (estimation/tables: windows kept from the fit, no_signal or
    clipped) with :func:`drive_columns`' columns added, NaN: a block's fitted and skipped windows merge into
    one table, and such a window is never usable."""

    def with_drive(index, status, true) -> tuple[list, list, dict]:
        rows, status_rows, columns = skipped_tables(index, status, true)
        k = int(index.shape[0])
        columns["drive_model"] = torch.zeros(k, dtype=torch.long)
        columns["drive_cand_theta"] = torch.full((k, n_models, n_params), math.nan, dtype=torch.float64)
        columns["drive_cand_cov"] = torch.full((k, n_models, n_params, n_params), math.nan, dtype=torch.float64)
        columns["drive_cand_model_cov"] = columns["drive_cand_cov"].clone()
        columns["drive_cand_prior_mean"] = torch.full((k, n_models, n_params), math.nan, dtype=torch.float64)
        columns["drive_cand_prior_precision"] = columns["drive_cand_prior_mean"].clone()
        columns["drive_cand_status"] = torch.zeros(k, n_models, dtype=torch.long)
        columns["drive_cand_fits"] = torch.zeros(k, n_models, dtype=torch.bool)
        columns["drive_cand_logz"] = torch.full((k, n_models), -math.inf, dtype=torch.float64)
        return rows, status_rows, columns

    return with_drive


def model_names(refinement) -> list[str]:
    """The occupant models a window can report: an occupant-model selection's candidates, else one."""
    return list(getattr(refinement, "names", None) or ["rigid"])


__all__ = [
    "DrivePlan",
    "drive_plan",
    "drive_columns",
    "drive_skipped_columns",
    "model_names",
    "WEIGHTS",
    "SCALES",
    "JOINTS",
    "PRIORS",
    "PRIOR_SOURCES",
]
