"""The results generator: reads pipeline run folders, compares with the source, fails loudly."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from hybridqcm.apps import results as app
from hybridqcm.metrics import error_distribution_rows, write_error_distribution
from hybridqcm.reports import results


def _run_folder(tmp_path: Path, name: str, error_scale: float, n_params: int = 10, bias: float = 0.0) -> Path:
    """A run folder whose error table is written by the metrics code path from known errors."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(1, 2, size=(500, n_params))
    pred = truth * (1 + bias + error_scale * rng.standard_normal(truth.shape))
    run_dir = tmp_path / name
    write_error_distribution(error_distribution_rows(pred, truth, [f"p{i + 1}" for i in range(n_params)]), run_dir)
    return run_dir


def _manifest(tmp_path: Path, stages: list[dict]) -> Path:
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps({"pipeline": "test", "dataset": "x.h5", "stages": stages}))
    return path


def _stage(name, run_dir, table, app="qcm-estimate"):
    return {
        "name": name,
        "app": app,
        "run_dir": str(run_dir),
        "table": table,
        "setting": "s",
        "command": f"{app} ...",
        "seconds": 1.0,
    }


def test_verdict_requires_every_criterion():
    source = {"mean_err": 0.1, "within_10pct": 0.8, "over_25pct": 0.05, "max_err": 1.0}
    good = {"mean_err": 0.01, "within_10pct": 0.99, "over_25pct": 0.0, "max_err": 0.2}
    assert results.verdict(good, source) == (True, [])
    assert results.verdict({**good, "max_err": 1.5}, source) == (False, ["max"])
    assert results.verdict({**good, "mean_err": 0.1}, source)[1] == ["mean"]
    assert results.verdict({**good, "within_10pct": 0.5, "over_25pct": 0.06}, source)[1] == ["≤10 %", ">25 %"]


def test_thesis_tables_are_packaged_and_complete():
    rows = results.load_thesis_tables()
    tables = {r["table"] for r in rows}
    assert {"5.1", "5.11", "5.14", "5.15"} <= tables
    exp5 = [r for r in rows if r["table"] == "5.11"]
    assert len(exp5) == 10 and abs(exp5[2]["over_25pct"] - 0.77024) < 1e-9  # p3: 77 % of samples > 25 % off


def test_render_compares_with_source_rows(tmp_path):
    good = _run_folder(tmp_path, "good", 0.001)
    bad = _run_folder(tmp_path, "bad", 0.0, bias=999.0)  # every estimate 1000x too large
    manifest = _manifest(tmp_path, [_stage("exp5_good", good, "5.11"), _stage("exp5_bad", bad, "5.11")])
    text, beaten, compared = results.render([manifest], tmp_path / "RESULTS.md", copy_plots=False)
    assert compared == 20
    assert beaten == 10  # the accurate run beats all ten rows of table 5.11, the noisy one none
    assert (tmp_path / "RESULTS.md").read_text() == text
    assert "Rows beaten: 10 of 20" in text and "qcm-estimate ..." in text


def test_missing_parameter_is_reported_not_beaten(tmp_path):
    run_dir = _run_folder(tmp_path, "two", 0.001, n_params=2)
    rows = results.compare_stage(_stage("exp5", run_dir, "5.11"), results.load_thesis_tables())
    assert [r["beat"] for r in rows[:2]] == [True, True]
    assert all(r["short"] == ["missing"] for r in rows[2:])


def test_missing_run_folder_fails_loudly(tmp_path):
    manifest = _manifest(tmp_path, [_stage("exp5", tmp_path / "nowhere", "5.11")])
    with pytest.raises(FileNotFoundError, match="nowhere"):
        results.render([manifest], tmp_path / "R.md", copy_plots=False)
    assert app.main(["--manifest", str(manifest), "--output", str(tmp_path / "R.md")]) == 2
    assert not (tmp_path / "R.md").exists()


