"""qcm-simulate vehicle=half_car | full_car's run: the half car and the full car (issue 30).

    qcm-simulate vehicle=half_car output=data/hcm.h5
    qcm-simulate vehicle=full_car seats=[driver,passenger,rear_left] output=data/fcm.h5
    qcm-simulate vehicle=full_car tyre_damping=true road_coherence=identical ...

The reference sedan (physics/sedan.py) drawn around by ``vehicle_prior``, its occupants' masses from
``prior_options.mass_range``, on two-track ISO 8608 roads (physics/two_track_road.py), simulated exactly
in continuous time from rest before a mid-drive window (data/vehicle_simulate.py, which also documents
the file's layout). Every bad setting is one line naming the key and value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from omegaconf import OmegaConf

from hybridqcm.console import print_table
from hybridqcm.data.vehicle_simulate import write_vehicle_dataset
from hybridqcm.physics.road import RoadProfile
from hybridqcm.physics.sedan import reference_physical, seat
from hybridqcm.physics.two_track_road import COHERENCE_MODELS, TwoTrackRoad
from hybridqcm.physics.vehicle_geometry import HALF_CAR, Seat, VehicleLayout, check_physical
from hybridqcm.physics.vehicle_model import VehicleModel
from hybridqcm.physics.vehicle_prior import VehiclePrior


def seats_from_config(kind: str, value) -> tuple[Seat, ...]:
    """The ``seats`` setting: null (the source's seat), a list of the sedan's seat names, or a mapping
    name -> [x, y] (half car: [x] or [x, 0]); ValueError (one line) otherwise."""
    if value is None:
        return (seat("source"),)
    if isinstance(value, str):
        value = [value]
    if isinstance(value, Mapping):
        out = []
        for name, position in value.items():
            position = [position] if isinstance(position, (int, float)) else list(position or [])
            if kind == HALF_CAR and len(position) == 1:
                position = [position[0], None]
            try:
                x, y = (None if v is None else float(v) for v in position)
            except (TypeError, ValueError):
                raise ValueError(f"seats.{name}={position!r}: give [x, y] in metres (half car: [x])") from None
            out.append(Seat(str(name), x, None if kind == HALF_CAR and not y else y))
        return tuple(out)
    try:
        return tuple(seat(str(name)) for name in value)
    except ValueError as error:
        raise ValueError(f"seats={list(value)}: {error}") from None


def check_vehicle_step(layout: VehicleLayout, h: float) -> None:
    """h must sample the reference sedan's fastest mode above the Nyquist rate; ValueError otherwise."""
    model = VehicleModel(layout)
    A, _, _, _ = model.matrices(model.model_params(reference_physical(layout)[None]))
    fastest = float(torch.linalg.eigvals(A).abs().max()) / (2 * math.pi)
    if not h * fastest < 0.5:
        raise ValueError(
            f"h={h}: sampling at {1 / h:g} Hz cannot resolve the {layout.kind}'s fastest mode ({fastest:.1f} Hz); "
            f"use h < {0.5 / fastest:.3g} s"
        )


def run_vehicle_simulation(cfg, output, warmup_s, splits, speed_mps: float) -> dict:
    """Simulate and write the half / full car of ``cfg`` (data/simulate_run.run_simulation checked the common keys)."""
    kind = str(cfg.vehicle)
    if str(cfg.physics) != "continuous":
        raise ValueError(
            f"physics={cfg.physics}: vehicle={kind} is simulated in continuous time only (physics=continuous)"
        )
    if str(cfg.get("occupant", "rigid")) != "rigid":
        raise ValueError(f"occupant={cfg.occupant}: vehicle={kind} seats rigid occupants (occupant=rigid)")
    if warmup_s[1] <= 0:
        raise ValueError(f"window.warmup_s={list(warmup_s)}: vehicle={kind} windows start mid-drive (warm-up > 0)")
    seats_value = cfg.get("seats")
    if seats_value is not None and not isinstance(seats_value, str):
        seats_value = OmegaConf.to_container(seats_value, resolve=True)
    tyre_damping = cfg.get("tyre_damping", False)
    if not isinstance(tyre_damping, bool):
        raise ValueError(f"tyre_damping={tyre_damping!r}: give true or false")
    coherence = str(cfg.get("road_coherence", "isotropic"))
    if coherence not in COHERENCE_MODELS:
        raise ValueError(f"road_coherence={coherence!r}: choose one of {list(COHERENCE_MODELS)}")
    layout = VehicleLayout(kind, seats_from_config(kind, seats_value), tyre_damping)
    check_physical(layout, reference_physical(layout)[None], "the reference sedan with seats=")
    check_vehicle_step(layout, float(cfg.h))
    options = OmegaConf.to_container(cfg.get("vehicle_prior") or {}, resolve=True)
    unknown = sorted(set(options) - {"sigma", "geometry_sigma", "seat_sigma"})
    if unknown:
        raise ValueError(f"vehicle_prior: unknown option(s) {unknown}; known: geometry_sigma, seat_sigma, sigma")
    prior = VehiclePrior(layout, mass_range=tuple(cfg.prior_options.mass_range), **options)
    summaries = write_vehicle_dataset(
        output,
        splits,
        prior,
        TwoTrackRoad(RoadProfile(n_waves=int(cfg.road.n_waves)), coherence),
        n_steps=int(cfg.n_steps),
        h=float(cfg.h),
        speed_mps=speed_mps,
        samples_per_profile=int(cfg.samples_per_profile),
        seed=int(cfg.seed),
        overwrite=bool(cfg.overwrite),
        profiles_per_chunk=int(cfg.profiles_per_chunk),
        progress=bool(cfg.progress),
        compression=cfg.compression,
        warmup_s=warmup_s,
    )
    summary = {split: s.as_dict() for split, s in summaries.items()}
    for entry in summary.values():  # the peak accelerations are per degree of freedom here
        entry["peak_accel"] = dict(zip(layout.dofs, entry.pop("peak_accel_a3_a2_a1")))
        entry["param_min"] = dict(zip(layout.param_names, entry["param_min"]))
        entry["param_max"] = dict(zip(layout.param_names, entry["param_max"]))
    print_table(
        f"{output} ({kind}, seats {', '.join(layout.seat_names)})",
        ["split", "samples", "per road class", "s"],
        [
            [split, s["n_samples"], " ".join(f"{k}:{v}" for k, v in s["per_class"].items()), f"{s['seconds']:.1f}"]
            for split, s in summary.items()
        ],
    )
    print_table(
        "peak |a| per degree of freedom (m/s², rad/s²)",
        ["split", *layout.dofs],
        [[split, *(f"{v:.3g}" for v in s["peak_accel"].values())] for split, s in summary.items()],
    )
    return summary


__all__ = ["seats_from_config", "check_vehicle_step", "run_vehicle_simulation"]
