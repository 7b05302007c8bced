"""qcm-simulate's run: check a simulate config (configs/simulate.yaml) and write its dataset (SPEC §5 layout).

    summary = run_simulation(compose("simulate", overrides=["preset=tiny", "output=FILE"]))

Every bad setting is one ValueError / FileExistsError line naming the key and value, raised before
anything is written; the quarter car is written by data/simulate.py, the half and full car by
data/vehicle_simulate_run.py. The summary is printed as tables and saved as RUN/summary.json.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from hybridqcm.atomic import atomic_write_text
from hybridqcm.config import check_task_name, check_writable_dir
from hybridqcm.console import print_table
from hybridqcm.data.simulate import (
    DEFAULT_WARMUP_S,
    check_occupant_physics,
    check_physics,
    check_warmup,
    kmh_to_mps,
    write_dataset,
)
from hybridqcm.physics.parameters import PARAM_NAMES, is_stable, reference_params, system_matrix
from hybridqcm.physics.prior import build_prior
from hybridqcm.physics.road import RoadProfile
from hybridqcm.physics.seated import seated_system_matrix


def _number(cfg: DictConfig, key: str, kind: type):
    value = cfg[key]
    if isinstance(value, bool) or (kind is int and isinstance(value, float) and not value.is_integer()):
        raise ValueError(f"{key} must be {'an integer' if kind is int else 'a number'}, got {value!r}")
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise ValueError(f"{key} must be {'an integer' if kind is int else 'a number'}, got {value!r}") from None


def _reference_person(occupant: str) -> torch.Tensor:
    """Body parameters [1, 3 n] of a light reference person: the heaviest body share (80 % of the
    static mass, so the lightest pan), the fastest modes of the drawn ranges (6 and 12 Hz)."""
    from hybridqcm.physics.occupant import N_MODES

    n = N_MODES[occupant]
    body = [(0.8 - 0.2 * (n == 2)) / 0.2, (2 * math.pi * 6.0) ** 2, 2 * 0.3 * 2 * math.pi * 6.0]
    if n == 2:
        body += [0.2 / 0.2, (2 * math.pi * 12.0) ** 2, 2 * 0.2 * 2 * math.pi * 12.0]
    return torch.tensor([body[: 3 * n]], dtype=torch.float64)


def check_step(h: float, physics: str = "euler", occupant: str = "rigid") -> None:
    """h must keep the reference vehicle's Euler step map stable (spectral radius < 1) for Euler
    physics — beyond that every prior draw is rejected as unstable and nothing could be simulated —
    and, for continuous physics, sample its fastest mode above the Nyquist rate; ValueError otherwise."""
    if physics == "continuous":
        A = system_matrix(reference_params()[None])
        if occupant != "rigid":  # a seated person's light pan on the seat spring is faster still
            A = seated_system_matrix(reference_params()[None], _reference_person(occupant))
        fastest = float(torch.linalg.eigvals(A).abs().max()) / (2 * math.pi)
        who = "reference vehicle" if occupant == "rigid" else f"reference vehicle with a light {occupant} person"
        if not h * fastest < 0.5:
            raise ValueError(
                f"h={h}: sampling at {1 / h:g} Hz cannot resolve the {who}'s fastest mode "
                f"({fastest:.1f} Hz); use h < {0.5 / fastest:.3g} s"
            )
        return
    if not is_stable(reference_params()[None], h=h).all():
        raise ValueError(
            f"h={h}: the Euler step is unstable for the reference vehicle at this step size; "
            f"use a smaller h (the reference protocol uses h=0.01)"
        )


def check_splits(splits) -> None:
    """Every split must simulate at least one profile (an all-zero split would be an empty group)."""
    if not isinstance(splits, dict) or not splits:
        raise ValueError(f"splits must map split names to {{profiles: {{A: n, ...}}}}, got {splits!r}")
    for split, spec in splits.items():
        profiles = (spec or {}).get("profiles") if isinstance(spec, dict) else None
        if not isinstance(profiles, dict):
            raise ValueError(f"splits.{split}.profiles must map road classes to counts, got {profiles!r}")
        counts = [v for v in profiles.values() if isinstance(v, int) and not isinstance(v, bool)]
        if len(counts) == len(profiles) and sum(counts) == 0:
            raise ValueError(
                f"splits.{split}.profiles = {profiles}: every count is 0, so /{split} would be empty; "
                f"give it at least one profile or remove it with ~splits.{split}"
            )


def check_settings(cfg: DictConfig) -> tuple[Path, str, str, tuple[float, float], str]:
    """The settings every vehicle shares: (output, physics, occupant, warm-up [s], vehicle), checked in this
    order, each a one-line ValueError (FileExistsError for an existing output without overwrite)."""
    output = Path(cfg.output)
    check_task_name(cfg.get("task_name", "simulate"))
    if output.exists() and not cfg.overwrite:
        raise FileExistsError(f"output={output} exists; pass overwrite=true to replace it")
    for key in ("n_steps", "samples_per_profile", "profiles_per_chunk"):
        if _number(cfg, key, int) < 1:
            raise ValueError(f"{key} must be >= 1, got {cfg[key]}")
    for key in ("h", "speed_kmh"):
        if not _number(cfg, key, float) > 0:
            raise ValueError(f"{key} must be > 0, got {cfg[key]}")
    physics = check_physics(str(cfg.physics))
    occupant = check_occupant_physics(cfg.get("occupant", "rigid"), physics)
    warmup_s = OmegaConf.to_container(cfg.window, resolve=True).get("warmup_s")
    warmup_s = check_warmup(DEFAULT_WARMUP_S[physics] if warmup_s is None else warmup_s)
    vehicle = str(cfg.get("vehicle", "quarter_car"))
    if vehicle not in ("quarter_car", "half_car", "full_car"):
        raise ValueError(f"vehicle={vehicle!r}: choose one of ['quarter_car', 'half_car', 'full_car']")
    return output, physics, occupant, warmup_s, vehicle


def check_seat(cfg: DictConfig, occupant: str, vehicle: str):
    """(LoadedSeat, known loads or None) from cfg.seat (physics/seat_law.py), or None for the reference seat
    without known loads; a one-line ValueError naming the key and value otherwise."""
    from hybridqcm.physics.seat_law import LoadedSeat

    spec = OmegaConf.to_container(cfg.seat, resolve=True) if cfg.get("seat") is not None else {}
    if not isinstance(spec, dict):
        raise ValueError(f"seat={spec!r}: a mapping (seat.law, seat.exponent, seat.pan_mass, seat.known_loads)")
    known = spec.pop("known_loads", None)
    unknown = sorted(set(spec) - {"law", "exponent", "c3_exponent", "pan_mass", "reference_load"})
    if unknown:
        raise ValueError(f"seat.{unknown[0]}: not a seat key (law, exponent, c3_exponent, pan_mass, known_loads)")
    law = spec.get("law") or "reference"
    if law == "power" and spec.get("exponent") is None:
        raise ValueError("seat.law=power needs seat.exponent (K3 = K3 (M / 80 kg)^exponent), e.g. seat.exponent=0.5")
    for key in ("exponent", "c3_exponent"):
        if law == "reference" and spec.get(key) is not None:
            raise ValueError(f"seat.{key}={spec[key]!r} with seat.law=reference (constant K3, C3): pass seat.law=power")
    seat = LoadedSeat(**{k: v for k, v in spec.items() if v is not None})
    if known is not None:
        known = [known] if isinstance(known, (int, float)) and not isinstance(known, bool) else known
        if (
            not isinstance(known, list)
            or not known
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in known)
        ):
            raise ValueError(f"seat.known_loads={known!r}: a list of loads in kg, e.g. [0, 40, 80, 120]")
        from hybridqcm.physics.prior import build_prior
        from hybridqcm.physics.seat_law import SeatLawPrior

        SeatLawPrior(build_prior("thesis", h=None), seat, known)  # checks the loads (>= 0, a mass on the spring)
    if seat.is_reference and known is None:
        return None
    if vehicle != "quarter_car":
        raise ValueError(
            f"seat.law={seat.law} / seat.pan_mass / seat.known_loads: the quarter car's seat only, not vehicle={vehicle}"
        )
    if occupant != "rigid":
        raise ValueError(
            f"seat.law={seat.law} / seat.pan_mass / seat.known_loads: rigid occupants only, not occupant={occupant}"
        )
    return seat, known


def run_simulation(cfg: DictConfig) -> dict:
    """Check cfg, simulate and write cfg.output; returns the per-split summary (also RUN/summary.json)."""
    output, physics, occupant, warmup_s, vehicle = check_settings(cfg)
    seat = check_seat(cfg, occupant, vehicle)
    if vehicle != "quarter_car":  # the half and full car (issue 30)
        from hybridqcm.data.vehicle_simulate_run import run_vehicle_simulation

        check_splits(OmegaConf.to_container(cfg.splits, resolve=True))
        summary_path = Path(cfg.paths.output_dir) / "summary.json"
        check_writable_dir(summary_path.parent)
        splits = OmegaConf.to_container(cfg.splits, resolve=True)
        summary = run_vehicle_simulation(cfg, output, warmup_s, splits, kmh_to_mps(cfg.speed_kmh))
        atomic_write_text(summary_path, json.dumps({"output": str(output), "vehicle": vehicle, **summary}, indent=2))
        return summary
    check_step(float(cfg.h), physics, occupant)
    check_splits(OmegaConf.to_container(cfg.splits, resolve=True))
    summary_path = Path(cfg.paths.output_dir) / "summary.json"
    check_writable_dir(summary_path.parent)
    options = OmegaConf.to_container(cfg.prior_options, resolve=True)
    # continuous physics: the prior checks the eigenvalues of A only (no Euler step map to keep stable)
    prior = build_prior(
        cfg.prior,
        h=float(cfg.h) if physics == "euler" else None,
        mass_range=tuple(options.pop("mass_range")),
        **options,
    )
    attrs = {}
    if seat is not None:  # a loaded seat (issue 31): the prior's vehicles under it, the law in the file's attrs
        from hybridqcm.physics.seat_law import SeatLawPrior

        prior = SeatLawPrior(prior, seat[0], seat[1])
        attrs["seat"] = json.dumps({**seat[0].as_dict(), "known_loads": seat[1]})
    splits = OmegaConf.to_container(cfg.splits, resolve=True)
    summaries = write_dataset(
        output,
        splits,
        prior,
        RoadProfile(n_waves=int(cfg.road.n_waves)),
        n_steps=int(cfg.n_steps),
        h=float(cfg.h),
        speed_mps=kmh_to_mps(cfg.speed_kmh),
        samples_per_profile=int(cfg.samples_per_profile),
        seed=int(cfg.seed),
        overwrite=bool(cfg.overwrite),
        profiles_per_chunk=int(cfg.profiles_per_chunk),
        method=cfg.integrator,
        progress=bool(cfg.progress),
        compression=cfg.compression,
        physics=physics,
        warmup_s=warmup_s,
        occupant=occupant,
        attrs=attrs,
    )
    summary = {split: s.as_dict() for split, s in summaries.items()}
    _print_summary(output, summary, occupant)
    if seat is not None:
        print(
            f"seat: {attrs['seat']} (/<split>/truth_occupant_mass" + (", known_mass)" if seat[1] is not None else ")")
        )
    atomic_write_text(summary_path, json.dumps({"output": str(output), **summary}, indent=2))
    return summary


def _print_summary(output: Path, summary: dict, occupant: str) -> None:
    rows = []
    for split, s in summary.items():
        rows.append(
            [
                split,
                s["n_samples"],
                " ".join(f"{k}:{v}" for k, v in s["per_class"].items()),
                f"{100 * s['prior_acceptance_rate']:.1f} %",
                " ".join(f"{x:.3g}" for x in s["peak_accel_a3_a2_a1"]),
                f"{s['seconds']:.1f}",
            ]
        )
    print_table(
        f"{output}", ["split", "samples", "per road class", "prior acceptance", "peak |a| (a3 a2 a1) m/s²", "s"], rows
    )
    ranges = [
        [
            name,
            f"{min(s['param_min'][i] for s in summary.values()):.4g}",
            f"{max(s['param_max'][i] for s in summary.values()):.4g}",
        ]
        for i, name in enumerate(PARAM_NAMES)
    ]
    print_table("parameter ranges", ["param", "min", "max"], ranges)
    if occupant != "rigid":
        print(f"occupant: {occupant} (seat pan + body modes; /<split>/occupant_params = (r_i, k_i, c_i) per mode)")
