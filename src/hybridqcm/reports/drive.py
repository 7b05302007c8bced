"""qcm-estimate aggregate=drive: one occupant estimate per drive segment from its windows (issue 32).

The windows of one drive share ``/<split>/profile_id`` (qcm-import window=/stride= cuts a recording into
them) and carry their start time ``/<split>/t_start`` [s]. Each window is estimated as usual (its own
initial state); its shared parameters and their covariance travel beside the block's columns
(estimation/drive_plan.py), and after the merge every drive is combined (estimation/drive.py):

    windows -> usable (status in drive.statuses, finite, positive definite covariance), not overlapping
            -> isolated outliers rejected -> segments (a change of occupant) -> one posterior per segment

Outputs in the run folder:

    drives.csv          one row per drive segment: drive, segment, start_s, end_s, m3, m3_std, m3_low,
                        m3_high (95 %), t_to_5pct_s, t_to_2pct_s, windows, windows_used, windows_rejected,
                        windows_outliers, windows_overlapping, windows_skipped, model, model_margin,
                        windows_models, chi2, dof,
                        chi2_per_dof, p_value, status (ok | inconsistent | no_usable_window), fit
                        (combined: the windows' Gaussians combined; joint: a joint fit of the segment's
                        windows, drive.joint; joint:<statuses>: a joint fit did not converge and the
                        combination's estimate stands)
                        [, m3_true when the file has params]
                        [, occupant_mass, occupant_mass_low, occupant_mass_high with a seat file:
                        the seat law (estimation/calibration.py) at the segment's p2 = K3 / m3, its 95 %
                        interval the image of m3's joined with the calibration's (common to every window,
                        so joined after the combination, never shrunk by it)]
                        windows_skipped: windows kept from the fit for want of information (no_signal: the
                        car standing still; clipped; estimation/window_check.py), never combined;
                        windows_rejected: windows fitted but not usable (a status not in drive.statuses,
                        no positive definite covariance)
    drive_progress.csv  every window of every drive in time order: its segment, whether it was used (or
                        why not), and the segment's running estimate after it (m3, m3_low, m3_high) at the
                        driving time t_s since the segment's start
    plots/drive_*.png   mass and 95 % band against driving time (also in TensorBoard, tb/, tag drive/...)

What is combined: every window under ONE occupant model per drive. An occupant-model selection fits every
candidate to every window (rigid, body1, body2, and the winner again with the channel delay τ); a model's
delay variant is that model with the window's own τ. The drive's model is the one with the most evidence
summed over its windows (each window's Laplace evidence of the model's better variant; the windows are
independent given the model), its prior probability counted once per drive rather than once per window, over
the windows where every model in the race fitted and settled (neither misfit nor diverged, a status in
drive.statuses: a Laplace evidence away from an optimum is no evidence); a model that fits and settles in
fewer than half the drive's windows is not in the race. Every window is then combined under that model, also
one whose own choice was another: θ = the model's parameters (p1, p2, body modes) less those each window
keeps for itself (drive.per_window, default τ: with two loggers it drifts with their clocks, so it is
marginalised like the initial state), from that model's better-settled variant in the window; a window the
drive's model did not fit is rejected (drive_progress.csv says why). m3 = K3/p2 with its interval mapped
from p2's. drives.csv's `model` is the drive's model, `model_margin` its evidence over the runner-up [nats]
and `windows_models` the windows' own choices. (Before, windows whose own choices differed — one rigid+delay
window among rigid ones, a person's body1 and body2 windows — were combined in m3 alone with the σ of each
window's joined interval, and a window whose interval reached infinity made that combination singular.)
Overlapping windows (stride < window) share samples, so their errors are correlated: only a non-overlapping
subset is used (the first window, then each next one starting at or after the end of the last one used); the
others are counted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from hybridqcm.atomic import atomic_write_csv
from hybridqcm.console import print_table
from hybridqcm.estimation.drive import (
    Gaussian,
    isolated_outliers,
    non_overlapping,
    progress,
    segment,
    static_mass,
    time_to_precision,
)
from hybridqcm.estimation.drive_fit import joint_running
from hybridqcm.estimation.drive_model import DriveView
from hybridqcm.estimation.drive_plan import DrivePlan
from hybridqcm.estimation.solver import STATUS_LABELS
from hybridqcm.estimation.tables import ALL_STATUS_LABELS, SEAT_COLUMNS
from hybridqcm.estimation.window_check import WINDOW_STATUS_LABELS

DRIVES_HEADER = [
    "drive",
    "segment",
    "start_s",
    "end_s",
    "m3",
    "m3_std",
    "m3_low",
    "m3_high",
    "t_to_5pct_s",
    "t_to_2pct_s",
    "windows",
    "windows_used",
    "windows_rejected",
    "windows_outliers",
    "windows_overlapping",
    "windows_skipped",
    "model",
    "model_margin",
    "windows_models",
    "chi2",
    "dof",
    "chi2_per_dof",
    "p_value",
    "status",
    "fit",
]
PROGRESS_HEADER = [
    "drive",
    "segment",
    "index",
    "window_start_s",
    "t_s",
    "used",
    "m3",
    "m3_low",
    "m3_high",
    "windows_used",
]
INCONSISTENT_P = 1e-3  # a segment whose windows disagree beyond this p-value is flagged, not hidden


def _fmt(x) -> str:
    if x is None:
        return ""
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, str):
        return x
    return repr(float(x)) if math.isfinite(float(x)) else ("inf" if float(x) > 0 else "")


def _time(x: float) -> str:
    """A time [s] to the microsecond (sums of window lengths carry float noise: 4.999999999999999)."""
    return _fmt(round(float(x), 6))


class _Windows:
    """Every window's status code [M], whether the status is one drive.statuses combines [M] and whether
    the window was kept from the fit (no_signal, clipped) [M]."""

    def __init__(self, status: torch.Tensor, drive: DrivePlan):
        allowed = {k for k, v in STATUS_LABELS.items() if v in drive.statuses}
        self.status = status
        self.ok_status = torch.tensor([int(s) in allowed for s in status], dtype=torch.bool)
        self.kept_out = torch.tensor([int(s) in WINDOW_STATUS_LABELS for s in status], dtype=torch.bool)


def _window_reasons(rows: np.ndarray, usable: np.ndarray, windows: _Windows, view: DriveView, drive: DrivePlan):
    """(used windows in time order, the overlapping ones, {row: why it was used or not}) for one drive's rows;
    usable [len(rows)]: whether the drive's model can combine each (DriveView.usable)."""
    good = rows[usable]
    keep = non_overlapping(drive.t_start[good].tolist(), drive.window_s)
    overlapping = set(good[[not k for k in keep]].tolist())
    good = good[keep]
    used = set(good.tolist())
    reason = {int(r): ("used" if r in used else "overlapping" if r in overlapping else "rejected") for r in rows}
    for r in rows:
        if reason[int(r)] != "rejected":
            continue
        if bool(windows.kept_out[r]):  # not fitted: no information in it
            reason[int(r)] = f"skipped:{ALL_STATUS_LABELS[int(windows.status[r])]}"
        else:  # the drive's model did not fit it (misfit, diverged) or ended with a status not combined
            reason[int(r)] = f"rejected:{STATUS_LABELS.get(view.status.get(int(r), -1), 'no_fit')}"
    return good, overlapping, reason


