#!/usr/bin/env bash
# seconds_solve of one qcm-estimate run with two trees' code, alternating, on the same file (issue 33's exp 5 target).
#
#   bash bench/estimate_side_by_side.sh OLD_TREE NEW_TREE OUT REPEATS qcm-estimate-overrides...
#   e.g. bash bench/estimate_side_by_side.sh /tmp/old . /tmp/sbs 2 experiment=exp5_random_init \
#            data.path=/tmp/demo300.h5 n_samples=300
#
# Each tree is a checkout (or `git archive` of src and configs); each repeat runs OLD then NEW with that tree's
# src/ and configs/, so both see the same machine load. Prints seconds_solve per run, the best of each and
# new / old; the estimates of the last two runs are compared by bench/equivalence.py's rule (OUT/old_*, OUT/new_*).
set -u
OLD=$(cd "$1" && pwd); NEW=$(cd "$2" && pwd); OUT=$3; REPEATS=$4; shift 4
BIN=$(dirname "$(command -v python3)")
[ -x "$PWD/.venv/bin/python" ] && BIN=$PWD/.venv/bin
mkdir -p "$OUT"
for r in $(seq 1 "$REPEATS"); do
  for tag in old new; do
    TREE=$OLD; [ $tag = new ] && TREE=$NEW
    dir=$OUT/${tag}_$r
    (cd "$TREE" && PYTHONPATH=$TREE/src $BIN/qcm-estimate "$@" hydra.run.dir="$dir" progress=false >"$dir.log" 2>&1) \
      || { echo "$tag run $r failed: $dir.log"; exit 1; }
    echo "$tag $r seconds_solve $($BIN/python -c "import json; print(json.load(open('$dir/summary.json'))['seconds_solve'])")"
  done
done | tee "$OUT/times.txt"
$BIN/python - "$OUT" <<'EOF'
import sys
from pathlib import Path
rows = [line.split() for line in Path(sys.argv[1], "times.txt").read_text().splitlines() if "seconds_solve" in line]
best = {tag: min(float(r[3]) for r in rows if r[0] == tag) for tag in ("old", "new")}
print(f"best seconds_solve: old {best['old']:.2f}  new {best['new']:.2f}  new / old {best['new'] / best['old']:.2f}")
EOF
