"""A pipeline's manifest (`<root>/manifest.json`): every finished stage's record (its Stage fields,
command, run folder, seconds, which table of the source study it answers).

The pipeline runner (pipelines/runner.py) writes it with `record_stage`, `qcm-results`
(reports/results.py) reads it with `load_manifest`; the format lives here, below both.
"""

from __future__ import annotations

import json
from pathlib import Path

from hybridqcm.atomic import atomic_write_text


def manifest_path(root: str) -> Path:
    return Path(root) / "manifest.json"


def load_manifest(path: str | Path, stage_keys: tuple[str, ...] = ()) -> dict:
    """The manifest at ``path``, every stage record a dict with a name (and each of ``stage_keys``);
    FileNotFoundError or ValueError (one line naming the file) otherwise."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: pipeline manifest not found (run `qcm-pipeline demo` or `reproduce` first)")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: malformed manifest ({error})") from None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("stages"), list):
        raise ValueError(f"{path}: malformed manifest (no 'stages' list)")
    if not isinstance(manifest.get("pipeline"), str) or not manifest["pipeline"]:
        raise ValueError(f"{path}: malformed manifest: pipeline = {manifest.get('pipeline')!r}, expected its name")
    for i, stage in enumerate(manifest["stages"]):
        if not isinstance(stage, dict) or "name" not in stage:
            raise ValueError(f"{path}: malformed manifest: stages[{i}] = {stage!r} is not a stage record")
    for i, stage in enumerate(manifest["stages"]):
        for key in stage_keys:
            if key not in stage:
                raise ValueError(f"{path}: malformed manifest: stages[{i}] ({stage['name']}) lacks {key!r}")
    return manifest


def record_stage(root: str, pipeline: str, dataset: str, record: dict | None, replace: bool = True) -> None:
    """Merge one stage's record into the manifest on disk (read, update, atomic rename), so two
    pipelines running `--only` different stages of the same root do not drop each other's records."""
    path = manifest_path(root)
    records = {r["name"]: r for r in load_manifest(path)["stages"]} if path.exists() else {}
    if record is not None and (replace or record["name"] not in records):
        records[record["name"]] = record
    atomic_write_text(
        path, json.dumps({"pipeline": pipeline, "dataset": dataset, "stages": list(records.values())}, indent=2)
    )
