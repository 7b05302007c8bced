"""qcm-import on an hour-long recording: rows per second and peak memory, the streaming reader beside the
csv-module reader it replaced (issue 32), each in a fresh process, side by side in one run.

    .venv/bin/python bench/foreign_sim.py drives --out data/hour --n 1 --duration 3600 --h 0.001 --sub 2 --noise 0.05
    .venv/bin/python bench/import_stream.py data/hour/drives.csv --window 5120 [--old-rev c6876e9]

The old reader is the importer as it was at --old-rev (read from git: `git show REV:src/hybridqcm/data/importer.py`),
run through its read_recordings + write_recordings; the new one is qcm-import's import_recordings (two passes
over the file, windows written as they are cut). Each run is a child process that reports its own peak
resident memory (resource.getrusage, RUSAGE_SELF: the interpreter and its imports included), so the two do
not share an allocator's high-water mark. The windows both write are compared, bit for bit.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _child(reader: str, csv: str, out: str, window: int, old_source: str | None) -> None:
    """Import ``csv`` into ``out`` with one reader; print {rows, seconds, max_rss_mib} as JSON."""
    kwargs = {"recording_column": "recording", "window": window} if _has_recording(csv) else {"window": window}
    started = time.perf_counter()
    if reader == "new":
        from hybridqcm.data.import_writer import import_recordings

        layout = import_recordings(csv, out, overwrite=True, **kwargs)
        rows = layout.n_rows
    else:
        spec = importlib.util.spec_from_file_location("old_importer", old_source)
        old = importlib.util.module_from_spec(spec)
        sys.modules["old_importer"] = old  # dataclasses look their module up there
        spec.loader.exec_module(old)
        data = old.read_recordings(csv, **kwargs)
        old.write_recordings(out, data, overwrite=True)
        rows = int(sum(data.rows))
    seconds = time.perf_counter() - started
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"reader": reader, "rows": rows, "seconds": seconds, "max_rss_mib": rss}))


def _has_recording(csv: str) -> bool:
    with open(csv) as handle:
        return "recording" in handle.readline().strip().split(",")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("csv")
    ap.add_argument("--window", type=int, default=5120)
    ap.add_argument("--old-rev", default="c6876e9", help="git revision holding the csv-module reader")
    ap.add_argument("--skip-old", action="store_true", help="the new reader only")
    ap.add_argument("--child", nargs=3, metavar=("READER", "OUT", "OLD_SOURCE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        reader, out, old_source = args.child
        _child(reader, args.csv, out, args.window, old_source if old_source != "-" else None)
        return
    size = os.path.getsize(args.csv)
    results = {}
    with tempfile.TemporaryDirectory(dir=REPO / "data" if (REPO / "data").is_dir() else None) as tmp:
        old_source = "-"
        if not args.skip_old:
            text = subprocess.run(
                ["git", "-C", str(REPO), "show", f"{args.old_rev}:src/hybridqcm/data/importer.py"],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
            # DatasetError lives in hybridqcm.errors (data.hdf5 no longer re-exports it)
            text = text.replace(
                "from hybridqcm.data.hdf5 import DatasetError", "from hybridqcm.errors import DatasetError"
            )
            old_source = str(Path(tmp) / "old_importer.py")
            Path(old_source).write_text(text)
        env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
        for reader in ("new",) if args.skip_old else ("new", "old"):
            out = str(Path(tmp) / f"{reader}.h5")
            proc = subprocess.run(
                [sys.executable, __file__, args.csv, "--window", str(args.window), "--child", reader, out, old_source],
                capture_output=True,
                text=True,
                env=env,
            )
            if proc.returncode:
                raise SystemExit(f"{reader} reader failed: {proc.stderr.strip().splitlines()[-1:]}")
            results[reader] = json.loads(proc.stdout.strip().splitlines()[-1])
        if "old" in results:
            import h5py
            import numpy as np

            with h5py.File(Path(tmp) / "new.h5") as a, h5py.File(Path(tmp) / "old.h5") as b:
                same = all(
                    np.array_equal(a[f"test/{k}"][()], b[f"test/{k}"][()], equal_nan=True) for k in ("accel", "t_start")
                )
            results["identical_windows"] = bool(same)
    print(f"{args.csv}: {size / 1e6:.1f} MB, {results['new']['rows']} rows, window {args.window}")
    print("| reader | rows/s | seconds | peak RSS [MiB] | RSS / file size |")
    print("|---|---|---|---|---|")
    for reader in ("new", "old"):
        if reader in results:
            r = results[reader]
            print(
                f"| {reader} | {r['rows'] / r['seconds']:,.0f} | {r['seconds']:.1f} | {r['max_rss_mib']:.0f} | "
                f"{r['max_rss_mib'] * 2**20 / size:.2f} |"
            )
    if "old" in results:
        n, o = results["new"], results["old"]
        print(
            f"new / old: {o['seconds'] / n['seconds']:.1f}x the rows per second, {n['max_rss_mib'] / o['max_rss_mib']:.2f}x "
            f"the peak memory; windows identical: {results['identical_windows']}"
        )


if __name__ == "__main__":
    main()
