"""The half / full car's per-block tables: estimates.csv's header and one block's rows (the shard writer's
``tables``), beside estimation/tables.py's for the quarter car."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from hybridqcm.estimation.solver import STATUS_LABELS
from hybridqcm.estimation.tables import status_rows, texts
from hybridqcm.physics.vehicle_geometry import VehicleLayout


def vehicle_estimates_header(theta_names: Sequence[str], n_params: int, layout: VehicleLayout) -> list[str]:
    params, states = list(theta_names[:n_params]), list(theta_names[n_params:])
    intervals = [f"{m}_{end}" for m in layout.seat_mass_names() for end in ("low", "high")]
    return [
        "index",
        *params,
        "status",
        *[f"std_{n}" for n in params],
        *intervals,
        *states,
        *[f"std_{n}" for n in states],
    ]


def vehicle_block_tables(record: Mapping, n_params: int, names: Sequence[str], layout: VehicleLayout):
    """One refined block -> (estimate rows, status rows, columns for the metrics)."""
    result = record["final"]
    theta, theta_std = record["params"], result.std
    params, std = theta[:, :n_params], theta_std[:, :n_params]
    x0, x0_std = theta[:, n_params:], theta_std[:, n_params:]
    status = [STATUS_LABELS[s] for s in result.status.tolist()]
    masses = [list(names).index(m) for m in layout.seat_mass_names()]
    low = params[:, masses] - 1.96 * std[:, masses]
    high = params[:, masses] + 1.96 * std[:, masses]
    bounds = texts(torch.stack([low, high], dim=2))  # per seat: low, high
    indices = [int(i) for i in record["index"].tolist()]
    p_t, std_t, x0_t, x0_std_t = texts(params), texts(std), texts(x0), texts(x0_std)
    rows = [
        [indices[i], *p_t[i], status[i], *std_t[i], *bounds[i], *x0_t[i], *x0_std_t[i]] for i in range(len(indices))
    ]
    index = record["index"]
    columns = {
        "index": index.long(),
        "params": params.double(),
        "std": std.double(),
        "status": result.status.long(),
        "iterations": result.iterations.long(),
        "restarts": record["restarts"].long(),
    }
    return rows, status_rows(record, indices, status), columns


__all__ = ["vehicle_estimates_header", "vehicle_block_tables"]
