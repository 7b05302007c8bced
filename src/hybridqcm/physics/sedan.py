"""The reference sedan: a mid-size passenger car for the half-car and full-car models.

Not a measured vehicle: a typical mid-size sedan built from the design rules of the ride
literature, so that every value has a stated origin (table and arithmetic in docs/design/vehicles.md):

* geometry: wheelbase 2.70 m with the centre of mass 43 % of it behind the front axle
  (l_f = 1.16 m, l_b = 1.54 m: 57 % of the sprung weight on the front axle, a front-engined car),
  track 1.55 m (w_l = w_r = 0.775 m) — the class's usual dimensions;
* sprung mass m2 = 1 350 kg; pitch inertia from Gillespie's dynamic index
  DI = k_y² / (l_f l_b) ≈ 1 for passenger cars (Gillespie 1992, Fundamentals of Vehicle Dynamics,
  SAE, ch. 5 "Ride"): I_pitch = m2 l_f l_b = 2 412 kg m²; roll inertia 450 kg m² (roll radius of
  gyration 0.58 m; the order of published sedan values, e.g. 700.7 kg m² for a 1 430 kg sprung mass,
  Chinese J. Mech. Eng. 2021, doi:10.1186/s10033-021-00666-0, table 4);
* ride frequencies 1.15 Hz front, 1.35 Hz rear (about 1-1.5 Hz for passenger cars, the rear
  above the front: Olley's flat-ride rule, Gillespie 1992 ch. 5); tyre radial stiffness
  200 kN/m (150-250 kN/m for passenger tyres: Wong 2008, Theory of Ground Vehicles, 4th ed., ch. 1;
  Mitschke & Wallentowitz 2014, Dynamik der Kraftfahrzeuge, 5th ed.); the suspension stiffness
  k2 = R k1 / (k1 − R) from the ride rate R = (2π f)² m_corner;
* unsprung mass 40 kg front, 35 kg rear per corner (about a tenth of the corner's sprung mass;
  Gillespie 1992), giving wheel hop at 11.9 and 12.7 Hz (10-12 Hz typical);
* suspension damping for a body damping ratio of 0.30 (0.2-0.4 for passenger cars, Gillespie 1992):
  c2 = 2 ζ sqrt(k2 m_corner);
* the seat: the source's K3 = 98 935 N/m and C3 = 615 Ns/m with seat + occupant m3 = 80 kg (SPEC § 1);
* tyre damping c1 = 0 (the source's C1), or 100 Ns/m when tyres are damped (small: a tyre's
  structural damping is a few per cent critical).

The half car is the sedan cut along its centre line: one wheel per axle with a corner's values,
half the sprung mass and half the pitch inertia, so that its ride and wheel-hop frequencies are
the full car's. Seat positions (x forward, y right, from the centre of mass) of the full car's
named seats: front seats 1.31 m behind the front axle, rear seats 0.54 m ahead of the rear axle,
0.37 m either side of the centre line.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybridqcm.physics.parameters import REFERENCE_VEHICLE as _REF
from hybridqcm.physics.vehicle_geometry import (
    FULL_CAR,
    SOURCE_SEAT,
    Seat,
    VehicleLayout,
    columns,
    source_seat_position,
)

L_F, L_B, HALF_TRACK = 1.16, 1.54, 0.775
SPRUNG_MASS = 1350.0
I_PITCH = SPRUNG_MASS * L_F * L_B  # dynamic index 1
I_ROLL = 450.0
TYRE_STIFFNESS = 200_000.0
TYRE_DAMPING = 100.0  # only where tyres are damped
UNSPRUNG = {"f": 40.0, "b": 35.0}
RIDE_HZ = {"f": 1.15, "b": 1.35}
BODY_DAMPING_RATIO = 0.30
# the source's seat and occupant (the quarter car's reference, physics/parameters.py)
SEAT = {"m3": _REF.m3, "k3": _REF.K3, "c3": _REF.C3}
# name -> (x, y) [m]
SEAT_POSITIONS = {
    "driver": (-0.15, -0.37),
    "passenger": (-0.15, 0.37),
    "rear_left": (-1.00, -0.37),
    "rear_right": (-1.00, 0.37),
}


def corner_values(axle: str) -> dict[str, float]:
    """m1, k1, k2, c2 of one corner of the sedan (axle "f" or "b"): the ride-rate arithmetic above."""
    corner = SPRUNG_MASS * (L_B if axle == "f" else L_F) / (2 * (L_F + L_B))  # static sprung mass per corner
    ride_rate = (2 * math.pi * RIDE_HZ[axle]) ** 2 * corner
    k2 = ride_rate * TYRE_STIFFNESS / (TYRE_STIFFNESS - ride_rate)
    return {
        "m1": UNSPRUNG[axle],
        "k1": TYRE_STIFFNESS,
        "k2": k2,
        "c2": 2 * BODY_DAMPING_RATIO * math.sqrt(k2 * corner),
    }


def seat(name: str) -> Seat:
    """A named seat of the sedan (driver, passenger, rear_left, rear_right) or the source's."""
    if name == SOURCE_SEAT:
        return Seat(SOURCE_SEAT)
    if name not in SEAT_POSITIONS:
        raise ValueError(f"seat {name!r} is not one of the sedan's {[SOURCE_SEAT, *SEAT_POSITIONS]}")
    return Seat(name, *SEAT_POSITIONS[name])


def reference_physical(layout: VehicleLayout, dtype: torch.dtype = torch.float64) -> Tensor:
    """The sedan's physical parameters [len(layout.param_names)] for ``layout`` (seats at their
    positions; the source's seat above the back(-left) wheel)."""
    full = layout.kind == FULL_CAR
    share = 1.0 if full else 0.5  # the half car: the sedan cut along its centre line
    values: dict[str, float] = {
        "m2": share * SPRUNG_MASS,
        "I_pitch": share * I_PITCH,
        "I_roll": I_ROLL,
        "l_f": L_F,
        "l_b": L_B,
        "w_l": HALF_TRACK,
        "w_r": HALF_TRACK,
    }
    for wheel in layout.wheels:
        corner = corner_values(wheel[0])
        values.update({f"m1{wheel}": corner["m1"], f"k1{wheel}": corner["k1"], f"k2{wheel}": corner["k2"]})
        values.update({f"c2{wheel}": corner["c2"], f"c1{wheel}": TYRE_DAMPING if layout.tyre_damping else 0.0})
    for s in layout.seats:
        for base, value in SEAT.items():
            values[layout.seat_param(base, s.name)] = value
        values[layout.seat_param("x_s", s.name)] = s.x if s.x is not None else float("nan")
        values[layout.seat_param("y_s", s.name)] = s.y if s.y is not None else float("nan")
    out = torch.tensor([values[n] for n in layout.param_names], dtype=dtype)
    return place_source_seats(layout, out[None])[0]


def place_source_seats(layout: VehicleLayout, physical: Tensor) -> Tensor:
    """physical [M, P] with every source seat's x_s, y_s set to the back(-left) wheel's position."""
    names = layout.param_names
    out = physical.clone()
    x, y = source_seat_position(layout, columns(names, out))
    for s in layout.seats:
        if s.source:
            out[:, names.index(layout.seat_param("x_s", s.name))] = x
            if layout.full:
                out[:, names.index(layout.seat_param("y_s", s.name))] = y
    return out


__all__ = [
    "SEAT",
    "SEAT_POSITIONS",
    "I_PITCH",
    "I_ROLL",
    "SPRUNG_MASS",
    "corner_values",
    "seat",
    "reference_physical",
    "place_source_seats",
]
