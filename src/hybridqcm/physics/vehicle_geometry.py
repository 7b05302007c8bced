"""Where things sit on a half-car or full-car body: wheels, seats, the degrees of freedom and the names.

Body axes (the source's convention, issue 30): x forward, y to the right, z up; pitch α positive
nose-up, roll β positive right side up. A chassis point at (x, y) moves vertically with

    z(x, y) = z2 + x α + y β            (small angles; the half car has no roll, y = 0)

so the source's corners are x2f = x2 + L_f α, x2b = x2 − L_b α (half car) and
x2fr = x2 + L_f α + L_r β, x2fl = x2 + L_f α − L_l β, x2br = x2 − L_b α + L_r β,
x2bl = x2 − L_b α − L_l β (full car): wheels at x = l_f (front) or −l_b (back), y = w_r (right)
or −w_l (left), l_f, l_b, w_l, w_r > 0 the distances from the centre of mass.

Degrees of freedom (the columns of the stored accel/vel/disp, attribute ``dofs``), in this order:

    half car:  z3 (one per seat), z2, z1f, z1b, pitch
    full car:  z3 (one per seat), z2, z1fl, z1fr, z1bl, z1br, pitch, roll

(the source orders the full car's wheels fr, fl, br, bl; the names make any order unambiguous).
One seat is ``z3``; several are ``z3_<seat>``. Wheels (``wheels`` of the stored road): f, b or
fl, fr, bl, br.

Physical parameters (the columns of ``physical``, attribute ``names``), in this order:

    m1<w> per wheel, m2, I_pitch[, I_roll], m3 per seat,
    k1<w>, c1<w>, k2<w>, c2<w> per wheel, k3, c3 per seat,
    l_f, l_b[, w_l, w_r], x_s[, y_s] per seat

with the seat's names suffixed ``_<seat>`` when there are several (m3_driver, x_s_driver, ...).
SI units, angles in rad. A seat position of None is the source's: above the back wheel (half
car: x_s = −l_b) or the back-left wheel (full car: x_s = −l_b, y_s = −w_l), per recording.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

HALF_CAR, FULL_CAR = "half_car", "full_car"
VEHICLES = (HALF_CAR, FULL_CAR)
WHEELS = {HALF_CAR: ("f", "b"), FULL_CAR: ("fl", "fr", "bl", "br")}
# Wheel -> (axle, side): axle "f" at x = l_f, "b" at x = -l_b; side "l" at y = -w_l, "r" at y = w_r,
# "" on the half car's centre line.
_WHEEL_PLACE = {"f": ("f", ""), "b": ("b", ""), "fl": ("f", "l"), "fr": ("f", "r"), "bl": ("b", "l"), "br": ("b", "r")}
# Seats of the full car's reference sedan (physics/sedan.py gives their coordinates); "source" is the
# source's seat above the back(-left) wheel.
SOURCE_SEAT = "source"
_NAME_OK = set("abcdefghijklmnopqrstuvwxyz0123456789_")


@dataclass(frozen=True)
class Seat:
    """A seat: its name and its position on the body (None: the source's, above the back(-left) wheel)."""

    name: str
    x: float | None = None
    y: float | None = None

    @property
    def source(self) -> bool:
        return self.x is None


@dataclass(frozen=True)
class VehicleLayout:
    """Which vehicle (half_car | full_car), its seats and whether its tyres are damped (c1 > 0).

    Everything that names columns (dofs, wheels, parameter names) comes from here, so a file and
    a model built from the same layout agree by construction."""

    kind: str
    seats: tuple[Seat, ...] = (Seat(SOURCE_SEAT),)
    tyre_damping: bool = False

    def __post_init__(self) -> None:
        if self.kind not in VEHICLES:
            raise ValueError(f"vehicle={self.kind!r}: choose one of {list(VEHICLES)}")
        if not self.seats:
            raise ValueError(f"{self.kind}: needs at least one seat")
        names = [s.name for s in self.seats]
        bad = [n for n in names if not n or set(n) - _NAME_OK]
        if bad:
            raise ValueError(f"{self.kind}: seat names must be lower-case letters, digits and _, got {bad}")
        if len(set(names)) != len(names):
            raise ValueError(f"{self.kind}: seat names must be unique, got {names}")
        for seat in self.seats:
            if self.kind == FULL_CAR and (seat.x is None) != (seat.y is None):
                raise ValueError(f"{self.kind}: seat {seat.name!r} needs both x and y (or neither: the source's)")
            if self.kind == HALF_CAR and seat.y not in (None, 0, 0.0):
                raise ValueError(f"{self.kind}: seat {seat.name!r} has y = {seat.y!r}, but a half car has no y")
            for value in (seat.x, seat.y):
                if value is not None and not math.isfinite(float(value)):
                    raise ValueError(f"{self.kind}: seat {seat.name!r} position must be finite, got {value!r}")

    # -- names ---------------------------------------------------------------------------------------
    @property
    def full(self) -> bool:
        return self.kind == FULL_CAR

    @property
    def wheels(self) -> tuple[str, ...]:
        return WHEELS[self.kind]

    @property
    def seat_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.seats)

    def suffix(self, seat: str) -> str:
        """ "" for a car with one seat, "_<seat>" with several."""
        return "" if len(self.seats) == 1 else f"_{seat}"

    @property
    def angles(self) -> tuple[str, ...]:
        return ("pitch", "roll") if self.full else ("pitch",)

    @property
    def dofs(self) -> tuple[str, ...]:
        """Names of the degrees of freedom, in state order."""
        return (
            tuple(f"z3{self.suffix(s)}" for s in self.seat_names)
            + ("z2",)
            + tuple(f"z1{w}" for w in self.wheels)
            + self.angles
        )

    @property
    def n_dof(self) -> int:
        return len(self.dofs)

    def seat_dof(self, seat: str) -> int:
        return self.seat_names.index(seat)

    @property
    def chassis_dof(self) -> int:
        return len(self.seats)

    def wheel_dof(self, wheel: str) -> int:
        return len(self.seats) + 1 + self.wheels.index(wheel)

    def angle_dof(self, angle: str) -> int:
        return len(self.seats) + 1 + len(self.wheels) + self.angles.index(angle)

    def seat_param(self, base: str, seat: str) -> str:
        return f"{base}{self.suffix(seat)}"

    @property
    def geometry_names(self) -> tuple[str, ...]:
        return ("l_f", "l_b", "w_l", "w_r") if self.full else ("l_f", "l_b")

    @property
    def param_names(self) -> tuple[str, ...]:
        """Every physical parameter (the ``names`` of the stored ``physical``), c1<w> included."""
        seats, wheels = self.seat_names, self.wheels
        names = [f"m1{w}" for w in wheels] + ["m2", "I_pitch"] + (["I_roll"] if self.full else [])
        names += [self.seat_param("m3", s) for s in seats]
        for base in ("k1", "c1", "k2", "c2"):
            names += [f"{base}{w}" for w in wheels]
        for s in seats:
            names += [self.seat_param("k3", s), self.seat_param("c3", s)]
        names += list(self.geometry_names)
        for s in seats:
            names += [self.seat_param("x_s", s)] + ([self.seat_param("y_s", s)] if self.full else [])
        return tuple(names)

    @property
    def model_param_names(self) -> tuple[str, ...]:
        """The parameters of the linear model: all but the tyre dampings c1<w> when tyres are undamped
        (they are then zero, a known value outside the model)."""
        if self.tyre_damping:
            return self.param_names
        return tuple(n for n in self.param_names if not n.startswith("c1"))

    @property
    def signed_names(self) -> tuple[str, ...]:
        """Parameters that may take either sign: the seats' coordinates."""
        return tuple(n for n in self.param_names if n.startswith(("x_s", "y_s")))

    def seat_mass_names(self) -> tuple[str, ...]:
        return tuple(self.seat_param("m3", s) for s in self.seat_names)

    def describe(self) -> dict:
        """JSON-able description (the file's ``layout`` attribute): kind, seats, tyre damping."""
        return {
            "vehicle": self.kind,
            "seats": [{"name": s.name, "x": s.x, "y": s.y} for s in self.seats],
            "tyre_damping": bool(self.tyre_damping),
        }

    @classmethod
    def from_description(cls, description: Mapping) -> VehicleLayout:
        seats = tuple(Seat(str(s["name"]), s.get("x"), s.get("y")) for s in description["seats"])
        return cls(str(description["vehicle"]), seats, bool(description.get("tyre_damping", False)))


