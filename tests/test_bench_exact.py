"""bench/bench_exact.py --gn --baseline: another tree's code imported next to this one (bench/_baseline.py)
and timed side by side; here with this very tree as the baseline, so both must give the same estimates."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_gn_against_a_baseline_tree_prints_both_and_equal_estimates(tmp_path):
    """A copy of src/ as the baseline: the table names every case at each thread count, and the estimates of
    the two copies (identical code) agree exactly."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "bench_exact.py"), "--gn", "--samples", "24", "--steps", "20",
         "--chunk", "8", "--substeps", "2", "--margin", "2", "--repeats", "1", "--threads", "1", "2",
         "--baseline", str(ROOT)],
        capture_output=True, text=True, check=True, cwd=tmp_path, timeout=600,
        env={"PYTHONPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin"},
    )  # fmt: skip
    rows = [line.split("|")[1:-1] for line in result.stdout.splitlines() if line.startswith("| ") and "---" not in line]
    table = {(r[0].strip(), int(r[1])): r for r in rows[1:]}
    assert set(table) == {(c, t) for c in ("euler", "exact recursion", "exact modal") for t in (1, 2)}
    for row in table.values():
        assert float(row[6]) == 0.0  # max rel. diff of the estimates: same code, same numbers
        assert float(row[2]) > 0 and float(row[3]) > 0


def test_baseline_package_is_a_separate_import(tmp_path):
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        from _baseline import load_baseline

        package = load_baseline(ROOT)
    finally:
        sys.path.remove(str(ROOT / "bench"))
    import hybridqcm.estimation.solver as ours

    theirs = sys.modules[f"{package.__name__}.estimation.solver"]
    assert theirs is not ours and theirs.SolverConfig is not ours.SolverConfig
    assert Path(theirs.__file__).read_text().count("hybridqcm_baseline") >= 1  # imports renamed
