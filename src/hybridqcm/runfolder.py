"""Run folders: one run's outputs per folder, and a completion marker written last.

A run folder (hydra.run.dir) that already holds another run's artefacts is refused unless
`overwrite=true`; then the files earlier runs recorded writing there (hybridqcm/runfiles.py: the
folder's manifest), never anything else, are removed before the run starts, so a new run never
leaves the previous run's tables and plots beside its own, and a user's own files stay.
The marker `.hybridqcm-done.json` is written after every artefact; it names the run's inputs
(the task overrides and each input file's size and mtime), so "this stage is done" means
"a run with exactly these inputs finished here" (pipeline.Stage.is_done).
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from hybridqcm import runfiles
from hybridqcm.atomic import atomic_write_text

MARKER = ".hybridqcm-done.json"
ESTIMATE_ARTEFACTS = (
    "estimates.csv",
    "status.csv",
    "error_distribution.csv",
    "error_distribution.md",
    "calibration.csv",
    "drives.csv",
    "drive_progress.csv",
    "summary.json",
    "plots",
    "tb",
    MARKER,
)
TRAIN_ARTEFACTS = (
    "checkpoints",
    "tensorboard",
    "test_metrics.json",
    "predictions.csv",
    "error_distribution.csv",
    "error_distribution.md",
    "per_sample_mse.csv",
    "mse_summary.csv",
    "mse_summary.md",
    "examples.png",
    MARKER,
)
TRAIN_GLOBS = ("sorted_predictions_*.png", "mse_hist_*.png")
ESTIMATE_SCRATCH = ("shards",)  # written under the run folder, no final output (a resumed run keeps them)
TRAIN_SCRATCH = ("csv", "mlruns")  # the csv and mlflow loggers' folders


def prepare_run_dir(
    run_dir: str | Path,
    names: Sequence[str],
    overwrite: bool,
    globs: Sequence[str] = (),
    inputs: Iterable[str | os.PathLike | None] = (),
    app: str | None = None,
    scratch: Sequence[str] = (),
) -> Path:
    """Refuse a folder holding another run's outputs (unless overwrite); when overwriting, remove only
    the files earlier runs recorded writing there (hybridqcm/runfiles.py), never the user's own.

    names / globs: the app's final outputs (top level); scratch: what else it writes there (shards, a
    logger's folder); inputs: files this run reads (clearing one of them, a checkpoint inside the folder,
    is refused). Raises ConfigError (one line) before any work."""
    return runfiles.begin(run_dir, app or Path(sys.argv[0]).name, overwrite, names, globs, inputs, scratch, MARKER)


def fingerprint(paths: Iterable[str | os.PathLike | None]) -> dict[str, list[int] | None]:
    """{path: [size, mtime_ns]} of each input file (None where it does not exist)."""
    out: dict[str, list[int] | None] = {}
    for p in paths:
        if not p:
            continue
        try:
            st = os.stat(p)
            out[str(p)] = [int(st.st_size), int(st.st_mtime_ns)]
        except OSError:
            out[str(p)] = None
    return out


def write_completion_marker(
    run_dir: str | Path, app: str, overrides: Sequence[str], input_files: Iterable[str | os.PathLike | None] = ()
) -> Path:
    """Write the marker last: app, task overrides and input file fingerprints."""
    record = {
        "app": app,
        "overrides": list(overrides),
        "inputs": fingerprint(input_files),
        "pid": os.getpid(),
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    return atomic_write_text(Path(run_dir) / MARKER, json.dumps(record, indent=2) + "\n")


def read_completion_marker(run_dir: str | Path) -> dict | None:
    try:
        data = json.loads((Path(run_dir) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def marker_matches(run_dir: str | Path, overrides: Sequence[str], base: str | Path | None = None) -> bool:
    """True when the folder's marker names exactly these overrides and its input files are unchanged."""
    marker = read_completion_marker(run_dir)
    if marker is None or list(marker.get("overrides", [])) != list(overrides):
        return False
    inputs: Mapping = marker.get("inputs") or {}
    return fingerprint(inputs) == dict(inputs)


def task_overrides() -> list[str]:
    """The current Hydra job's task overrides (empty outside Hydra)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    return [str(o) for o in HydraConfig.get().overrides.task]


__all__ = [
    "MARKER",
    "ESTIMATE_ARTEFACTS",
    "TRAIN_ARTEFACTS",
    "TRAIN_GLOBS",
    "ESTIMATE_SCRATCH",
    "TRAIN_SCRATCH",
    "prepare_run_dir",
    "write_completion_marker",
    "read_completion_marker",
    "marker_matches",
    "task_overrides",
    "fingerprint",
]