def _occupant_cells(seat, K3: float, m3: float, low: float, high: float) -> list[str]:
    """drives.csv's occupant_mass, _low, _high from a segment's (m3, m3_low, m3_high) with K3: p2 = K3 / m3 and
    its interval [K3 / m3_high, K3 / m3_low] (0 where m3_high is inf) through the seat law (SeatLaw)."""
    p2, p2_low, p2_high = K3 / m3, (K3 / high if math.isfinite(high) else 0.0), K3 / low
    occupant, occupant_low, occupant_high = seat.occupant_interval(np.array(p2), np.array(p2_low), np.array(p2_high))
    return [_fmt(float(occupant)), _fmt(float(occupant_low)), _fmt(float(occupant_high))]


def _no_estimate(name: str, rows: np.ndarray, reason: dict, overlapping: set, drive: DrivePlan, extra: int):
    """(drives.csv row, drive_progress.csv rows) of a drive none of whose windows is usable."""
    skipped = sum(reason[int(r)].startswith("skipped") for r in rows)
    drive_row = (
        [name, 0, _time(drive.t_start[rows[0]]), _time(drive.t_start[rows[-1]] + drive.window_s)]
        + [""] * 6
        + [rows.size, 0, rows.size - len(overlapping) - skipped, 0, len(overlapping), skipped]
        + ["", "", "", "", "", "", "", "no_usable_window", ""]
        + [""] * extra  # m3_true, the occupant's columns
    )
    progress_rows = [[name, 0, int(r), _time(drive.t_start[r]), "", reason[int(r)], "", "", "", 0] for r in rows]
    return drive_row, progress_rows


