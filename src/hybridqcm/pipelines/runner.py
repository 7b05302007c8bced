"""Runs a pipeline (catalog.py) stage by stage, each stage one console-script call with its own run folder.

A stage that is done (stage.py) is skipped, so an interrupted pipeline resumes where it stopped.
Every finished stage is recorded in `<root>/manifest.json` (reports/manifest.py); at the end the
runs are printed beside the source study's tables (reports/results.py).
"""

from __future__ import annotations

import shlex
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

from hybridqcm.pipelines.catalog import PIPELINES
from hybridqcm.pipelines.stage import BIN
from hybridqcm.reports.manifest import manifest_path, record_stage
from hybridqcm.reports.results import print_summary


def run_pipeline(
    name: str,
    root: str | None = None,
    dataset: str | None = None,
    only: list[str] | None = None,
    plan: bool = False,
    **options,
) -> int:
    root = root or f"outputs/{name}"
    dataset = dataset or ("data/reference.h5" if name == "reproduce" else "data/demo.h5")
    stages = all_stages = PIPELINES[name](root, dataset, **options)
    by_name = {s.name: s for s in all_stages}
    if only:
        unknown = sorted(set(only) - {s.name for s in stages})
        if unknown:
            raise SystemExit(f"error: unknown stage(s) {unknown}; stages: {[s.name for s in stages]}")
        stages = [s for s in stages if s.name in only]
    missing = sorted({f for s in stages if not s.is_done() for f in s.requires if not Path(f).exists()})
    if missing and not plan:
        raise SystemExit(
            f"error: {name} needs {missing}, which do not exist"
            + (" (run `make demo` first: its dataset and networks)" if name == "noise" else "")
        )
    total = sum(s.minutes for s in stages if not s.is_done())
    print(
        f"[qcm-pipeline] {name}: {len(stages)} stages, about {total:.0f} min of work left on 2 CPU cores; root {root}"
    )
    if plan:
        for s in stages:
            state = "done" if s.is_done() else f"~{s.minutes:g} min"
            print(f"  {s.name:28s} {state:>10s}  {shlex.join(s.command())}")
        return 0
    for index, stage in enumerate(stages, 1):
        header = f"[{index}/{len(stages)}] {stage.name}"
        if stage.is_done():
            print(f"{header}: done already ({stage.run_dir}), skipped")
            record_stage(
                root,
                name,
                dataset,
                {**asdict(stage), "command": shlex.join(stage.command()), "seconds": None},
                replace=False,
            )
            continue
        missing = [n for n in stage.needs if not by_name[n].is_done()]
        if missing:
            print(f"{header}: needs {missing}, which did not finish; skipped")
            continue
        print(f"{header}: {shlex.join(stage.command())}", flush=True)
        start = time.perf_counter()
        result = subprocess.run(stage.command())
        seconds = time.perf_counter() - start
        if result.returncode != 0:
            print(
                f"{header}: FAILED (exit {result.returncode}) after {seconds:.0f} s; see {stage.run_dir}",
                file=sys.stderr,
            )
            return result.returncode
        record_stage(
            root, name, dataset, {**asdict(stage), "command": shlex.join(stage.command()), "seconds": round(seconds, 1)}
        )
        print(f"{header}: finished in {seconds:.0f} s -> {stage.run_dir}")
    record_stage(root, name, dataset, None)
    print_summary(manifest_path(root))
    print(
        f"\nArtefacts: dataset {dataset}; run folders under {root}/ (checkpoints, estimates.csv, error_distribution.*, plots)"
    )
    print(f"Manifest: {manifest_path(root)}    Results: qcm-results --manifest {manifest_path(root)}")
    print(f"TensorBoard: {BIN / 'tensorboard'} --logdir {root}")
    return 0