# ------------------------------------------------------------------------------------------------ kinematics
def columns(names: Sequence[str], physical: Tensor) -> dict[str, Tensor]:
    """{name: physical[..., j]} for the columns of physical [..., P] named by ``names``."""
    if physical.shape[-1] != len(names):
        raise ValueError(f"physical has {physical.shape[-1]} columns, the names list {len(names)}")
    return {name: physical[..., j] for j, name in enumerate(names)}


def wheel_position(layout: VehicleLayout, values: Mapping[str, Tensor], wheel: str) -> tuple[Tensor, Tensor]:
    """(x, y) [batch] of a wheel's suspension point from the geometry columns of ``values``."""
    axle, side = _WHEEL_PLACE[wheel]
    x = values["l_f"] if axle == "f" else -values["l_b"]
    if side == "":
        return x, torch.zeros_like(x)
    return x, (values["w_r"] if side == "r" else -values["w_l"])


def seat_position(layout: VehicleLayout, values: Mapping[str, Tensor], seat: str) -> tuple[Tensor, Tensor]:
    """(x, y) [batch] of a seat's base from its x_s, y_s columns (y = 0 on the half car)."""
    x = values[layout.seat_param("x_s", seat)]
    y = values[layout.seat_param("y_s", seat)] if layout.full else torch.zeros_like(x)
    return x, y


