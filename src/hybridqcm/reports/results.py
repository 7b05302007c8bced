"""The results page (`qcm-results`): our error-distribution tables beside the source study's, from
pipeline run folders (their manifests, reports/manifest.py).

Every table of the source (reference/thesis_tables.csv) that a run answers is shown row by row
with ours beside it, and a verdict per row: we beat the source when our mean error is lower,
our fraction within 10 % is not lower, our fraction above 25 % is not higher and our max error
is lower. Runs without a source table (noise sweeps, the U-Net) are listed with their own tables;
a pipeline's noise-sweep stages (the `noise` pipeline) also get one table over all its noise levels.
Fails loudly on a missing or malformed run folder.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import shutil
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path

from hybridqcm.atomic import atomic_write_text
from hybridqcm.console import print_table
from hybridqcm.metrics import COLUMNS, read_error_distribution
from hybridqcm.reports.manifest import load_manifest

STAGE_KEYS = ("app", "run_dir", "command", "setting")  # what the page reads of every stage record


def load_thesis_tables(path: str | Path | None = None) -> list[dict]:
    """Rows of the source's result tables (floats parsed, empty cells None)."""
    if path is None:
        text = resources.files("hybridqcm").joinpath("reference/thesis_tables.csv").read_text()
    else:
        text = Path(path).read_text()
    rows = []
    for raw in csv.DictReader(text.splitlines()):
        row = dict(raw)
        for key in COLUMNS[2:]:  # the source rows carry our error-distribution columns
            row[key] = float(row[key])
        rows.append(row)
    return rows


def verdict(ours: dict, source: dict) -> tuple[bool, list[str]]:
    """Whether our row beats the source's on mean, within-10 %, over-25 % and max; what fell short."""
    short = []
    if not ours["mean_err"] < source["mean_err"]:
        short.append("mean")
    if not ours["within_10pct"] >= source["within_10pct"]:
        short.append("≤10 %")
    if not ours["over_25pct"] <= source["over_25pct"]:
        short.append(">25 %")
    if not ours["max_err"] < source["max_err"]:
        short.append("max")
    return not short, short


def _pct(x: float) -> str:
    return f"{100 * x:.3g} %" if x < 10 else f"{100 * x:.0f} %"


def _stage_rows(stage: dict) -> list[dict]:
    run_dir = Path(stage["run_dir"])
    if not run_dir.is_dir():
        raise FileNotFoundError(f"stage {stage['name']}: run folder {run_dir} does not exist")
    return read_error_distribution(run_dir / "error_distribution.csv")


def compare_stage(stage: dict, thesis: list[dict]) -> list[dict]:
    """Side-by-side rows for one stage that answers a source table (test split)."""
    ours = {r["param"]: r for r in _stage_rows(stage)}
    source_rows = [r for r in thesis if r["table"] == stage["table"] and r["split"] == "test"]
    if not source_rows:
        raise ValueError(f"stage {stage['name']}: no test rows for table {stage['table']} in the source tables")
    out = []
    for src in source_rows:
        name = f"p{src['param']}"
        mine = ours.get(name)
        if mine is None:
            out.append({"param": name, "source": src, "ours": None, "beat": False, "short": ["missing"]})
            continue
        beat, short = verdict(mine, src)
        out.append({"param": name, "source": src, "ours": mine, "beat": beat, "short": short})
    return out


def _markdown_comparison(rows: list[dict]) -> str:
    header = (
        "| param | mean (source → ours) | ≤10 % (source → ours) | >25 % (source → ours) | max (source → ours) | beat |"
    )
    lines = [header, "|---|---|---|---|---|---|"]
    for r in rows:
        s, o = r["source"], r["ours"]
        if o is None:
            lines.append(f"| {r['param']} | {_pct(s['mean_err'])} → — | | | | ✗ not estimated |")
            continue
        mark = "✓" if r["beat"] else "✗ (" + ", ".join(r["short"]) + ")"
        if not r["beat"] and o.get("n"):  # say how many samples the verdict hangs on
            over = round(o["over_25pct"] * o["n"])
            mark += f": {over} of {int(o['n'])} samples above 25 %"
        lines.append(
            f"| {r['param']} | {_pct(s['mean_err'])} → **{_pct(o['mean_err'])}** | {_pct(s['within_10pct'])} → "
            f"**{_pct(o['within_10pct'])}** | {_pct(s['over_25pct'])} → **{_pct(o['over_25pct'])}** | "
            f"{_pct(s['max_err'])} → **{_pct(o['max_err'])}** | {mark} |"
        )
    return "\n".join(lines) + "\n"


