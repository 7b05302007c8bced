"""qcm-calibrate's run: a seat's mass scale from drives with known loads (issue 31), written as a seat file.

    result = run_calibration(cfg, fit)      # cfg: configs/calibrate.yaml composed; fit(cfg, run_dir) -> rows

The inputs are checked first (law, output, /<split>/known_mass: present, finite, >= 0, not all
equal), each a one-line error naming the file and key, before any fitting. `fit` returns each
recording's estimates.csv row (p1, p2, their standard deviations, status) of qcm-estimate's road-free
rigid seat model (the app runs it into RUN/fit); the seat's law over the load and the pan mass come
from estimation/calibration.py. Writes cfg.output (exclusively, unless overwrite), RUN/seat.json and
RUN/plots/seat_k3.png, and prints the law and the per-load errors.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hydra.core.hydra_config import HydraConfig

from hybridqcm import config
from hybridqcm.atomic import atomic_create_text, atomic_write_text
from hybridqcm.data.hdf5 import read_split
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.calibration import LAWS, CalibrationError, SeatLaw, fit_seat_law, seat_document


def known_loads(path, split: str, n_samples: int | None) -> np.ndarray:
    """/<split>/known_mass [M] kg, checked: present, finite, >= 0, not all equal (one line otherwise)."""
    try:
        loads = read_split(path, split, ("known_mass",))["known_mass"]
    except DatasetError as error:
        if "lacks" in str(error):
            raise DatasetError(
                f"{path}: /{split}/known_mass is missing: a calibration needs each drive's known load [M] in kg "
                "(0 for the empty seat; qcm-import's known_mass column)"
            ) from None
        raise
    loads = np.asarray(loads, float)
    if loads.ndim != 1:
        raise DatasetError(f"{path}: /{split}/known_mass has shape {list(loads.shape)}; expected [M] (kg)")
    if n_samples is not None:
        loads = loads[: int(n_samples)]
    negative = np.flatnonzero(loads < 0)
    if negative.size:
        i = int(negative[0])
        raise DatasetError(f"{path}: /{split}/known_mass[{i}] = {float(loads[i])!r} kg is negative: loads are >= 0 kg")
    if np.unique(loads).size < 2:
        raise DatasetError(
            f"{path}: /{split}/known_mass: all {loads.size} loads are {float(loads[0])!r} kg; a calibration needs drives "
            "at different loads (e.g. 0, 40, 80, 120 kg)"
        )
    return loads


def plot_k3(path: Path, seat: SeatLaw, loads, p2, used) -> None:
    """K3 over the load: each recording's K3 = p2 (load + pan) and the fitted law."""
    from hybridqcm.plots import close, plt, save_figure

    fig, ax = plt.subplots(figsize=(6, 4))
    k3 = p2 * (loads + seat.pan_mass)
    ax.plot(loads[used], k3[used] / 1e3, "o", ms=4, label="recordings: p2 (load + pan)")
    if (~used).any():
        ax.plot(loads[~used], k3[~used] / 1e3, "x", color="grey", label="not used (status)")
    grid = np.linspace(0, max(loads.max(), 1.0) * 1.25, 200)
    ax.plot(grid, seat.k3(grid + seat.pan_mass) / 1e3, "-", label=f"K3 = {seat.K3_ref:.4g} (M/80)^{seat.exponent:.3f}")
    ax.set_xlabel("load on the empty seat [kg]")
    ax.set_ylabel("K3 [kN/m]")
    ax.set_title(f"seat calibration: pan {seat.pan_mass:.2f} kg")
    ax.legend(fontsize=8)
    save_figure(fig, path)
    close(fig)