def test_malformed_table_and_manifest_fail_loudly(tmp_path):
    run_dir = tmp_path / "broken"
    run_dir.mkdir()
    (run_dir / "error_distribution.csv").write_text("param,n,max_err\np1,3,0.1\n")
    with pytest.raises(ValueError, match="missing columns"):
        results.render([_manifest(tmp_path, [_stage("exp5", run_dir, "5.11")])], tmp_path / "R.md", copy_plots=False)
    bad_manifest = tmp_path / "bad.json"
    bad_manifest.write_text("{not json")
    with pytest.raises(ValueError, match="malformed manifest"):
        results.render([bad_manifest], tmp_path / "R.md", copy_plots=False)
    assert app.main(["--manifest", str(tmp_path / "absent.json"), "--output", str(tmp_path / "R.md")]) == 2


@pytest.mark.parametrize(
    "manifest, message",
    [
        ({"stages": []}, r"pipeline = None, expected its name"),
        ({"pipeline": 3, "stages": []}, r"pipeline = 3, expected its name"),
        ({"pipeline": "demo", "stages": ["x"]}, r"stages\[0\] = .x. is not a stage record"),
        ({"pipeline": "demo", "stages": [{"name": "exp5", "run_dir": "r"}]}, r"stages\[0\] \(exp5\) lacks 'app'"),
    ],
)
def test_a_manifest_missing_what_results_read_is_one_line(tmp_path, capsys, manifest, message):
    """Before: KeyError tracebacks ('pipeline', 'app') from deep in the rendering."""
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(manifest))
    assert app.main(["--manifest", str(path), "--output", str(tmp_path / "R.md"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {path}: malformed manifest: ")
    assert re.search(message, err)
    assert not (tmp_path / "R.md").exists()


def test_unknown_table_id_fails(tmp_path):
    run_dir = _run_folder(tmp_path, "x", 0.01)
    with pytest.raises(ValueError, match="no test rows for table 9.99"):
        results.compare_stage(_stage("exp", run_dir, "9.99"), results.load_thesis_tables())


def test_noise_sweep_network_rows_read_each_evaluations_test_metrics(tmp_path):
    """A noise pipeline's network evaluations (qcm-train stages) get their own table by noise level, from
    test_metrics.json, apart from the estimation table; a run without it fails naming the file."""
    stages = []
    for sigma, mean in ((0.05, 0.0094), (0.0, 0.0015)):
        run_dir = _run_folder(tmp_path, f"cnn{sigma}", 0.001, n_params=2)
        metrics = {"test/loss": 0.1, "test/mean_rel_err": mean}
        for p, offset in (("p1", 0.0), ("p2", 0.0001)):
            metrics |= {
                f"test/{p}/mean_rel_err": mean + offset,
                f"test/{p}/max_rel_err": 0.14,
                f"test/{p}/over_25pct": 0,
            }
        (run_dir / "test_metrics.json").write_text(json.dumps({"n_test": 1200, "metrics": metrics}))
        stages.append(
            {
                **_stage(f"cnn_noise{sigma:g}", run_dir, None, app="qcm-train"),
                "noise": sigma,
                "setting": f"the CNN alone, additive noise {sigma:.0%}",
            }
        )
    text, _, _ = results.render([_manifest(tmp_path, stages)], tmp_path / "R.md", copy_plots=False)
    assert "m3 mean error" not in text  # no estimation stage, no estimation table
    rows = [line for line in text.splitlines() if line.startswith(("| 0 %", "| 5 %"))]
    assert rows == [
        "| 0 % | the CNN alone | 1200 | p1 / p2 | 0.15 % / 0.16 % | 14 % / 14 % | 0 % / 0 % |",
        "| 5 % | the CNN alone | 1200 | p1 / p2 | 0.94 % / 0.95 % | 14 % / 14 % | 0 % / 0 % |",
    ]
    (tmp_path / "cnn0.0" / "test_metrics.json").unlink()
    with pytest.raises(FileNotFoundError, match="cnn0.0/test_metrics.json"):
        results.render([_manifest(tmp_path, stages)], tmp_path / "R.md", copy_plots=False)


def test_noise_sweep_table_reads_each_runs_summary(tmp_path):
    """A noise pipeline's stages become one table ordered by noise level, numbers from summary.json;
    a run without its summary fails naming the file."""
    stages = []
    for sigma, mean in ((0.05, 0.0123), (0.0, 0.0001)):
        run_dir = _run_folder(tmp_path, f"occ{sigma}", 0.001, n_params=2)
        summary = {
            "n_samples": 200,
            "status_counts": {"converged": 190, "misfit": 6, "singular": 4},
            "m3_mean_rel_err": mean,
            "m3_p95_rel_err": 3 * mean,
            "m3_within_1pct": 0.5,
            "m3_within_5pct": 0.97,
            "m3_coverage_95": 0.951,
            "m3_interval_median_rel_width": 0.04,
            "seconds_solve": 10.0,
        }
        if sigma > 0:  # the 0 % run's summary predates the converged-only numbers
            summary.update(m3_mean_rel_err_converged=0.0105, m3_max_rel_err_converged=0.061)
        (run_dir / "summary.json").write_text(json.dumps(summary))
        stages.append(
            {
                **_stage(f"occupant_noise{sigma:g}", run_dir, None),
                "noise": sigma,
                "setting": f"road-free (a3, a2), additive noise {sigma:.0%}",
            }
        )
    text, _, _ = results.render([_manifest(tmp_path, stages)], tmp_path / "R.md", copy_plots=False)
    assert "No table of the source study is answered by these runs." in text and "Rows beaten" not in text
    rows = [line for line in text.splitlines() if line.startswith("| 0 %") or line.startswith("| 5 %")]
    assert [row.split(" | ")[0] for row in rows] == ["| 0 %", "| 5 %"]
    assert (
        "| road-free (a3, a2) | 200 | 1.23 % |" in rows[1]
        and "| 95.1 % |" in rows[1]
        and "| 1.05 % / 6.1 % | 190 / 6 / 4 | 50 |" in rows[1]
        and "| 4 % | — | 190 / 6 / 4 |" in rows[0]
    )
    (tmp_path / "occ0.0" / "summary.json").unlink()
    with pytest.raises(FileNotFoundError, match="occ0.0/summary.json"):
        results.render([_manifest(tmp_path, stages)], tmp_path / "R.md", copy_plots=False)


def test_bench_tables_are_included_under_their_own_heading(tmp_path):
    """A table a bench script generated (docs/results/persons.md) joins the results page as it is."""
    from hybridqcm.reports.results import _generated_tables

    assert _generated_tables(tmp_path) == []
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "persons.md").write_text("# Seated persons\n\n| a | b |\n|---|---|\n| 1 | 2 |\n")
    parts = _generated_tables(tmp_path)
    assert parts[0] == "## Seated persons" and "| 1 | 2 |" in parts and "bench/persons_table.py" in parts[2]
    (tmp_path / "results" / "calibration.md").write_text("# Seat calibration\n\n| c |\n|---|\n| 3 |\n")
    parts = _generated_tables(tmp_path)
    assert parts.index("## Seated persons") < parts.index("## Seat calibration") and "| 3 |" in parts
    assert "bench/calibration_table.py" in parts[parts.index("## Seat calibration") + 2]


def test_stages_appear_in_their_pipelines_order(tmp_path):
    """Manifest records are stored as stages finish; qcm-results lists them in the order the pipeline
    defines (the demo's stage list), the library's render without an order keeps the manifest's."""
    from hybridqcm.pipelines.catalog import demo_stages

    order = [stage.name for stage in demo_stages()]
    records = [_stage(name, _run_folder(tmp_path, name, 0.01, n_params=2), None) for name in reversed(order)]
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps({"pipeline": "demo", "dataset": "x.h5", "stages": records}))

    def headings(text):
        return [line.split(" — ")[0].removeprefix("### ") for line in text.splitlines() if line.startswith("### ")]

    assert app.main(["--manifest", str(path), "--output", str(tmp_path / "R.md"), "--no-plots"]) == 0
    assert headings((tmp_path / "R.md").read_text()) == order
    text, _, _ = results.render([path], tmp_path / "R2.md", copy_plots=False)
    assert headings(text) == order[::-1]


def test_tables_only_refreshes_the_bench_tables_as_render_would(tmp_path, capsys):
    """qcm-results --tables-only on a page render wrote, after the bench tables changed (a heading renamed, a
    table's own sub-heading, rows changed, a table new), gives the page render writes from the same run folders
    and the new tables."""
    good = _run_folder(tmp_path, "good", 0.001)
    manifest = _manifest(tmp_path, [_stage("exp5_good", good, "5.11")])
    docs = tmp_path / "docs"
    (docs / "results").mkdir(parents=True)
    persons, calibration = docs / "results" / "persons.md", docs / "results" / "calibration.md"
    persons.write_text("# Seated persons\n\n## A part of its own\n\n| a |\n|---|\n| 1 |\n")
    calibration.write_text("# Seat calibration\n\n| c |\n|---|\n| 3 |\n")
    results.render([manifest], docs / "RESULTS.md", copy_plots=False)
    persons.write_text("# Seated persons, remade\n\nGenerated today.\n\n## Its own part\n\n| a |\n|---|\n| 2 |\n")
    calibration.write_text("# Seat calibration\n\n| c |\n|---|\n| 4 |\n")
    (docs / "results" / "calibration_linear.md").write_text("# The linear seat\n\n| d |\n|---|\n| 5 |\n")
    assert app.main(["--tables-only", "--output", str(docs / "RESULTS.md")]) == 0
    assert "persons.md, calibration.md, calibration_linear.md" in capsys.readouterr().out
    refreshed = (docs / "RESULTS.md").read_text()
    (tmp_path / "again" / "results").mkdir(parents=True)
    for table in docs.joinpath("results").iterdir():
        (tmp_path / "again" / "results" / table.name).write_text(table.read_text())
    expected, _, _ = results.render([manifest], tmp_path / "again" / "RESULTS.md", copy_plots=False)

    def body(text):  # the page's own generation line carries the minute it was written
        return [line for line in text.split("\n") if not line.startswith("Generated by `qcm-results`")]

    assert body(refreshed) == body(expected) and "| 4 |" in refreshed and "| 3 |" not in refreshed
    assert "## A part of its own" not in refreshed  # the old table's own heading went with it
    assert app.main(["--tables-only", "--output", str(tmp_path / "none.md")]) == 2
    assert "none.md: no results page" in capsys.readouterr().err
    assert app.main(["--tables-only", "--manifest", str(manifest), "--output", str(docs / "RESULTS.md")]) == 2
    assert "--tables-only reads no manifest" in capsys.readouterr().err


def test_tables_only_leaves_a_table_whose_file_is_gone(tmp_path):
    """Only the tables on disk are refreshed: a section whose file was removed stays as the page had it, and the
    section before it ends where it starts."""
    docs = tmp_path / "docs"
    (docs / "results").mkdir(parents=True)
    page = docs / "RESULTS.md"
    page.write_text(
        "# Results\n\n## Seated persons\n\n"
        + results._source_line("persons.md", "bench/persons_table.py")
        + "\n\n| old |\n\n## Seat calibration\n\n"
        + results._source_line("calibration.md", "bench/calibration_table.py")
        + "\n\n| kept |\n"
    )
    (docs / "results" / "persons.md").write_text("# Seated persons\n\n| new |\n")
    assert results.refresh_generated_tables(page) == ["persons.md"]
    text = page.read_text()
    assert (
        "| new |" in text
        and "| old |" not in text
        and text.endswith(
            "## Seat calibration\n\n"
            + results._source_line("calibration.md", "bench/calibration_table.py")
            + "\n\n| kept |\n"
        )
    )
