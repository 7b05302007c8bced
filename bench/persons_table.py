"""Issue 28's table: the occupant mass of seated persons, before (rigid occupant, one clock) and after
(`experiment=occupant_roadfree`'s default), each file beside its Cramér–Rao bound, and the time of both side by side.

    .venv/bin/python bench/persons_table.py run   [--n 100] [--files rigid_n0 body1_n5 ...]   # the runs
    .venv/bin/python bench/persons_table.py import --csv RUN/estimates.csv --file body1_n5      # a run made elsewhere
    .venv/bin/python bench/persons_table.py table [--out docs/results/persons.md]              # the table
    .venv/bin/qcm-results --tables-only                                # and into docs/RESULTS.md
    .venv/bin/python bench/persons_table.py speed --n 32 --files rigid_n5 [--trees OLD .]      # the time ratio
    .venv/bin/python bench/persons_table.py floor --n 400 [--budget 8 5]                       # the fits' floor

The recordings come from the second simulator (bench/foreign_sim.py; data/persons/*.h5, made as its
docstring says, 400 each) and the bounds from bench/occupant_crb.py (data/persons/crb_<file>.json). `run`
estimates the first --n recordings of each file twice, into outputs/persons/<file>__rigid (the old default,
`occupant_roadfree occupant.models=[rigid] delay=null`) and outputs/persons/<file> (`occupant_roadfree`'s
default: rigid, body1, body2 by evidence, delay auto), on two processes; a run folder that holds a
summary.json is kept. `import CSV FILE` files an estimates.csv made elsewhere (a larger machine's run of
the same command) as FILE's "after" run. `table` reads the run folders (estimates.csv against the file's truth) and
writes the markdown table with the commands that produced it. `speed` times both methods on the same first --n
recordings of each file, one process each (`trainer=cpu batch_size=N`), alternating `--repeat` times, and prints
seconds_solve (wall) and the process's CPU seconds of each, the ratio default / rigid (issue 28's target ≤ 4×) and
the recordings per second of seconds_solve (issue 33's target ≥ 800 for the default on rigid recordings); with
`--trees` the same for each source tree (its src/ and configs/, e.g. an exported copy of main), side by side in
one run so that the machine's load falls on all alike. `floor` times what the default's three candidates' fits
alone cost when none runs more iterations than the rigid fit does (the stages capped at --budget, no restarts, no
delay variant, one worker; each candidate's own CPU from seconds_phases.fit_cpu), beside the rigid model capped
alike and as `speed` times it: the floor, on this machine, of a selection that fits every candidate with this
solver, whatever its iterations (docs/measurements/persons.md, "The floor of fitting every candidate").
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "persons"
RUNS = ROOT / "outputs" / "persons"
FILES = (
    "rigid_n0",
    "rigid_n5",
    "rigid_delay5_n0",
    "body1_n0",
    "body1_n1",
    "body1_n5",
    "body1_n10",
    "body2_n0",
    "body2_n5",
    "mixed_n5",
)
# before: the rigid occupant on one clock (the old default); after: occupant_roadfree's default (persons, delay auto)
METHODS = {
    "rigid": ["experiment=occupant_roadfree", "occupant.models=[rigid]", "delay=null"],
    "persons": ["experiment=occupant_roadfree"],
}
NOISE = {"n0": 0.0, "n1": 0.01, "n5": 0.05, "n10": 0.10}


def _run_dir(name: str, method: str, runs: Path | None = None) -> Path:
    return (runs or RUNS) / (name if method == "persons" else f"{name}__{method}")


def _command(name: str, method: str, n: int, runs: Path | None = None) -> list[str]:
    return [
        str(ROOT / ".venv" / "bin" / "qcm-estimate"),
        *METHODS[method],
        f"data.path={DATA / (name + '.h5')}",
        f"n_samples={n}",
        f"hydra.run.dir={_run_dir(name, method, runs)}",
        "trainer=ddp",
        "trainer.devices=2",
        f"batch_size={max(1, n // 2)}",
        "progress=false",
        "plots=false",
        "tensorboard=false",
        "overwrite=true",
    ]


def run(args) -> None:
    for name in args.files:
        if not (DATA / f"{name}.h5").is_file():
            sys.exit(f"{DATA / name}.h5: missing; make it with bench/foreign_sim.py (see bench/persons_table.py)")
        for method in args.methods:
            if (_run_dir(name, method, args.runs) / "summary.json").is_file() and not args.force:
                print(f"{name} {method}: kept")
                continue
            print(f"{name} {method}: running", flush=True)
            proc = subprocess.run(_command(name, method, args.n, args.runs), capture_output=True, text=True)
            if proc.returncode != 0:
                sys.exit(f"{name} {method}: qcm-estimate failed: {proc.stderr.strip().splitlines()[-1:]}")


def _truth(name: str) -> tuple[np.ndarray, dict]:
    import h5py

    with h5py.File(DATA / f"{name}.h5", "r") as f:
        return f["test/truth_m3"][()], {k: f["test"][k][()] for k in ("truth_occupant",) if k in f["test"]}


def score(name: str, method: str, runs: Path | None = None) -> dict | None:
    folder = _run_dir(name, method, runs)
    if not (folder / "estimates.csv").is_file():
        return None
    with open(folder / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    truth, _ = _truth(name)
    idx = np.array([int(r["index"]) for r in rows])
    m3 = np.array([float(r["m3"]) for r in rows])
    low = np.array([float(r["m3_low"]) for r in rows])
    high = np.array([float(r["m3_high"]) for r in rows])
    status = np.array([r["status"] for r in rows])
    true = truth[idx]
    err = np.abs(m3 / true - 1)
    inside = (low <= true) & (true <= high)
    # a run made elsewhere (bench/persons_table.py import) has its estimates without this machine's timing
    summary = json.loads((folder / "summary.json").read_text()) if (folder / "summary.json").is_file() else {}
    return {
        "n": len(rows),
        "mean": float(err.mean()),
        "within2": float((err <= 0.02).mean()),
        "within5": float((err <= 0.05).mean()),
        "within10": float((err <= 0.10).mean()),
        "coverage": float(inside.mean()),
        "converged": float((status == "converged").mean()),
        "dishonest": float(((status == "converged") & (err > 0.10) & ~inside).mean()),
        "seconds": float(summary.get("seconds_solve", float("nan"))),
    }


def _bound_cell(stem: str, level: float) -> str | None:
    """data/persons/<stem>.json's mean E|error| at the noise ``level`` (every recording's own model, τ unknown), as
    a table cell; None where the file or the level is not there."""
    path = DATA / f"{stem}.json"
    if not path.is_file():
        return None
    entry = json.loads(path.read_text())["noise"]
    entry = entry.get(str(level)) or entry.get(f"{level:g}")
    cell = None if entry is None else (entry.get("matched_unknown") or next(iter(entry.values())))
    # the periodic bound has no series chain (body2): its body1-fit cell carries no mean
    return None if cell is None or cell["mean_abs_error"] is None else f"{100 * cell['mean_abs_error']:.2f} %"


def _bound(name: str) -> str:
    """The finite window's bound (data/persons/crb_<file>.json, `occupant_crb.py --domain time`) and, in brackets,
    the periodic one the table stood beside before (crb_dft_<file>.json, `--domain dft`) where that file exists."""
    level = NOISE[name.rsplit("_", 1)[-1]]
    finite, periodic = _bound_cell(f"crb_{name}", level), _bound_cell(f"crb_dft_{name}", level)
    if level == 0 and finite is not None:
        return "0 (noise-free)"
    if finite is None:
        return "—"
    return finite + ("" if periodic is None else f" ({periodic})")


def _prior_bound(name: str) -> str:
    """The finite window's bound with the default's literature body prior as information (crb_prior_<file>.json,
    `occupant_crb.py --domain time --body-prior` at the file's noise), where that file exists."""
    level = NOISE[name.rsplit("_", 1)[-1]]
    return (level != 0 and _bound_cell(f"crb_prior_{name}", level)) or "—"


def _honesty_bound(name: str, n: int, coverage: float) -> float | None:
    """The fraction of answers more than 10 % off with the truth outside that an estimator at the Cramér–Rao bound
    gives with exactly calibrated intervals of this ``coverage`` (bench/occupant_crb.py's dishonest_at_bound),
    on the file's first ``n`` recordings, each at its own occupant's bound (τ unknown); None noise-free or without
    the bound's file."""
    import importlib.util

    path = DATA / f"crb_{name}.json"
    level = NOISE[name.rsplit("_", 1)[-1]]
    if level == 0 or not path.is_file():
        return None
    per = json.loads(path.read_text())["per_recording_rel_sd_at_unit_noise"]
    columns = [
        np.array([np.nan if v is None else v for v in per[f"{kind}_unknown"]], dtype=float)
        for kind in ("rigid", "body1", "body2")
        if f"{kind}_unknown" in per
    ]
    if not columns:
        return None
    spec = importlib.util.spec_from_file_location("occupant_crb", Path(__file__).with_name("occupant_crb.py"))
    crb = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(crb)
    return crb.dishonest_at_bound(np.fmin.reduce(columns)[:n] * level, coverage)


def _dishonest(name: str, s: dict) -> str:
    bound = _honesty_bound(name, s["n"], s["coverage"]) if 0 < s["coverage"] < 1 else None
    return _pct(s["dishonest"]) + ("" if bound is None else f" ({_pct(bound)})")


def _seconds(x: float) -> str:
    return "elsewhere" if x != x else f"{x:.0f} s"


def _pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.2f} %"


