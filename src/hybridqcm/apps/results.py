"""qcm-results: our error-distribution tables beside the source study's, from pipeline run folders.

    qcm-results                                   # outputs/{reproduce,demo,noise}/manifest.json -> docs/RESULTS.md
    qcm-results --manifest outputs/demo/manifest.json --output /tmp/R.md
    qcm-results --tables-only                     # docs/results/*.md (bench tables) into the existing page

``--tables-only`` re-includes the bench-generated tables (bench/persons_table.py, bench/calibration_table.py:
docs/results/*.md) into the page as they are now, and leaves the rest of it as it was: for a table remade on a
machine without the pipelines' run folders.

Every table of the source (reference/thesis_tables.csv) that a run answers is shown row by row
with ours beside it, and a verdict per row: we beat the source when our mean error is lower,
our fraction within 10 % is not lower, our fraction above 25 % is not higher and our max error
is lower. Runs without a source table (noise sweeps, the U-Net) are listed with their own tables;
a pipeline's noise-sweep stages (the `noise` pipeline) also get one table over all its noise levels.
Fails loudly on a missing or malformed run folder.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from hybridqcm.pipelines.catalog import stage_order
from hybridqcm.reports.results import refresh_generated_tables, render

DEFAULT_MANIFESTS = ("outputs/reproduce/manifest.json", "outputs/demo/manifest.json", "outputs/noise/manifest.json")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="qcm-results", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--manifest",
        action="append",
        help="pipeline manifest(s); default: those of outputs/reproduce, outputs/demo and outputs/noise that exist",
    )
    parser.add_argument("--output", default="docs/RESULTS.md", help="page to write (default docs/RESULTS.md)")
    parser.add_argument("--no-plots", action="store_true", help="do not copy sorted-prediction plots next to the page")
    parser.add_argument(
        "--tables-only",
        action="store_true",
        help="only re-include the bench-generated tables (docs/results/*.md) into the existing page",
    )
    args = parser.parse_args(argv)
    if args.tables_only:
        if args.manifest:
            print("error: --tables-only reads no manifest: drop --manifest, or --tables-only", file=sys.stderr)
            return 2
        try:
            names = refresh_generated_tables(Path(args.output))
        except (FileNotFoundError, ValueError) as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
        print(f"refreshed {args.output}: {', '.join(names) or 'no bench table found beside it'}")
        return 0
    manifests = [Path(m) for m in (args.manifest or [m for m in DEFAULT_MANIFESTS if Path(m).exists()])]
    if not manifests:
        print(
            "error: no pipeline manifest found; run `make demo` or `make reproduce` first, or pass --manifest",
            file=sys.stderr,
        )
        return 2
    given = sys.argv[1:] if argv is None else list(argv)
    command = shlex.join(["qcm-results", *given]) if given else "make results"  # to regenerate this page
    try:
        _, beaten, compared = render(
            manifests, Path(args.output), copy_plots=not args.no_plots, command=command, stage_order=stage_order()
        )
    except (FileNotFoundError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {args.output}: {beaten} of {compared} source rows beaten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
