"""Stage-by-stage pipelines over the console scripts: `qcm-pipeline demo`, `reproduce` and `noise`.

Each stage is one console-script call with its own run folder. A stage whose outputs exist is
skipped, so an interrupted pipeline resumes where it stopped (delete a run folder to redo it).
Every finished stage is recorded in `<root>/manifest.json` (command, run folder, seconds,
which table of the source study it answers); `qcm-results` turns that manifest into tables.
The stages themselves and the manifest's reader/writer live in `apps/stages.py`.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

from hybridqcm.apps.results import print_summary
from hybridqcm.apps.stages import BIN, PIPELINES, manifest_path, record_stage


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="qcm-pipeline", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "pipeline",
        choices=sorted(PIPELINES),
        help="demo (small, ~20 min), reproduce (reference protocol) or noise (the occupant mass with and without "
        "the road at sensor noise 0-10 %%, on the demo's data and networks, ~30 min)",
    )
    parser.add_argument("--root", help="folder of the run folders and manifest (default outputs/<pipeline>)")
    parser.add_argument("--dataset", help="dataset file (default data/demo.h5 or data/reference.h5)")
    parser.add_argument("--only", nargs="+", metavar="STAGE", help="run only these stages")
    parser.add_argument(
        "--plan", action="store_true", help="print the stages, their commands and expected cost, run nothing"
    )
    parser.add_argument("--preset", help="demo only: qcm-simulate preset (default small; tiny for a smoke test)")
    parser.add_argument(
        "--train-time", help="demo only: time limit of each training run, DD:HH:MM:SS (default 00:00:04:00)"
    )
    parser.add_argument(
        "--networks", help="noise only: the pipeline root whose checkpoints it uses (default outputs/demo)"
    )
    args = parser.parse_args(argv)
    options = {k: v for k, v in (("preset", args.preset), ("train_time", args.train_time)) if v is not None}
    if options and args.pipeline != "demo":
        parser.error("--preset and --train-time apply to the demo pipeline only")
    if args.networks is not None:
        if args.pipeline != "noise":
            parser.error("--networks applies to the noise pipeline only")
        options["networks"] = args.networks
    return run_pipeline(args.pipeline, args.root, args.dataset, args.only, args.plan, **options)


if __name__ == "__main__":
    sys.exit(main())
