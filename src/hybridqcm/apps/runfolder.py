"""Run folders: one run's outputs per folder, and a completion marker written last.

A run folder (hydra.run.dir) that already holds another run's artefacts is refused unless
`overwrite=true`; then our own artefacts (never anything else) are removed before the run
starts, so a new run never leaves the previous run's tables and plots beside its own.
The marker `.hybridqcm-done.json` is written after every artefact; it names the run's inputs
(the task overrides and each input file's size and mtime), so "this stage is done" means
"a run with exactly these inputs finished here" (pipeline.Stage.is_done).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from hybridqcm.atomic import atomic_write_text
from hybridqcm.errors import ConfigError

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


def existing_artefacts(run_dir: Path, names: Iterable[str], globs: Iterable[str] = ()) -> list[Path]:
    run_dir = Path(run_dir)
    found = [run_dir / n for n in names if (run_dir / n).exists()]
    for pattern in globs:
        found += sorted(run_dir.glob(pattern))
    return found


def prepare_run_dir(
    run_dir: str | Path,
    names: Sequence[str],
    overwrite: bool,
    globs: Sequence[str] = (),
    inputs: Iterable[str | os.PathLike | None] = (),
) -> Path:
    """Refuse a folder holding another run's artefacts (unless overwrite), clear ours when overwriting.

    inputs: files this run reads; clearing one of them (a checkpoint inside the folder) is refused.
    Raises ConfigError (one line) before any work."""
    run_dir = Path(run_dir)
    found = existing_artefacts(run_dir, names, globs)
    for given in (i for i in inputs if i):
        resolved = Path(given).resolve()
        for path in found:
            if resolved == path.resolve() or path.resolve() in resolved.parents:
                raise ConfigError(
                    f"{given} is an input of this run but lies in {path}, which overwrite would "
                    f"clear; choose another hydra.run.dir"
                )
    if found and not overwrite:
        shown = ", ".join(p.name for p in found[:4]) + (" ..." if len(found) > 4 else "")
        raise ConfigError(
            f"hydra.run.dir={run_dir} already holds another run's outputs ({shown}); "
            f"pass overwrite=true to clear them first, or choose another folder"
        )
    for path in found:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
    return run_dir


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
    "prepare_run_dir",
    "write_completion_marker",
    "read_completion_marker",
    "marker_matches",
    "task_overrides",
    "fingerprint",
]
