"""estimates.csv / status.csv rows of a block: the column-at-once formatting against each entry formatted alone
(repr of the float, the old row-at-a-time path), on a record with every kind of value a fit leaves."""

from __future__ import annotations

import math

import pytest
import torch

from hybridqcm.estimation.solver import STATUS_LABELS, SolverResult
from hybridqcm.estimation.tables import block_tables, estimates_header, status_rows
from hybridqcm.estimation.vehicle_tables import vehicle_block_tables, vehicle_estimates_header
from hybridqcm.metrics import m3_interval
from hybridqcm.physics.vehicle_geometry import VehicleLayout

K3 = 98935.0


def _record(b: int, n_params: int, n_states: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    n = n_params + n_states
    theta = torch.rand(b, n, generator=g, dtype=torch.float64) * 100 + 1
    std = torch.rand(b, n, generator=g, dtype=torch.float64)
    std[0, 1] = math.inf  # an unidentified parameter
    singular = torch.rand(b, n, generator=g, dtype=torch.float64).sort(1, descending=True).values
    singular[min(1, b - 1), -1] = 0.0  # rank deficient: condition number inf
    status = torch.randint(0, len(STATUS_LABELS), (b,), generator=g)
    result = SolverResult(
        params=theta,
        status=status,
        iterations=torch.randint(0, 40, (b,), generator=g),
        loss=torch.rand(b, generator=g, dtype=torch.float64),
        loss_history=torch.zeros(1, b, dtype=torch.float64),
        std=std,
        covariance=torch.zeros(b, n, n, dtype=torch.float64),
        singular_values=singular,
        residual_variance=torch.ones(b, dtype=torch.float64),
        relative_residual=torch.rand(b, generator=g, dtype=torch.float64),
        whiteness=torch.full((b,), math.inf, dtype=torch.float64),
    )
    return {
        "final": result,
        "params": theta,
        "index": torch.arange(b) * 3 + 7,
        "relative_loss": torch.rand(b, generator=g, dtype=torch.float32),  # a float32 column: repr of its float
        "restarts": torch.randint(0, 3, (b,), generator=g),
        "extra": {"model": [f"m{i}" for i in range(b)], "f_body": torch.rand(b, generator=g, dtype=torch.float64)},
    }


def _status_by_entry(record: dict, i: int) -> list:
    r = record["final"]
    s = r.singular_values[i]
    condition = float(s[0] / s[-1]) if float(s[-1]) > 0 else math.inf
    return [
        int(record["index"][i]),
        STATUS_LABELS[int(r.status[i])],
        int(r.iterations[i]),
        repr(float(r.loss[i])),
        repr(float(record["relative_loss"][i])),
        int(record["restarts"][i]),
        repr(condition),
        repr(float(r.relative_residual[i])),
        repr(float(r.whiteness[i])),
    ]


def test_block_tables_format_every_entry_as_alone():
    n_params, n_states, b = 10, 6, 33
    record = _record(b, n_params, n_states)
    rows, status, columns = block_tables(record, n_params, K3, extra=("model", "f_body"))
    names = [f"p{i}" for i in range(1, n_params + 1)] + [f"x{i}" for i in range(n_states)]
    header = estimates_header(names, n_params, extra=("model", "f_body"))
    theta, std = record["params"], record["final"].std
    m3, m3_std, low, high = m3_interval(theta[:, :n_params], std[:, :n_params], K3)
    assert len(rows) == len(status) == b
    for i in range(b):
        row = dict(zip(header, rows[i], strict=True))
        assert row["index"] == int(record["index"][i])
        assert row["status"] == STATUS_LABELS[int(record["final"].status[i])]
        for j, name in enumerate(names):
            assert row[name] == repr(float(theta[i, j]))
            assert row[f"std_{name}"] == repr(float(std[i, j]))
        assert [row["m3"], row["m3_std"], row["m3_low"], row["m3_high"]] == [
            repr(float(v[i])) for v in (m3, m3_std, low, high)
        ]
        assert row["model"] == f"m{i}" and row["f_body"] == repr(float(record["extra"]["f_body"][i]))
        assert status[i] == _status_by_entry(record, i)
    assert status[0][6] == repr(float(record["final"].condition_number[0]))
    assert status[1][6] == "inf"
    assert torch.equal(columns["index"], record["index"])


def test_tables_of_an_empty_block_and_a_block_without_states():
    names = [f"p{i}" for i in range(1, 17)]
    empty = _record(2, 10, 6)
    keep = torch.zeros(2, dtype=torch.bool)
    fields = {
        k: (v[keep] if torch.is_tensor(v) and k != "loss_history" else v) for k, v in vars(empty["final"]).items()
    }
    empty.update(
        final=SolverResult(**fields),
        params=empty["params"][keep],
        index=empty["index"][keep],
        relative_loss=empty["relative_loss"][keep],
        restarts=empty["restarts"][keep],
    )
    assert block_tables(empty, 10, K3)[:2] == ([], [])
    rows, status, _ = block_tables(_record(5, 10, 0), 10, K3)
    assert len(status) == 5 and all(len(row) == len(estimates_header(names[:10], 10)) for row in rows)


def test_status_rows_refuse_a_length_mismatch():
    with pytest.raises(ValueError):
        status_rows(_record(3, 10, 0), [1, 2], ["a", "b"])


def test_vehicle_block_tables_format_every_entry_as_alone():
    layout = VehicleLayout("half_car")
    names = list(layout.param_names)
    n_params, b = len(names), 9
    record = _record(b, n_params, 4, seed=1)
    rows, status, _ = vehicle_block_tables(record, n_params, names, layout)
    header = vehicle_estimates_header(names + [f"x{i}" for i in range(4)], n_params, layout)
    theta, std = record["params"], record["final"].std
    for i in range(b):
        row = dict(zip(header, rows[i], strict=True))
        for j, name in enumerate(names):
            assert row[name] == repr(float(theta[i, j])) and row[f"std_{name}"] == repr(float(std[i, j]))
        for m in layout.seat_mass_names():
            j = names.index(m)
            assert row[f"{m}_low"] == repr(float(theta[i, j] - 1.96 * std[i, j]))
            assert row[f"{m}_high"] == repr(float(theta[i, j] + 1.96 * std[i, j]))
        assert row["x3"] == repr(float(theta[i, n_params + 3]))
        assert status[i] == _status_by_entry(record, i)
