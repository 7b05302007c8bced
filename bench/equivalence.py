"""Compare the CSV outputs of two bench/equivalence.sh runs: every cell equal, or within 1e-12 relative.

python bench/equivalence.py OUT_A OUT_B      -> one line per file, then BAD <count> (0: unchanged)
"""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path


def compare(a: Path, b: Path, rel: float = 1e-12) -> int:
    bad = 0
    for fa in sorted(a.glob("*/*.csv")):
        fb = b / fa.relative_to(a)
        if not fb.exists():
            print("MISSING", fb)
            bad += 1
            continue
        ra, rb = list(csv.reader(open(fa))), list(csv.reader(open(fb)))
        if ra[:1] != rb[:1]:
            print("HEADER differs", fa.relative_to(a))
            bad += 1
            continue
        worst, diff = 0.0, 0
        for x, y in zip(ra[1:], rb[1:]):
            for u, v in zip(x, y):
                if u == v:
                    continue
                try:
                    fu, fv = float(u), float(v)
                except ValueError:
                    diff += 1
                    continue
                if math.isnan(fu) and math.isnan(fv):
                    continue
                r = abs(fu - fv) / max(abs(fu), abs(fv), 1e-300)
                worst = max(worst, r)
                diff += r > rel
        bad += len(ra) != len(rb) or diff > 0
        status = f"DIFF {diff}" if diff else "ok"
        print(f"{str(fa.relative_to(a)):45s} rows {len(ra) - 1}/{len(rb) - 1} worst rel {worst:.1e} {status}")
    print("BAD", bad)
    return bad


if __name__ == "__main__":
    sys.exit(1 if compare(Path(sys.argv[1]), Path(sys.argv[2])) else 0)