def table(args) -> None:
    lines = [
        "# Seated persons and two clocks (issue 28): before and after",
        "",
        f"Generated by `bench/persons_table.py table` on {datetime.date.today()} from the runs of "
        "`bench/persons_table.py run` (the first N recordings of each file of the second simulator, "
        "`bench/foreign_sim.py`; `data/persons/`, 100 Hz, 512 samples, a3 on the seat pan and a2 on the chassis, "
        "no road, no network). before: `qcm-estimate experiment=occupant_roadfree` (a rigid occupant on one "
        "clock, `occupant.models=[rigid] delay=null`); after: `qcm-estimate experiment=occupant_roadfree`, its default "
        "(rigid, body1, body2 by Laplace evidence, the channel delay where evidence asks for it). Bound: the Cramér–Rao bound of the static "
        "mass as E|error| (`bench/occupant_crb.py --domain time`, τ unknown, each recording's own occupant model): "
        "the Fisher information of the finite window with its unknown initial state, errors in variables, from the "
        "noise-free twin's channels (bench/window_fisher.py); in brackets the periodic (DFT) bound the table stood "
        "beside until 2026-11-26, too small by the window's leakage and transient. Bound with the body prior: the same "
        "with the default's literature prior on the body mode (r, k, c; `hybridqcm.physics.occupant.BODY_PRIOR`) "
        "added as information at each person's truth (`--body-prior`; a local, van Trees-like bound of an "
        "estimator that knows that prior, for persons drawn from it). "
        "dishonest: `converged`, more than 10 % off and the truth outside the 95 % interval; in brackets what an "
        "estimator at the bound with exactly calibrated intervals of the row's coverage gives (`bench/occupant_crb.py "
        "--coverage`: where the static mass's uncertainty is ~5 %, every miss of an interval is more than 10 % off). "
        "Solve time "
        "'elsewhere': a run of the same command made on another machine (a lent 16-core one, "
        "`trainer.devices=16`) and filed by `import`: its estimates count, its time does not.",
        "",
        "| file | recordings | method | m3 mean error | bound | bound with the body prior | within 2 % | within 5 % "
        "| within 10 % | 95 % interval covers | converged | dishonest | solve time |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in args.files:
        for method in METHODS:
            s = score(name, method)
            if s is None:
                continue
            lines.append(
                f"| {name} | {s['n']} | {'before' if method == 'rigid' else 'after'} | {_pct(s['mean'])} | "
                f"{_bound(name)} | {_prior_bound(name)} | {_pct(s['within2'])} | {_pct(s['within5'])} | {_pct(s['within10'])} | "
                f"{_pct(s['coverage'])} | {_pct(s['converged'])} | {_dishonest(name, s)} | {_seconds(s['seconds'])} |"
            )
    for runs in args.speed_runs:
        speed = []
        for name in args.files:  # the time of both on the same recordings, side by side on this machine
            scores = {m: score(name, m, runs) for m in METHODS}
            if all(scores.values()) and all(v["seconds"] == v["seconds"] for v in scores.values()):
                speed.append((name, scores["rigid"]["n"], scores["rigid"]["seconds"], scores["persons"]["seconds"]))
        if speed:
            lines += [
                "",
                f"Time (GN solve, the same recordings side by side on this machine, the runs in "
                f"`{runs.resolve().relative_to(ROOT)}`; issue target ≤ 4×):",
                "",
            ]
            lines += [
                f"- {name}, {n} recordings: before {a:.1f} s, after {b:.1f} s: {b / a:.0f}×" for name, n, a, b in speed
            ]
    lines += _floor_lines(args.floor_runs, args.files)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def _require(files: list) -> None:
    """Every file's recordings present before the first timed run, else one line naming the first missing."""
    for name in files:
        if not (DATA / f"{name}.h5").is_file():
            sys.exit(f"{DATA / name}.h5: missing; make it with bench/foreign_sim.py (see bench/persons_table.py)")


def _speed_once(tree: Path, name: str, method: str, n: int, folder: Path) -> dict:
    """One timed run of ``method`` on the first ``n`` recordings of ``name`` with the code of ``tree``."""
    return _timed_run(tree, name, METHODS[method], n, folder)


def _timed_run(tree: Path, name: str, overrides: list[str], n: int, folder: Path) -> dict:
    """One timed run of qcm-estimate with ``overrides`` on the first ``n`` recordings of ``name`` with the code of
    ``tree``, one process: its seconds_solve, CPU seconds and seconds_phases (None without a selection)."""
    import os

    command = [
        str(Path(sys.executable).parent / "qcm-estimate"),
        *overrides,
        f"data.path={DATA / (name + '.h5')}",
        f"n_samples={n}",
        f"hydra.run.dir={folder}",
        "trainer=cpu",
        f"batch_size={n}",
        "progress=false",
        "plots=false",
        "tensorboard=false",
        "overwrite=true",
    ]
    env = {**os.environ, "PYTHONPATH": str(tree / "src")}
    proc = subprocess.run(command, capture_output=True, text=True, cwd=tree, env=env)
    if proc.returncode != 0:
        sys.exit(f"{name} {' '.join(overrides)} ({tree}): qcm-estimate failed: {proc.stderr.strip().splitlines()[-1:]}")
    summary = json.loads((folder / "summary.json").read_text())
    # the selection's CPU seconds by phase and by candidate (estimation/occupant.PhaseClock; absent from trees before it)
    seconds = summary.get("seconds_phases") or {}
    return {
        "wall": float(summary["seconds_solve"]),
        "cpu": float(summary["cpu_seconds_blocks"]),
        "phases": seconds.get("cpu"),
        "fits": seconds.get("fit_cpu"),
    }


def _phase_table(times: dict, trees: list, files: list) -> None:
    """Where the default's CPU went (summary.json's seconds_phases, medians over the runs), each phase over the
    rigid model's whole solve CPU; trees without the phase clock are left out."""
    from hybridqcm.estimation.occupant import PHASES

    rows = []
    for t in range(len(trees)):
        for name in files:
            runs = [x["phases"] for x in times[(t, name, "persons")] if x.get("phases")]
            if not runs:
                continue
            rigid = float(np.median([x["cpu"] for x in times[(t, name, "rigid")]]))
            cells = [float(np.median([r.get(p, float("nan")) for r in runs])) for p in (*PHASES, "total")]
            rows.append(f"| tree{t} | {name} | " + " | ".join(f"{c:.2f} ({c / rigid:.1f}×)" for c in cells) + " |")
    if rows:
        print("\nThe default's CPU s by phase (× the rigid model's solve CPU):\n")
        print("| tree | file | " + " | ".join((*PHASES, "total")) + " |")
        print("|---|---|" + "---|" * (len(PHASES) + 1))
        print("\n".join(rows))


def speed(args) -> None:
    """Both methods' solve time on the same recordings, alternating, per tree (module docstring)."""
    trees = [Path(t).resolve() for t in args.trees]
    args.runs = args.runs.resolve()
    _require(args.files)
    times: dict = {}
    for repeat in range(args.repeat):
        for name in args.files:
            for t, tree in enumerate(trees):
                for method in METHODS:
                    folder = args.runs / f"{name}__{method}__tree{t}"
                    took = _speed_once(tree, name, method, args.n, folder)
                    times.setdefault((t, name, method), []).append(took)
                    print(f"# {name} {method} tree{t} run {repeat + 1}: {took['wall']:.2f} s, cpu {took['cpu']:.2f} s")
    print(f"\n{args.n} recordings each, one process, {args.repeat} alternating run(s) (median); trees:")
    for t, tree in enumerate(trees):
        print(f"  tree{t}: {tree}")
    print("\n| tree | file | rigid s (cpu) | default s (cpu) | default / rigid (cpu) | rec/s rigid | rec/s default |")
    print("|---|---|---|---|---|---|---|")
    for t in range(len(trees)):
        for name in args.files:
            med = {
                m: {k: float(np.median([x[k] for x in times[(t, name, m)]])) for k in ("wall", "cpu")} for m in METHODS
            }
            r, p = med["rigid"], med["persons"]
            print(
                f"| tree{t} | {name} | {r['wall']:.2f} ({r['cpu']:.2f}) | {p['wall']:.2f} ({p['cpu']:.2f}) | "
                f"{p['wall'] / r['wall']:.1f}× ({p['cpu'] / r['cpu']:.1f}×) | {args.n / r['wall']:.1f} | "
                f"{args.n / p['wall']:.2f} |"
            )
    _phase_table(times, trees, args.files)
    if len(trees) > 1:  # each tree's time over the first one's, measured in the same run
        print("\n| tree | file | rigid / tree0 | default / tree0 (cpu) |")
        print("|---|---|---|---|")
        for t in range(1, len(trees)):
            for name in args.files:
                ratio = {
                    m: {k: np.median([x[k] for x in times[(t, name, m)]]) / np.median([x[k] for x in times[(0, name, m)]])
                        for k in ("wall", "cpu")}
                    for m in METHODS
                }  # fmt: skip
                print(
                    f"| tree{t} | {name} | {ratio['rigid']['wall']:.2f} | "
                    f"{ratio['persons']['wall']:.2f} ({ratio['persons']['cpu']:.2f}) |"
                )


CANDIDATES = ("rigid", "body1", "body2")
FLOOR_RUNS = ("rigid", "rigid_capped", "candidates")  # _floor_runs' keys, the run folders' suffixes


def _budget(w30: int, seat: int) -> str:
    """The default's two stages with their iterations capped at ``w30`` and ``seat`` (each pass of the last)."""
    return (
        f"stages=[{{name: seat_w30, channels: all, n_steps: 30, max_iterations: {w30}}},"
        f"{{name: seat, channels: all, max_iterations: {seat}}}]"
    )


def _floor_runs(budget: tuple[int, int]) -> dict[str, list[str]]:
    """The floor's three runs: the rigid model as `speed` times it, the rigid model with its stages capped at
    ``budget``, and the default's three candidates, each fitted once (no delay variant, no restarts), one worker,
    at the same caps. Without restarts on both sides a capped fit is never run twice."""
    capped = [_budget(*budget), "restarts.count=0"]
    return {
        "rigid": METHODS["rigid"],
        "rigid_capped": [*METHODS["rigid"], *capped],
        "candidates": [
            "experiment=occupant_roadfree",
            f"occupant.models=[{','.join(CANDIDATES)}]",
            "delay=null",
            "occupant.workers=1",
            *capped,
        ],
    }


def _floor_table(times: dict, files: list, n: int, budget: tuple[int, int]) -> list[str]:
    """The floor's rows (medians over the runs): each candidate's own fit CPU at the budget (its thread's,
    seconds_phases.fit_cpu) over the capped rigid model's solve CPU, and the three together over the rigid model
    as `speed` times it (issue 28's ≤ 4× compares the default with that)."""
    lines = [
        f"| file | rigid model s (cpu) | rigid model at {budget[0]} + {budget[1]} iterations, cpu s | "
        + " | ".join(f"{c} fit, cpu s (×)" for c in CANDIDATES)
        + " | the three fits, cpu s | × the capped rigid model | × the rigid model |",
        "|---|---|---|" + "---|" * len(CANDIDATES) + "---|---|---|",
    ]
    for name in files:
        rigid = {k: float(np.median([x[k] for x in times[(name, "rigid")]])) for k in ("wall", "cpu")}
        capped = float(np.median([x["cpu"] for x in times[(name, "rigid_capped")]]))
        fits = {c: float(np.median([x["fits"][c] for x in times[(name, "candidates")]])) for c in CANDIDATES}
        total = sum(fits.values())
        lines.append(
            f"| {name} | {rigid['wall']:.2f} ({rigid['cpu']:.2f}) | {capped:.2f} | "
            + " | ".join(f"{fits[c]:.2f} ({fits[c] / capped:.1f}×)" for c in CANDIDATES)
            + f" | {total:.2f} | {total / capped:.1f}× | {total / rigid['cpu']:.1f}× |"
        )
    return lines


def _floor_lines(runs: Path, files: list) -> list[str]:
    """The table's floor lines from the last `floor` runs in ``runs`` (<file>__rigid, __rigid_capped and
    __candidates each, with summary.json); none where a file has not all three."""
    rows = []
    for name in files:
        found = {k: runs / f"{name}__{k}" / "summary.json" for k in FLOOR_RUNS}
        if not all(path.is_file() for path in found.values()):
            continue
        summary = {k: json.loads(path.read_text()) for k, path in found.items()}
        fits = (summary["candidates"].get("seconds_phases") or {}).get("fit_cpu") or {}
        if set(fits) != set(CANDIDATES):
            continue
        total = sum(fits[c] for c in CANDIDATES)
        rigid, capped = (float(summary[k]["cpu_seconds_blocks"]) for k in ("rigid", "rigid_capped"))
        rows.append(
            f"- {name}, {summary['rigid']['n_samples']} recordings: the three candidates' fits "
            + " + ".join(f"{fits[c]:.1f}" for c in CANDIDATES)
            + f" = {total:.1f} CPU s, {total / rigid:.1f}× the rigid model's {rigid:.2f} ({total / capped:.1f}× the rigid "
            "model at the same budget)"
        )
    if not rows:
        return []
    return [
        "",
        "The floor of fitting every candidate (`bench/persons_table.py floor`: the default's stages capped at the rigid "
        f"fit's own iterations, no restarts, no delay variant, one worker; each candidate's thread CPU; the runs in "
        f"`{runs.resolve().relative_to(ROOT) if runs.resolve().is_relative_to(ROOT) else runs}`): even if every body "
        "candidate converged in the rigid fit's iterations,",
        "",
        *rows,
    ]


def floor(args) -> None:
    """What the three candidates' fits alone cost when each runs no more iterations than the rigid fit does (the
    default's stages capped at --budget), beside the rigid model, side by side in one run: the floor of any
    selection that fits every candidate with this solver, below which no tuning of iterations can go."""
    budget = tuple(args.budget)
    runs = _floor_runs(budget)
    args.runs = args.runs.resolve()
    _require(args.files)
    times: dict = {}
    for repeat in range(args.repeat):
        for name in args.files:
            for kind, overrides in runs.items():
                took = _timed_run(ROOT, name, overrides, args.n, args.runs / f"{name}__{kind}")
                if kind == "candidates" and set(took["fits"] or ()) != set(CANDIDATES):
                    sys.exit(
                        f"{name}: the run's summary.json has no fit_cpu of {', '.join(CANDIDATES)} (an older tree?)"
                    )
                times.setdefault((name, kind), []).append(took)
                print(f"# {name} {kind} run {repeat + 1}: {took['wall']:.2f} s, cpu {took['cpu']:.2f} s", flush=True)
    print(
        f"\n{args.n} recordings each, one process, {args.repeat} alternating run(s) (median); the stages capped at "
        f"seat_w30 {budget[0]} and seat {budget[1]} iterations (each pass), no restarts:\n"
    )
    print("\n".join(_floor_table(times, args.files, args.n, budget)))


def import_run(args) -> None:
    """An estimates.csv of the "after" command made on another machine, filed as FILE's run (no timing)."""
    import shutil

    source = Path(args.csv)
    if not source.is_file():
        sys.exit(f"{source}: no such file")
    folder = _run_dir(args.file, "persons")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "summary.json").unlink(missing_ok=True)
    shutil.copyfile(source, folder / "estimates.csv")
    (folder / "source.txt").write_text(f"{source}\n")
    print(f"{args.file}: {source} -> {folder / 'estimates.csv'}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="estimate every file before and after")
    r.add_argument("--n", type=int, default=100)
    r.add_argument("--files", nargs="+", default=list(FILES))
    r.add_argument("--force", action="store_true", help="run again where a summary.json exists")
    r.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    r.add_argument("--runs", type=Path, default=RUNS, help="run folders' parent (default outputs/persons)")
    t = sub.add_parser("table", help="write the markdown table")
    t.add_argument("--files", nargs="+", default=list(FILES))
    t.add_argument("--out", default=str(ROOT / "docs" / "results" / "persons.md"))
    t.add_argument(
        "--speed-runs",
        type=Path,
        nargs="+",
        default=[ROOT / "outputs" / "persons_speed", ROOT / "outputs" / "persons_speed400"],
        help="folders of timing runs (<file> and <file>__rigid each), one time list per folder that has them "
        "(persons_speed400: links to `speed --n 400`'s runs)",
    )
    t.add_argument(
        "--floor-runs",
        type=Path,
        default=ROOT / "outputs" / "persons_floor_bench",
        help="the folder of `floor`'s runs (its --runs): the floor's lines where they are all there",
    )
    i = sub.add_parser("import", help="file an estimates.csv made elsewhere as a file's after-run")
    i.add_argument("--csv", required=True)
    i.add_argument("--file", required=True, choices=FILES)
    v = sub.add_parser("speed", help="time the default against the rigid one-clock fit, side by side")
    v.add_argument("--n", type=int, default=32)
    v.add_argument("--files", nargs="+", default=["rigid_n5", "body1_n5"])
    v.add_argument("--repeat", type=int, default=1, help="alternating runs of each (the median is printed)")
    v.add_argument("--trees", nargs="+", default=[str(ROOT)], help="source trees (their src/ and configs/)")
    v.add_argument("--runs", type=Path, default=ROOT / "outputs" / "persons_speed_bench")
    f = sub.add_parser("floor", help="the candidates' fits at the rigid fit's iteration budget, beside the rigid model")
    f.add_argument("--n", type=int, default=400)
    f.add_argument("--files", nargs="+", default=["rigid_n5", "body1_n5"])
    f.add_argument(
        "--budget",
        type=int,
        nargs=2,
        default=[8, 5],
        metavar=("W30", "SEAT"),
        help="iterations of seat_w30 and of each pass of seat (default: the rigid candidate's own, 8.3 and 5.6 / 4.0 "
        "on rigid_n5's first 96 in the default)",
    )
    f.add_argument("--repeat", type=int, default=2, help="alternating runs of each (the median is printed)")
    f.add_argument("--runs", type=Path, default=ROOT / "outputs" / "persons_floor_bench")
    args = ap.parse_args(argv)
    if args.command == "floor" and min(args.budget) < 1:
        ap.error(f"floor --budget {args.budget[0]} {args.budget[1]}: iterations must be >= 1")
    {"run": run, "table": table, "import": import_run, "speed": speed, "floor": floor}[args.command](args)


if __name__ == "__main__":
    main()