def _in_pipeline_order(manifest: dict, stage_order: Mapping[str, Sequence[str]]) -> list[dict]:
    """The manifest's stages in the order its pipeline defines them (``stage_order``: pipeline name -> stage
    names; records are merged as runs finish); a pipeline not in it keeps the manifest's order."""
    order = {name: i for i, name in enumerate(stage_order.get(manifest.get("pipeline"), ()))}
    return sorted(manifest["stages"], key=lambda stage: order.get(stage["name"], len(order)))


def _sweep_rows(stages: list[dict], filename: str, what: str, cells) -> list[str]:
    """One row per noise-sweep stage, by noise level: ``cells(report)`` turns the run's ``filename``
    (JSON) into (recordings, [cell, ...]); a missing file or a report without them fails naming it."""
    rows = []
    for stage in sorted(stages, key=lambda st: st["noise"]):
        path = Path(stage["run_dir"]) / filename
        try:
            n, row = cells(json.loads(path.read_text()))
        except FileNotFoundError:
            raise FileNotFoundError(f"stage {stage['name']}: {path} does not exist") from None
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"stage {stage['name']}: {path}: no {what} ({error!r})") from None
        method = stage["setting"].rsplit(", additive noise", 1)[0]
        rows.append(f"| {_pct(stage['noise'])} | {method} | {n} | " + " | ".join(row) + " |")
    return rows


def _estimate_cells(summary: dict) -> tuple[int, list[str]]:
    """An estimation run's summary.json: the occupant mass m3's errors, its 95 % interval's coverage
    and width, the status counts and the solve time."""
    counts, n = summary["status_counts"], int(summary["n_samples"])
    keys = ("m3_mean_rel_err", "m3_p95_rel_err", "m3_within_1pct", "m3_within_5pct", "m3_coverage_95")
    converged, misfit = counts.get("converged", 0), counts.get("misfit", 0)
    # the converged recordings' mean / max (summaries written before they were recorded: a dash)
    mean_c, max_c = summary.get("m3_mean_rel_err_converged"), summary.get("m3_max_rel_err_converged")
    return n, [
        *(_pct(summary[k]) for k in (*keys, "m3_interval_median_rel_width")),
        "—" if mean_c is None or max_c is None else f"{_pct(mean_c)} / {_pct(max_c)}",
        f"{converged} / {misfit} / {n - converged - misfit}",
        f"{1000.0 * summary['seconds_solve'] / max(n, 1):.0f}",
    ]


def _network_cells(report: dict) -> tuple[int, list[str]]:
    """A network evaluation's test_metrics.json: every estimated parameter's mean and max error, > 25 %."""
    metrics, n = report["metrics"], int(report["n_test"])
    params = sorted({key.split("/")[1] for key in metrics if key.endswith("/mean_rel_err") and key.count("/") == 2})
    kinds = ("mean_rel_err", "max_rel_err", "over_25pct")
    return n, [" / ".join(params), *(" / ".join(_pct(metrics[f"test/{p}/{k}"]) for p in params) for k in kinds)]


