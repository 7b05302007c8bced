"""The hybrid estimator on recordings in memory: qcm-estimate's plan, networks and GN refinement without
a file, a trainer or a run folder (README, "Python API").

    rows = estimate_recordings(cfg, accel, road, h=0.01)     # cfg: configs/estimate.yaml + an experiment

One dict per recording with estimates.csv's columns: p1..pP, their std_p, status, m3 with its 95 %
interval [m3_low, m3_high], the initial state (x0) where estimated, the occupant model's columns.
The same plan, batch and refinement as a run of the file (estimation/plan.py, blocks.py, runner.py).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from hybridqcm.errors import ConfigError
from hybridqcm.estimation.blocks import batch_from_arrays, without_skipped
from hybridqcm.estimation.plan import EstimationPlan, validate
from hybridqcm.estimation.runner import build_module, build_refinement, estimate_tables
from hybridqcm.estimation.tables import merge_block_tables

IN_MEMORY = Path("<arrays>")  # the plan's "path" for recordings in memory (named in its error messages)


def array_layout(cfg, n_recordings: int, n_steps: int, h: float) -> dict:
    """validate's dataset layout for ``n_recordings`` recordings of ``n_steps`` samples at period ``h`` [s]
    in memory, from an unknown producer (dynamics=auto: the exact model, the initial state estimated).
    Without a truth the known parameters come from the vehicle config (known_source=reference)."""
    if cfg.get("known") and cfg.get("known_source") == "file":
        raise ConfigError(
            f"known={list(cfg.known)} with known_source=file: recordings in memory carry no parameters; "
            f"set known_source=reference (the vehicle config's values)"
        )
    if n_recordings < 1 or n_steps < 2 or not (math.isfinite(h) and h > 0):
        raise ConfigError(f"recordings: {n_recordings} x {n_steps} samples at h = {h} s; give >= 1 x >= 2 at h > 0")
    if cfg.get("n_samples") is not None and int(cfg.n_samples) != n_recordings:
        raise ConfigError(f"n_samples={cfg.n_samples} but {n_recordings} recordings are given (n_samples=null)")
    return {
        "path": IN_MEMORY,
        "split": "arrays",
        "info": {"physics": "continuous", "initial_state": "unknown"},
        "seat_view": None,
        "has_params": False,
        "stored": int(n_steps),
        "n_total": int(n_recordings),
        "h": float(h),
    }


def in_memory(cfg):
    """``cfg`` with data.path naming the recordings in memory (IN_MEMORY): a composed config's default
    path is resolved through Hydra's runtime, which a Python session has not set."""
    return OmegaConf.merge(cfg, {"data": {"path": str(IN_MEMORY)}})


def array_plan(cfg, accel, h: float) -> EstimationPlan:
    """The checked plan for ``accel`` [b, T, 3] recorded at period ``h`` [s] (validate on array_layout;
    ``cfg`` as in_memory returns it)."""
    shape = np.shape(accel)
    if len(shape) != 3 or shape[2] != 3:
        raise ConfigError(f"accel has shape {list(shape)}: give [recordings, samples, 3] (a3, a2, a1) in m/s²")
    return validate(cfg, array_layout(cfg, int(shape[0]), int(shape[1]), h))


def estimate_recordings(cfg, accel, road=None, h: float = 0.01) -> list[dict]:
    """The hybrid estimator (networks of cfg's checkpoints, then the GN stages) on recordings in memory.

    accel [b, T, 3]: (a3, a2, a1) in m/s² (unobserved channels may be NaN); road [b, T] in m (None for
    the road-free models, base_excitation); h: the sampling period [s]. The window is cfg's n_steps
    (n_steps=max: all T samples less the input margins). Returns one dict per recording: estimates.csv's
    columns, numbers as floats (nan where a window was kept from the fit), status and model names as text.
    """
    cfg = in_memory(cfg)
    plan = array_plan(cfg, accel, h)
    arrays = {"accel": np.asarray(accel, dtype=np.float64)[:, : plan["n_read_steps"]]}
    if plan["base_excitation"] is None:
        if road is None:
            raise ConfigError("road=None: the road-driven models need the road profile [recordings, samples] in m")
        arrays["road"] = np.asarray(road, dtype=np.float64)[:, : plan["n_read_steps"]]
    batch = without_skipped(batch_from_arrays(cfg, plan, arrays))
    module, refinement = build_module(cfg, plan), build_refinement(cfg, plan)
    tables = estimate_tables(cfg, plan, refinement)
    rows = None
    if int(batch["index"].shape[0]):  # windows all kept from the fit have nothing to refine
        rows = tables.rows(refinement.refine_block(module.prepare(batch), module, 0))
    if int(batch["skipped_index"].shape[0]):
        skipped = tables.skipped(batch["skipped_index"], batch["skipped_status"], None)
        rows = skipped if rows is None else merge_block_tables(rows, skipped)
    return [{name: _value(name, v) for name, v in zip(tables.header, row)} for row in rows[0]]


def _value(name: str, value):
    """estimates.csv's text as a number, except the status and model names."""
    if name == "index":
        return int(value)
    try:
        return float(value)
    except (TypeError, ValueError):
        return value


__all__ = ["IN_MEMORY", "array_layout", "array_plan", "estimate_recordings", "in_memory"]