def _segment_rows(name, k, seg, in_seg, good, reason, running, k3, view: DriveView, drive: DrivePlan):
    """(drives.csv row, drive_progress.csv rows, final masses) of segment ``k`` of a drive: its windows
    ``seg`` (positions in ``good``) combined, and the running estimate after each of ``in_seg``; running:
    [(Gaussian, index of p2 in it)] after each window of ``seg``."""
    seg_start = float(drive.t_start[good[seg[0]]])
    masses = [static_mass(g, index, k3) for g, index in running]
    running = [g for g, _ in running]
    ends = [float(drive.t_start[good[i]]) + drive.window_s - seg_start for i in seg]
    t5 = time_to_precision(ends, *zip(*[(m[0], m[2], m[3]) for m in masses]), level=0.05)
    t2 = time_to_precision(ends, *zip(*[(m[0], m[2], m[3]) for m in masses]), level=0.02)
    final: Gaussian = running[-1]
    m3, m3_std, low, high = masses[-1]
    state = "inconsistent" if final.dof > 0 and final.p_value < INCONSISTENT_P else "ok"
    counts = [reason[int(r)] for r in in_seg]
    drive_row = [
        name,
        k,
        _time(seg_start),
        _time(float(drive.t_start[good[seg[-1]]]) + drive.window_s),
        _fmt(m3),
        _fmt(m3_std),
        _fmt(low),
        _fmt(high),
        _time(t5),
        _time(t2),
        len(in_seg),
        len(seg),
        sum(c.startswith("rejected") for c in counts),
        sum(c == "outlier" for c in counts),
        sum(c == "overlapping" for c in counts),
        sum(c.startswith("skipped") for c in counts),
        view.family,
        _fmt(view.margin),
        view.own,
        _fmt(final.chi2),
        final.dof,
        _fmt(final.chi2_per_dof),
        _fmt(final.p_value),
        state,
        view.fit,
    ]
    step = {i: j for j, i in enumerate(seg)}
    last = None
    progress_rows = []
    for r in in_seg:
        position = int(np.flatnonzero(good == r)[0]) if r in set(good.tolist()) else None
        if position is not None and position in step:
            last = step[position]
        m = masses[last] if last is not None else None
        progress_rows.append(
            [
                name,
                k,
                int(r),
                _time(drive.t_start[r]),
                _time(float(drive.t_start[r]) + drive.window_s - seg_start),
                reason[int(r)],
                _fmt(m[0]) if m else "",
                _fmt(m[2]) if m else "",
                _fmt(m[3]) if m else "",
                0 if last is None else last + 1,
            ]
        )
    return drive_row, progress_rows, (m3, low, high)


def _combine_drive(
    name, rows, good, reason, view: DriveView, drive: DrivePlan, K3, param_names, true, seat=None, joint=None
):
    """One drive's usable windows ``good`` combined under its model: outliers marked in ``reason``, segments
    found. Returns (drives.csv rows, drive_progress.csv rows, [(m3, m3_low, m3_high, true m3 or None)] per
    segment)."""
    combiner, index = view.gaussians(good, drive, param_names)
    local = list(range(good.size))  # positions in `good`, time order
    outliers = isolated_outliers(combiner, local, drive.outlier_alpha, drive.neighbours)
    for o in outliers:
        reason[int(good[o])] = "outlier"
    kept = [i for i in local if i not in set(outliers)]
    segments = segment(combiner, kept, drive.min_windows, drive.alpha, drive.split)
    running = [[(g, index) for g in progress(combiner, seg)] for seg in segments]
    view.fit = "combined"
    if joint is not None and drive.joint != "none":
        running, view.fit = joint_running(joint, view, good, segments, running, combiner, drive, param_names)
    bounds = [float(drive.t_start[good[s[0]]]) for s in segments[1:]] + [math.inf]
    starts = [float(drive.t_start[rows[0]])] + bounds[:-1]
    drive_rows, progress_rows, masses = [], [], []
    for k, seg in enumerate(segments):
        in_seg = rows[(drive.t_start[rows] >= starts[k]) & (drive.t_start[rows] < bounds[k])]
        row, progress_part, (m3, low, high) = _segment_rows(
            name, k, seg, in_seg, good, reason, running[k], K3, view, drive
        )
        true_m3 = None
        if true is not None:
            true_m3 = float((K3 / true[good[seg], 1]).mean())
            row.append(_fmt(true_m3))
        if seat is not None:
            row += _occupant_cells(seat, K3, m3, low, high)
        drive_rows.append(row)
        progress_rows += progress_part
        masses.append((m3, low, high, true_m3))
    return drive_rows, progress_rows, masses


