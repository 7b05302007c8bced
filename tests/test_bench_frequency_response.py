"""bench/bench_frequency_response.py: both paths timed on the same tensors, and the table says they agree."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_table_names_every_case_and_the_two_paths_agree(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "bench_frequency_response.py"), "--n", "6", "--steps", "64",
         "--repeat", "1"],
        capture_output=True, text=True, check=True, cwd=tmp_path, timeout=300,
        env={"PYTHONPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    rows = [line.split("|")[1:-1] for line in result.stdout.splitlines() if line.startswith("| ") and "---" not in line]
    table = {(r[0].strip(), r[1].strip()): r for r in rows[1:]}
    models = ("seat, body1", "seat, body2", "quarter car, body1")
    assert set(table) == {(m, d) for m in models for d in ("no", "yes")}
    for (_, derivatives), row in table.items():
        assert float(row[2]) > 0 and float(row[3]) > 0
        assert float(row[5]) < 1e-10
        assert (row[6].strip() == "–") == (derivatives == "no")
        if derivatives == "yes":
            assert float(row[6]) < 1e-10