def run_calibration(cfg, fit: Callable[..., list[dict]], run_dir: Path | None = None) -> dict:
    """Check cfg's inputs, fit every recording (``fit(cfg, run_dir)``: its estimates.csv rows), fit the
    seat law, write the seat file; returns {"seat": SeatLaw, "per_load": [...], "fit": fit_seat_law's result}."""
    if str(cfg.law) not in LAWS:
        raise ConfigError(f"law={cfg.law!r}: choose one of {list(LAWS)}")
    output = Path(str(cfg.output))
    if output.exists() and not cfg.overwrite:
        raise ConfigError(f"output={output}: exists; choose another name or pass overwrite=true")
    if output.suffix.lower() != ".json":
        raise ConfigError(f"output={output}: a seat file is JSON: name it *.json")
    path = Path(str(cfg.data.path))
    split = str(cfg.data.split)
    loads_all = known_loads(path, split, cfg.n_samples)
    if run_dir is None:
        run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path(".")
    config.check_writable_dir(run_dir)
    rows = fit(cfg, run_dir)
    index = np.array([int(r["index"]) for r in rows])
    value = {k: np.array([float(r[k]) for r in rows]) for k in ("p1", "p2", "std_p1", "std_p2")}
    status = np.array([r["status"] for r in rows])
    loads = loads_all[index]
    used = np.isin(status, list(cfg.statuses)) & np.isfinite(value["p2"]) & (value["p2"] > 0)
    if not used.any():
        raise CalibrationError(f"{path}: no recording's fit ended {list(cfg.statuses)} (see {run_dir / 'fit'})")
    result = fit_seat_law(
        loads[used],
        value["p2"][used],
        value["std_p2"][used],
        p1=value["p1"][used],
        p1_std=value["std_p1"][used],
        law=str(cfg.law),
        rel_floor=float(cfg.rel_floor),
        alpha=float(cfg.get("alpha", 0.05)),
    )
    seat = result["law"]
    per_load = []
    for load in np.unique(loads):
        sel = loads[used] == load
        loo = result["loo"].get(float(load))
        per_load.append(
            {
                "load_kg": float(load),
                "recordings": int((loads == load).sum()),
                "used": int(sel.sum()),
                "mean_error_kg": float(result["residual_kg"][sel].mean()) if sel.any() else None,
                "rms_error_kg": float(np.sqrt(np.mean(result["residual_kg"][sel] ** 2))) if sel.any() else None,
                "leave_one_load_out_error_kg": None if loo is None else float(np.mean(loo)),
            }
        )
    std = np.sqrt(np.diag(seat.covariance))
    extra = {
        "standard_deviation": dict(zip(("K3_ref", "exponent", "pan_mass"), std.tolist())),
        "fit": {
            "chi2": result["chi2"],
            "dof": result["dof"],
            "scale": result["scale"],
            "law_asked": str(cfg.law),
            "selection": result["selection"],
            "per_load": per_load,
        },
        "recordings": {"total": int(len(rows)), "used": int(used.sum()), "statuses": list(cfg.statuses)},
        "source": {"data": str(path.resolve()), "split": split},
    }
    text = seat_document(seat, _no_none_numbers(extra))
    try:
        atomic_create_text(output, text, overwrite=bool(cfg.overwrite))
    except FileExistsError:
        raise ConfigError(f"output={output}: appeared while calibrating; not replaced (overwrite=true)") from None
    atomic_write_text(run_dir / "seat.json", text)
    if cfg.plots:
        plot_k3(run_dir / "plots" / "seat_k3.png", seat, loads, value["p2"], used)
    _print_table(seat, per_load, result, output)
    return {"seat": seat, "per_load": per_load, "fit": result}


def _no_none_numbers(tree):
    """JSON null for the absent numbers (a load left without leave-one-out), never NaN."""
    if isinstance(tree, dict):
        return {k: _no_none_numbers(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_no_none_numbers(v) for v in tree]
    if isinstance(tree, float) and not math.isfinite(tree):
        return None
    return tree


def _print_table(seat: SeatLaw, per_load: list, result: dict, output: Path) -> None:
    std = np.sqrt(np.diag(seat.covariance))
    print(f"seat law ({seat.law}): K3(M) = K3_ref (M / {seat.reference_load:g} kg)^e, M = load + pan")
    for row in result["selection"]:
        p = "reference" if row["p_value"] == 1.0 else ("—" if row["p_value"] is None else f"p = {row['p_value']:.3g}")
        mark = "  <- chosen" if row["chosen"] else ""
        print(f"  candidate {row['law']:18s} fits {', '.join(row['free']):28s} chi2 {row['chi2']:9.3g} ({p}){mark}")
    held = "held at 0"
    print(f"  K3_ref   = {seat.K3_ref:12.1f} ± {std[0]:.1f} N/m")
    print(f"  e        = {seat.exponent:12.4f} " + (f"± {std[1]:.4f}" if "exponent" in seat.free else held))
    print(f"  pan mass = {seat.pan_mass:12.3f} " + (f"± {std[2]:.3f} kg" if "pan_mass" in seat.free else held))
    if seat.C3_ref is not None:
        print(f"  C3(M)    = {seat.C3_ref:.1f} (M / {seat.reference_load:g} kg)^{seat.c3_exponent:.4f} Ns/m")
    print(f"  chi2 / dof = {result['chi2']:.3g} / {result['dof']} (the covariance's scale {result['scale']:.3g})")
    print(f"  {'load kg':>8} {'used':>5} {'mean err kg':>12} {'rms err kg':>11} {'leave-out err kg':>17}")
    for row in per_load:

        def cell(x, width):
            return f"{'—':>{width}}" if x is None else f"{x:{width}.3f}"

        print(
            f"  {row['load_kg']:8.1f} {row['used']:5d} {cell(row['mean_error_kg'], 12)} "
            f"{cell(row['rms_error_kg'], 11)} {cell(row['leave_one_load_out_error_kg'], 17)}"
        )
    print(f"seat file: {output}")