def aggregate_drives(
    cfg,
    plan: Mapping,
    drive: DrivePlan,
    columns: Mapping,
    run_dir: Path,
    names: Sequence[str],
    param_names: Sequence[str] = ("p1", "p2"),
    log_prior: Mapping[str, float] | None = None,
    seat=None,
    joint=None,
) -> dict:
    """Combine every drive's windows (module docstring); write drives.csv, drive_progress.csv and the plots.
    names: the occupant models a window may report (drive_cand_*'s candidates); param_names: the parameters'
    layout (p1, p2, ...); log_prior: each occupant model's log prior probability (the selection's model_prior);
    seat: the seat file's law (estimation/calibration.SeatLaw) or None: drives.csv's occupant_mass columns.
    Returns the summary entries (counts; with the file's truth the drive-level m3 error and coverage)."""
    K3 = float(cfg.K3)
    windows = _Windows(columns["status"], drive)
    true = columns.get("true")
    drive_rows, progress_rows, pictures, notes = [], [], [], []
    errors, covered = [], []
    order = np.unique(drive.profile_id)  # in id order: drive names follow the file's recordings
    for number, pid in enumerate(order):
        rows = np.flatnonzero(drive.profile_id == pid)
        rows = rows[np.argsort(drive.t_start[rows], kind="stable")]
        name = drive.names[pid] if drive.names else str(int(pid))
        view = DriveView(columns, rows, drive, names, log_prior, windows.kept_out)
        good, overlapping, reason = _window_reasons(rows, view.usable(rows, drive.weights), windows, view, drive)
        if good.size == 0:
            notes.append(
                f"drive {name}: every one of its {rows.size} window(s) was rejected "
                f"({', '.join(sorted({reason[int(r)] for r in rows}))}); no estimate"
            )
            extra = int(true is not None) + (3 if seat is not None else 0)
            drive_row, progress_part = _no_estimate(name, rows, reason, overlapping, drive, extra)
            drive_rows.append(drive_row)
            progress_rows += progress_part
            continue
        rows_of_drive, progress_part, masses = _combine_drive(
            name, rows, good, reason, view, drive, K3, param_names, true, seat, joint
        )
        drive_rows += rows_of_drive
        progress_rows += progress_part
        if len(masses) == 1 and masses[0][3] is not None:  # drive-level error: drives without a change only
            m3, low, high, true_m3 = masses[0]
            errors.append(abs(m3 / true_m3 - 1))
            covered.append(low <= true_m3 <= high)
        if cfg.plots and number < drive.plots:
            pictures.append(_plot_drive(run_dir, name, progress_rows, drive))
    header = (
        DRIVES_HEADER + (["m3_true"] if true is not None else []) + (list(SEAT_COLUMNS) if seat is not None else [])
    )
    atomic_write_csv(run_dir / "drives.csv", header, drive_rows)
    atomic_write_csv(run_dir / "drive_progress.csv", PROGRESS_HEADER, progress_rows)
    if cfg.tensorboard and pictures:
        from hybridqcm.tracking import log_estimation_to_tensorboard

        log_estimation_to_tensorboard(run_dir / "tb", [], pictures, prefix="drive")
    for line in notes:
        print(line)
    summary = {
        "drives": int(order.size),
        "segments": len(drive_rows),
        "drives_split": int(sum(1 for d in {r[0] for r in drive_rows} if sum(r[0] == d for r in drive_rows) > 1)),
        "drives_without_estimate": len(notes),
    }
    if errors:
        summary["m3_mean_rel_err"] = float(np.mean(errors))
        summary["m3_max_rel_err"] = float(np.max(errors))
        summary["m3_coverage_95"] = float(np.mean(covered))
    _print_drives(header, drive_rows, run_dir)
    return summary


def _print_drives(header: Sequence[str], rows: Sequence[Sequence], run_dir: Path, limit: int = 12) -> None:
    wanted = [
        "drive",
        "segment",
        "start_s",
        "end_s",
        "m3",
        "m3_low",
        "m3_high",
        "t_to_2pct_s",
        "windows_used",
        "status",
    ]
    cols = [header.index(k) for k in wanted]

    def short(x):
        try:
            return f"{float(x):.4g}"
        except ValueError:
            return x

    table = [[short(r[c]) if c > 1 else r[c] for c in cols] for r in rows[:limit]]
    more = f" (first {limit} of {len(rows)})" if len(rows) > limit else ""
    print_table(f"drives{more} -> {run_dir / 'drives.csv'}", wanted, table)


def _plot_drive(run_dir: Path, name: str, progress_rows: Sequence[Sequence], drive: DrivePlan) -> Path:
    """Mass and 95 % band of each segment's running estimate against the drive's time (window ends)."""
    from hybridqcm.plots import close, plot_running_estimate

    rows = [r for r in progress_rows if r[0] == name]
    segments = []
    for k in sorted({r[1] for r in rows}):
        seg = [r for r in rows if r[1] == k and r[6] != ""]
        if seg:
            t = np.array([float(r[3]) + drive.window_s for r in seg])
            segments.append((t, *(np.array([float(r[c]) for r in seg]) for c in (6, 7, 8))))
    skipped = np.array([float(r[3]) + drive.window_s for r in rows if r[5] != "used"])
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
    path = run_dir / "plots" / f"drive_{safe}.png"
    close(plot_running_estimate(segments, skipped, path, title=f"drive {name}"))
    return path


__all__ = ["aggregate_drives", "DRIVES_HEADER", "PROGRESS_HEADER"]