def _noise_table(stages: list[dict]) -> str:
    """One table over a noise sweep's estimation stages (those with a ``noise`` level), from each run's
    summary.json (``_estimate_cells``)."""
    lines = [
        "| noise (of RMS) | method | recordings | m3 mean error | m3 p95 | m3 within 1 % | m3 within 5 % "
        "| 95 % coverage | median width | converged: m3 mean / max | converged / misfit / other | GN s per 1 000 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    return "\n".join(lines + _sweep_rows(stages, "summary.json", "m3 summary", _estimate_cells)) + "\n"


def _network_noise_table(stages: list[dict]) -> str:
    """One table over a noise sweep's network evaluations (qcm-train stages with a ``noise`` level),
    from each run's test_metrics.json (``_network_cells``)."""
    lines = [
        "| noise (of RMS) | network | recordings | parameters | mean error | max error | above 25 % |",
        "|---|---|---|---|---|---|---|",
    ]
    return "\n".join(lines + _sweep_rows(stages, "test_metrics.json", "test metrics", _network_cells)) + "\n"


def _display(command: str) -> str:
    """The command as a user types it: the console script's name instead of its path in the venv."""
    head, _, rest = command.partition(" ")
    return f"{Path(head).name} {rest}".strip()


def _stage_section(stage: dict, thesis: list[dict], pipeline: str, output: Path, copy_plots: bool):
    """One stage's part of the page: title, command, training time, its table (beside the source's when it
    answers one) and extra tables, links to its sorted-prediction plots (copied beside ``output``).
    Returns (lines, compared rows)."""
    if stage["app"] == "qcm-simulate":
        return [f"### {stage['name']}", "", f"`{_display(stage['command'])}`", ""], []
    answers = f" — source table {stage['table']}: " if stage.get("table") else " — "
    seconds = stage.get("seconds")
    wall = f"  \nWall time: {seconds:.0f} s on this machine" if seconds else ""
    parts = [
        f"### {stage['name']}{answers}{stage['setting']}",
        "",
        f"Command: `{_display(stage['command'])}`{wall}",
        "",
    ]
    run_dir = Path(stage["run_dir"])
    metrics_path = run_dir / "test_metrics.json"
    if metrics_path.exists():
        metrics = json.loads(metrics_path.read_text())
        if metrics.get("train_seconds"):
            data = metrics.get("data_path") or "freshly simulated data"
            parts += [
                f"Training: {metrics['train_seconds']:.0f} s, {metrics.get('steps')} optimiser steps "
                f"(tested on {metrics.get('n_test')} samples of {data})",
                "",
            ]
    rows = []
    if stage.get("table"):
        rows = compare_stage(stage, thesis)
        parts.append(_markdown_comparison(rows))
    elif (run_dir / "error_distribution.md").exists():
        parts.append((run_dir / "error_distribution.md").read_text())
    elif not run_dir.is_dir():
        raise FileNotFoundError(f"stage {stage['name']}: run folder {run_dir} does not exist")
    for extra in ("mse_summary.md", "calibration.md", "timing.md"):
        if (run_dir / extra).exists():
            parts += [(run_dir / extra).read_text(), ""]
    if copy_plots and stage.get("table"):
        plots = sorted(run_dir.glob("sorted_*.png")) + sorted(run_dir.glob("plots/sorted_*.png"))
        if plots:
            folder = f"results/{pipeline}/{stage['name']}"
            (output.parent / folder).mkdir(parents=True, exist_ok=True)
            for plot in plots[:10]:
                shutil.copyfile(plot, output.parent / folder / plot.name)
            links = [f"[{plot.stem}]({folder}/{plot.name})" for plot in plots[:10]]
            parts += ["Sorted-prediction plots: " + " · ".join(links), ""]
    return parts, rows


def render(
    manifests: list[Path],
    output: Path,
    copy_plots: bool = True,
    command: str = "make results",
    stage_order: Mapping[str, Sequence[str]] | None = None,
) -> tuple[str, int, int]:
    """Write the results page; returns (markdown, rows beaten, rows compared). ``stage_order`` (pipeline
    name -> its stage names in order) orders each manifest's stages; without it they keep the manifest's order."""
    thesis = load_thesis_tables()
    header = [
        "# Results",
        "",
        f"Generated by `qcm-results` from {', '.join(f'`{m}`' for m in manifests)} on "
        f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC. Do not edit by hand: rerun `{command}`.",
        "",
        "Each table: the source study's test-set row (`reference/thesis_tables.csv`) → ours, per parameter. "
        "A row is beaten (✓) when our mean error is lower, our fraction within 10 % is not lower, our fraction "
        "above 25 % is not higher and our max error is lower.",
        "",
    ]
    parts: list[str] = []
    beaten = compared = 0
    for manifest_path in manifests:
        manifest = load_manifest(manifest_path, STAGE_KEYS)
        parts += [f"## Pipeline `{manifest['pipeline']}` — dataset `{manifest.get('dataset')}`", ""]
        ordered = _in_pipeline_order(manifest, stage_order or {})
        swept = [stage for stage in ordered if stage.get("noise") is not None]
        estimated = [stage for stage in swept if stage["app"] != "qcm-train"]
        networks = [stage for stage in swept if stage["app"] == "qcm-train"]
        if estimated:
            parts += [_noise_table(estimated), ""]
        if networks:
            parts += [_network_noise_table(networks), ""]
        for stage in ordered:
            section, rows = _stage_section(stage, thesis, manifest["pipeline"], output, copy_plots)
            parts += section
            beaten += sum(r["beat"] for r in rows)
            compared += len(rows)
    verdict_line = (
        f"**Rows beaten: {beaten} of {compared} compared.**"
        if compared
        else "No table of the source study is answered by these runs."
    )
    parts += _generated_tables(output.parent)
    text = "\n".join(header + [verdict_line, ""] + parts)
    atomic_write_text(output, text)
    return text, beaten, compared


# Tables generated by their own bench scripts (docs/results/<name>.md), included as they are.
GENERATED_TABLES = (
    ("persons.md", "bench/persons_table.py"),
    ("calibration.md", "bench/calibration_table.py"),
    ("calibration_linear.md", "bench/calibration_table.py"),
)


def _generated_tables(docs: Path) -> list[str]:
    """The bench-generated tables that exist beside the page, each under its own heading."""
    return [line for name, script in GENERATED_TABLES for line in _generated_block(docs, name, script) or []]


def _source_line(name: str, script: str) -> str:
    """The line under a generated table's heading that names where it comes from (and finds it on a page)."""
    return f"(from `{script}`; also [results/{name}](results/{name}))"


def _generated_block(docs: Path, name: str, script: str) -> list[str] | None:
    """docs/results/<name> as the page's section (its heading, the source line, the table), None where absent."""
    path = docs / "results" / name
    if not path.is_file():
        return None
    lines = path.read_text().splitlines()
    title = lines[0].lstrip("# ") if lines and lines[0].startswith("#") else name
    return [f"## {title}", "", _source_line(name, script), ""] + lines[1:] + [""]


def refresh_generated_tables(page: Path) -> list[str]:
    """Re-include the bench-generated tables (docs/results/<name> beside ``page``) into a page that render wrote,
    in place and without the pipelines' run folders: each table's section — found by its source line, from its
    heading to the next generated table's or the page's end (render puts them last, so a table may hold headings
    of its own) — becomes the table as it is now, and one not yet on the page is appended. The rest of the page,
    a table whose file is gone included, is left as it is. -> the tables' names refreshed."""
    if not page.is_file():
        raise FileNotFoundError(f"{page}: no results page to refresh; write it with qcm-results first")
    lines = page.read_text().split("\n")
    refreshed = []
    for name, script in GENERATED_TABLES:
        block = _generated_block(page.parent, name, script)
        if block is None:
            continue
        try:
            start = lines.index(_source_line(name, script)) - 2
        except ValueError:  # not on the page yet: after everything, as render would have put it
            lines += block
            refreshed.append(name)
            continue
        if start < 0 or not lines[start].startswith("## "):
            raise ValueError(f"{page}: the section of results/{name} has no heading two lines above its source line")
        others = {_source_line(n, sc) for n, sc in GENERATED_TABLES if n != name}
        end = min([i - 2 for i, line in enumerate(lines) if line in others and i - 2 > start] or [len(lines)])
        lines[start:end] = block  # a section ends with its blank line, as the block does
        refreshed.append(name)
    atomic_write_text(page, "\n".join(lines))
    return refreshed


def print_summary(manifest_path: str | Path) -> None:
    """Console tables of one pipeline's runs beside the source (used at the end of qcm-pipeline)."""
    thesis = load_thesis_tables()
    manifest = load_manifest(manifest_path, STAGE_KEYS)
    for stage in manifest["stages"]:
        if not stage.get("table"):
            continue
        try:
            rows = compare_stage(stage, thesis)
        except (FileNotFoundError, ValueError) as error:
            print(f"{stage['name']}: {error}")
            continue
        table = []
        for r in rows:
            s, o = r["source"], r["ours"]
            if o is None:
                table.append([r["param"], _pct(s["mean_err"]), "—", "", "", "", "", "", "", "✗"])
                continue
            table.append(
                [
                    r["param"],
                    _pct(s["mean_err"]),
                    _pct(o["mean_err"]),
                    _pct(s["within_10pct"]),
                    _pct(o["within_10pct"]),
                    _pct(s["over_25pct"]),
                    _pct(o["over_25pct"]),
                    _pct(s["max_err"]),
                    _pct(o["max_err"]),
                    "✓" if r["beat"] else "✗ " + ",".join(r["short"]),
                ]
            )
        print_table(
            f"{stage['name']} vs source table {stage['table']} ({stage['setting']})",
            [
                "param",
                "mean src",
                "mean ours",
                "≤10% src",
                "≤10% ours",
                ">25% src",
                ">25% ours",
                "max src",
                "max ours",
                "beat",
            ],
            table,
        )
