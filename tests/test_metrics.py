"""Error-distribution metrics against hand-computed values, the CSV round trip, and the plots."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hybridqcm.metrics import (
    COLUMNS,
    ErrorDistribution,
    error_distribution_rows,
    read_error_distribution,
    relative_errors,
    write_error_distribution,
)

# p1 errors 0.5 %, 3 %, 20 %, 40 % (none on a threshold); p2 errors 0, 1.5 %, 8 %, 30 %
TARGET = torch.tensor([[100.0, 10.0], [200.0, 20.0], [50.0, 40.0], [400.0, 5.0]], dtype=torch.float64)
PRED = torch.tensor([[100.5, 10.0], [194.0, 20.3], [60.0, 36.8], [560.0, 3.5]], dtype=torch.float64)
E1 = [0.005, 0.03, 0.2, 0.4]
E2 = [0.0, 0.015, 0.08, 0.3]


def hand_row(name, e):
    mean = sum(e) / 4
    return {
        "param": name,
        "n": 4,
        "max_err": max(e),
        "mean_err": mean,
        "std_err": math.sqrt(sum((x - mean) ** 2 for x in e) / 4),
        "within_1pct": sum(x <= 0.01 for x in e) / 4,
        "within_5pct": sum(x <= 0.05 for x in e) / 4,
        "within_10pct": sum(x <= 0.10 for x in e) / 4,
        "within_25pct": sum(x <= 0.25 for x in e) / 4,
        "over_25pct": sum(x > 0.25 for x in e) / 4,
    }


def assert_rows_equal(rows, expected):
    assert len(rows) == len(expected)
    for row, exp in zip(rows, expected):
        assert row["param"] == exp["param"] and row["n"] == exp["n"]
        for key in COLUMNS[2:]:
            assert row[key] == pytest.approx(exp[key], rel=1e-12, abs=1e-15), key


def test_relative_errors_by_hand():
    e = relative_errors(PRED, TARGET)
    np.testing.assert_allclose(e.numpy(), np.array([E1, E2]).T, rtol=1e-12, atol=1e-15)
    assert e.dtype == torch.float64
    # numpy input, and a non-finite prediction counts as an infinite error
    e = relative_errors(np.array([[np.nan, 1.0]]), np.array([[2.0, 4.0]]))
    assert math.isinf(e[0, 0]) and e[0, 1] == 0.75
    with pytest.raises(ValueError, match="differ in shape"):
        relative_errors(PRED, TARGET[:3])


def test_error_distribution_fractions_by_hand():
    # hand values: p1 fractions 1/4, 2/4, 2/4, 3/4, 1/4; mean 15.875 %
    expected = [hand_row("p1", E1), hand_row("p2", E2)]
    assert (
        expected[0]["within_1pct"] == 0.25 and expected[0]["within_25pct"] == 0.75 and expected[0]["over_25pct"] == 0.25
    )
    assert expected[0]["mean_err"] == pytest.approx(0.15875)
    metric = ErrorDistribution(["p1", "p2"])
    metric.update(PRED[:3], TARGET[:3])  # accumulated over two batches
    metric.update(PRED[3:], TARGET[3:])
    assert_rows_equal(metric.compute(), expected)
    assert_rows_equal(error_distribution_rows(PRED, TARGET, ["p1", "p2"]), expected)
    scalars = metric.scalars("test/")
    assert scalars["test/p1/over_25pct"] == 0.25 and scalars["test/p2/within_10pct"] == 0.75
    assert "test/p1/n" not in scalars
    metric.reset()
    with pytest.warns(UserWarning, match="before the ``update``"):
        assert metric.compute()[0]["n"] == 0


def test_error_distribution_counts_non_finite_predictions():
    pred = PRED.clone()
    pred[1, 0] = float("inf")
    row = error_distribution_rows(pred, TARGET, ["p1", "p2"])[0]
    assert row["non_finite"] == 1 and row["max_err"] == math.inf
    assert row["over_25pct"] == 0.5 and row["within_25pct"] == 0.5
    with pytest.raises(ValueError, match="names"):
        error_distribution_rows(PRED, TARGET, ["p1"])


def test_csv_round_trip(tmp_path):
    pred = PRED.clone()
    pred[2, 1] = float("nan")
    rows = error_distribution_rows(pred, TARGET, ["p1", "p2"])
    csv_path, md_path = write_error_distribution(rows, tmp_path / "out", title="test set")
    assert csv_path.name == "error_distribution.csv" and md_path.name == "error_distribution.md"
    back = read_error_distribution(csv_path)
    # every value, including inf, nan (std of a column with an inf) and the non-finite count
    assert [sorted(r) for r in back] == [sorted(r) for r in rows]
    for row, orig in zip(back, rows):
        for key, value in orig.items():
            assert row[key] == value or (isinstance(value, float) and math.isnan(value) and math.isnan(row[key])), key
    assert rows[1]["non_finite"] == 1 and math.isnan(rows[1]["std_err"])
    markdown = md_path.read_text()
    assert "**test set**" in markdown and "| p1 | 40 % | 15.9 % |" in markdown
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["error_distribution.csv", "error_distribution.md"]


@pytest.mark.parametrize(
    "content,pattern",
    [
        ("param,n,max_err\np1,4,0.4\n", r"missing columns \['mean_err'"),
        ("", "missing columns"),
        (",".join(COLUMNS) + "\np1,4,0.4,zero,0.1,0.25,0.5,0.5,0.75,0.25\n", r":2: malformed value"),
        (",".join(COLUMNS) + "\np1,4,0.4,0.1\n", r":2: malformed value"),
        (",".join(COLUMNS) + "\n,4,0.4,0.1,0.1,0.25,0.5,0.5,0.75,0.25\n", r":2: row without a parameter name"),
    ],
)
def test_read_malformed_table_fails_loudly(tmp_path, content, pattern):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(ValueError, match=pattern):
        read_error_distribution(path)


def test_read_missing_table(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        read_error_distribution(tmp_path / "none.csv")


def test_plots_write_png(tmp_path):
    from hybridqcm import plots

    rng = np.random.default_rng(0)
    target = rng.uniform(4, 20, 300)
    figure = plots.plot_sorted_predictions(
        target * (1 + 0.1 * rng.normal(size=300)), target, "p1", tmp_path / "a" / "p1.png"
    )
    plots.close(figure)
    figure = plots.plot_histogram(np.abs(rng.normal(size=300)), tmp_path / "h.png", xlabel="e")
    plots.close(figure)
    figure = plots.plot_overlays(
        np.arange(50) * 0.01, {"true": rng.normal(size=(2, 50)), "est": rng.normal(size=(2, 50))}, tmp_path / "o.png"
    )
    plots.close(figure)
    for name in ("a/p1.png", "h.png", "o.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "h.png", "o.png"]  # no temporary files left
