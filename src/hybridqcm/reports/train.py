"""qcm-train's outputs beyond the checkpoint: the test artefacts of a run folder and the summary of a sweep.

Run folder: predictions.csv, error_distribution.{csv,md}, sorted_predictions_<p>.png (parameter CNNs);
per_sample_mse.csv, mse_summary.{csv,md}, mse_hist_<channel>.png, examples.png (CAE, U-Net). Sweep
folder: summary.{csv,md} with every job's table and overrides (the MultirunSummary Hydra callback).
"""

from __future__ import annotations

import csv
import io
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from hybridqcm.atomic import atomic_write_text

log = logging.getLogger("qcm-train")


def _write_csv(path: Path, rows: Sequence[Mapping[str, Any]], fieldnames: Sequence[str] | None = None) -> None:
    buffer = io.StringIO()
    fieldnames = list(fieldnames or (rows[0].keys() if rows else []))
    writer = csv.DictWriter(buffer, fieldnames=fieldnames, extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow(row)
    atomic_write_text(path, buffer.getvalue())


# ---------------------------------------------------------------------------------------------------------
# test artefacts
def write_test_outputs(model, out_dir: Path, trainer=None) -> list[Path]:
    """predictions.csv + error_distribution.* + sorted plots (CNNs) or MSE tables/plots (CAE, U-Net)."""
    results = model.test_results or {}
    writer = model._tensorboard() if trainer is not None else None
    if hasattr(model, "estimate"):
        return _write_estimator_outputs(model, results, out_dir, writer)
    return _write_signal_outputs(model, results, out_dir, writer)


def _write_estimator_outputs(model, results: Mapping, out_dir: Path, writer) -> list[Path]:
    from hybridqcm.metrics import error_distribution_rows, write_error_distribution
    from hybridqcm.plots import close, plot_sorted_predictions

    names = list(model.hparams.target_channels)
    pred, index = results["pred"].numpy(), results["index"].numpy()
    true = results["true"].numpy() if "true" in results else None
    rows = []
    for i in range(pred.shape[0]):
        row = {"index": int(index[i])}
        for j, name in enumerate(names):
            if true is not None:
                row[f"{name}_true"] = repr(float(true[i, j]))
            row[f"{name}_pred"] = repr(float(pred[i, j]))
        rows.append(row)
    fields = ["index"] + [f"{n}_{k}" for n in names for k in (("true", "pred") if true is not None else ("pred",))]
    written = [out_dir / "predictions.csv"]
    _write_csv(written[0], rows, fields)
    if true is not None:
        table = error_distribution_rows(pred, true, names)
        written += list(
            write_error_distribution(table, out_dir, title=f"{type(model).__name__}: test set ({len(pred)} samples)")
        )
        for j, name in enumerate(names):
            path = out_dir / f"sorted_predictions_{name}.png"
            fig = plot_sorted_predictions(
                pred[:, j], true[:, j], name, path=path, title=f"{name}: test, sorted by true value"
            )
            if writer is not None:
                writer.add_figure(f"test/sorted_{name}", fig)
            close(fig)
            written.append(path)
    return written


def _write_signal_outputs(model, results: Mapping, out_dir: Path, writer) -> list[Path]:
    import numpy as np

    from hybridqcm.plots import close, plot_histogram

    names = list(model.data_requirements()["targets"])
    written = []
    if "mse" not in results:
        return written
    mse, rel = results["mse"].numpy(), results["rel_mse"].numpy()
    base = results["input_mse"].numpy() if "input_mse" in results else None
    rows = []
    for i in range(mse.shape[0]):
        row = {"index": int(results["index"][i])}
        for j, name in enumerate(names):
            row[f"mse_{name}"] = repr(float(mse[i, j]))
            row[f"rel_mse_{name}"] = repr(float(rel[i, j]))
            if base is not None:
                row[f"noisy_input_mse_{name}"] = repr(float(base[i, j]))
        rows.append(row)
    written.append(out_dir / "per_sample_mse.csv")
    _write_csv(written[-1], rows)
    summary = []
    for j, name in enumerate(names):
        m = mse[:, j]
        entry = {
            "channel": name,
            "n": int(m.size),
            "mean_mse": float(m.mean()),
            "median_mse": float(np.median(m)),
            "p95_mse": float(np.quantile(m, 0.95)),
            "max_mse": float(m.max()),
            "frac_below_1e-5": float((m < 1e-5).mean()),
            "frac_below_1e-4": float((m < 1e-4).mean()),
            "mean_rel_mse": float(rel[:, j].mean()),
            "max_rel_mse": float(rel[:, j].max()),
        }
        if base is not None:
            entry["mean_noisy_input_mse"] = float(base[:, j].mean())
        summary.append(entry)
        path = out_dir / f"mse_hist_{name}.png"
        fig = plot_histogram(
            m, path=path, title=f"{type(model).__name__}: per-sample MSE of {name} (test)", xlabel="MSE [(m/s²)²]"
        )
        if writer is not None:
            writer.add_figure(f"test/mse_hist_{name}", fig)
        close(fig)
        written.append(path)
    written.append(out_dir / "mse_summary.csv")
    _write_csv(written[-1], summary)
    lines = ["| " + " | ".join(summary[0].keys()) + " |", "|" + "---|" * len(summary[0])]
    lines += [
        "| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in s.values()) + " |" for s in summary
    ]
    atomic_write_text(out_dir / "mse_summary.md", "\n".join(lines) + "\n")
    written.append(out_dir / "mse_summary.md")
    if "examples" in results:
        path = out_dir / "examples.png"
        fig = model.example_figure(results["examples"], path=path)
        if writer is not None:
            writer.add_figure("test/examples", fig)
        close(fig)
        written.append(path)
    return written


# ---------------------------------------------------------------------------------------------------------
# multirun summary
def summarize_multirun(sweep_dir: str | Path) -> Path | None:
    """Collect each job's error_distribution.csv / mse_summary.csv (+ its overrides) into sweep_dir/summary.{csv,md}."""
    sweep_dir = Path(sweep_dir)
    rows: list[dict] = []
    for job in sorted((p for p in sweep_dir.iterdir() if p.is_dir()), key=lambda p: (len(p.name), p.name)):
        overrides_file = job / ".hydra" / "overrides.yaml"
        overrides = yaml.safe_load(overrides_file.read_text()) if overrides_file.exists() else []
        for table in ("error_distribution.csv", "mse_summary.csv"):
            if (job / table).exists():
                with open(job / table, newline="") as handle:
                    for row in csv.DictReader(handle):
                        rows.append({"job": job.name, "overrides": " ".join(overrides or []), "table": table, **row})
    if not rows:
        return None
    fields: list[str] = []
    for row in rows:
        fields += [k for k in row if k not in fields]
    path = sweep_dir / "summary.csv"
    _write_csv(path, rows, fields)
    lines = ["| " + " | ".join(fields) + " |", "|" + "---|" * len(fields)]
    lines += ["| " + " | ".join(str(r.get(f, "")) for f in fields) + " |" for r in rows]
    atomic_write_text(sweep_dir / "summary.md", "\n".join(lines) + "\n")
    return path


try:
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover
    _HydraCallback = object


class MultirunSummary(_HydraCallback):
    """Hydra callback: after a multirun, write summary.csv/.md into the sweep folder."""

    def on_multirun_end(self, config, **kwargs: Any) -> None:
        try:
            path = summarize_multirun(config.hydra.sweep.dir)
        except Exception as error:  # noqa: BLE001 - a summary must never fail the sweep
            log.warning("multirun summary failed: %s", error)
            return
        if path is not None:
            log.info("multirun summary: %s", path)