def source_seat_position(layout: VehicleLayout, values: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
    """The source's seat: above the back wheel (half car) or the back-left wheel (full car)."""
    return wheel_position(layout, values, "bl" if layout.full else "b")


def point_motion(layout: VehicleLayout, x: Tensor, y: Tensor) -> Tensor:
    """[batch, n_dof] coefficients g with z(x, y) = g · (the body's generalised coordinates):
    z2 + x α (+ y β). Built out of place (torch.func's jacfwd/vmap differentiate through it)."""
    zero, one = torch.zeros_like(x), torch.ones_like(x)
    entries = [zero] * layout.n_dof
    entries[layout.chassis_dof] = one
    entries[layout.angle_dof("pitch")] = x
    if layout.full:
        entries[layout.angle_dof("roll")] = y
    return torch.stack(entries, -1)


def unit(layout: VehicleLayout, dof: int, like: Tensor) -> Tensor:
    """[batch, n_dof] the coordinate vector of one degree of freedom (out of place)."""
    zero = torch.zeros_like(like)
    entries = [zero] * layout.n_dof
    entries[dof] = torch.ones_like(like)
    return torch.stack(entries, -1)


def seat_base(layout: VehicleLayout, physical: Tensor, seat: str, motion: Tensor) -> Tensor:
    """The seat base's vertical motion [M, T] (acceleration, velocity or displacement, whichever
    ``motion`` [M, T, n_dof] holds): z2 + x_s α + y_s β at the seat's position (physical [M, P])."""
    values = columns(layout.param_names, physical)
    x, y = seat_position(layout, values, seat)
    g = point_motion(layout, x.to(motion.dtype), y.to(motion.dtype))  # [M, n_dof]
    return (motion * g[:, None, :]).sum(-1)


# ------------------------------------------------------------------------------------------------ checks
_POSITIVE = ("m1", "m2", "m3", "I_", "k1", "k2", "k3", "c2", "c3", "l_", "w_")
_QUANTITY = {
    "m": "mass",
    "I": "inertia",
    "k": "stiffness",
    "c": "damping",
    "l": "length",
    "w": "half-track",
}


def physical_problems(layout: VehicleLayout, physical: Tensor, where: str = "physical") -> list[str]:
    """One line per kind of problem in physical [M, P] (non-finite values, a mass, inertia,
    stiffness, damping or length that is not > 0 (tyre damping c1 >= 0), a seat outside the
    chassis: x in [-l_b, l_f], y in [-w_l, w_r]); [] when the parameters describe a vehicle."""
    names = layout.param_names
    if physical.ndim != 2 or physical.shape[1] != len(names):
        return [f"{where} must be [M, {len(names)}] ({', '.join(names)}), got {tuple(physical.shape)}"]
    problems = []
    finite = torch.isfinite(physical)
    if not bool(finite.all()):
        i, j = (int(v) for v in (~finite).nonzero()[0])
        problems.append(f"{where}[{i}, {j}] ({names[j]}) = {float(physical[i, j])!r} is not finite")
        return problems
    for j, name in enumerate(names):
        column = physical[:, j]
        if name.startswith("c1"):
            bad = column < 0
            need = ">= 0"
        elif name.startswith(_POSITIVE):
            bad = column <= 0
            need = "> 0"
        else:
            continue
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            kind = _QUANTITY.get(name[0], "value")
            article = "an" if kind[0] in "aeiou" else "a"
            problems.append(
                f"{where}[{i}, {j}] ({name}) = {float(column[i])!r}: {article} {kind} must be {need} "
                f"({int(bad.sum())} such row(s))"
            )
    if problems:
        return problems
    values = columns(names, physical)
    for seat in layout.seat_names:
        x, y = seat_position(layout, values, seat)
        outside = (x > values["l_f"] + 1e-9) | (x < -values["l_b"] - 1e-9)
        if layout.full:
            outside |= (y > values["w_r"] + 1e-9) | (y < -values["w_l"] - 1e-9)
        if bool(outside.any()):
            i = int(outside.nonzero()[0])
            span = f"x in [-l_b, l_f] = [{-float(values['l_b'][i]):.3g}, {float(values['l_f'][i]):.3g}] m"
            if layout.full:
                span += f", y in [-w_l, w_r] = [{-float(values['w_l'][i]):.3g}, {float(values['w_r'][i]):.3g}] m"
            problems.append(
                f"{where}[{i}]: seat {seat!r} at (x, y) = ({float(x[i]):.3g}, {float(y[i]):.3g}) m is outside "
                f"the chassis ({span})"
            )
    return problems


def check_physical(layout: VehicleLayout, physical: Tensor, where: str = "physical") -> None:
    """ValueError with the first of physical_problems, if any."""
    problems = physical_problems(layout, physical, where)
    if problems:
        raise ValueError(problems[0])


__all__ = [
    "HALF_CAR",
    "FULL_CAR",
    "VEHICLES",
    "WHEELS",
    "SOURCE_SEAT",
    "Seat",
    "VehicleLayout",
    "columns",
    "wheel_position",
    "seat_position",
    "source_seat_position",
    "point_motion",
    "unit",
    "seat_base",
    "physical_problems",
    "check_physical",
]
