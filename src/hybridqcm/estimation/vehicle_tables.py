"""The half / full car's per-block tables: estimates.csv's header and one block's rows (the shard writer's
``tables``), beside estimation/tables.py's for the quarter car."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from hybridqcm.estimation.solver import STATUS_LABELS
from hybridqcm.estimation.tables import status_row
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
    status = [STATUS_LABELS[int(s)] for s in result.status]
    masses = [list(names).index(m) for m in layout.seat_mass_names()]
    low = params[:, masses] - 1.96 * std[:, masses]
    high = params[:, masses] + 1.96 * std[:, masses]
    index = record["index"]
    rows, status_rows = [], []
    for i in range(params.shape[0]):
        bounds = [repr(float(v)) for pair in zip(low[i], high[i]) for v in pair]
        rows.append(
            [
                int(index[i]),
                *[repr(float(x)) for x in params[i]],
                status[i],
                *[repr(float(x)) for x in std[i]],
                *bounds,
                *[repr(float(x)) for x in x0[i]],
                *[repr(float(x)) for x in x0_std[i]],
            ]
        )
        status_rows.append(status_row(record, i, int(index[i]), status[i]))
    columns = {
        "index": index.long(),
        "params": params.double(),
        "std": std.double(),
        "status": result.status.long(),
        "iterations": result.iterations.long(),
        "restarts": record["restarts"].long(),
    }
    return rows, status_rows, columns


__all__ = ["vehicle_estimates_header", "vehicle_block_tables"]
