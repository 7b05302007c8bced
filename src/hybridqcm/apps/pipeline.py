"""Stage-by-stage pipelines over the console scripts: `qcm-pipeline demo`, `reproduce` and `noise`.

Each stage is one console-script call with its own run folder. A stage whose outputs exist is
skipped, so an interrupted pipeline resumes where it stopped (delete a run folder to redo it).
Every finished stage is recorded in `<root>/manifest.json` (command, run folder, seconds,
which table of the source study it answers); `qcm-results` turns that manifest into tables.
The stages themselves live in `hybridqcm/pipelines/`, the manifest in `hybridqcm/reports/manifest.py`.
"""

from __future__ import annotations

import argparse
import sys

from hybridqcm.pipelines.catalog import PIPELINES
from hybridqcm.pipelines.runner import run_pipeline


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
