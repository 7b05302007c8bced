"""A seat whose stiffness and damping depend on its static load, with a seat pan on the spring (issue 31).

A foam cushion stiffens under load and its pan moves with the occupant. For a rigid occupant of m kg on a
rigid pan of ``pan_mass`` kg, the mass on the seat spring is M = m + pan_mass and

    K3(M) = K3 (M / reference_load)^exponent,     C3(M) = C3 (M / reference_load)^c3_exponent,

K3, C3 the vehicle's seat constants (the reference seat's at the reference load). The quarter car keeps its
form (SPEC § 1) with these in p1 = C3(M)/M, p2 = K3(M)/M, p3 = C3(M)/m2, p5 = K3(M)/m2: the seat's law scales
the drawn vehicle's p1, p2, p3, p5 per sample (m2 unchanged). ``law="reference"`` with pan 0 is the source's
seat (every parameter as drawn).

``SeatLawPrior`` wraps a prior (physics/prior.py): the occupant's mass is drawn from the prior's mass range
(or, for calibration drives, ``known_loads`` cycled over the samples: ballast on the seat, 0 = the empty
seat), the vehicle from the prior, the law applied, unstable draws redrawn with the same occupant; the draw
carries ``occupant`` [n] (the occupant alone, kg) for the file's truth and known loads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.parameters import is_stable
from hybridqcm.physics.prior import PriorDraw, _RejectionPrior

SEAT_LAWS = ("reference", "power")


@dataclass(frozen=True)
class LoadedSeat:
    """The seat's law over its static load (module docstring). c3_exponent None: the stiffness's exponent."""

    law: str = "reference"
    exponent: float = 0.0
    c3_exponent: float | None = None
    pan_mass: float = 0.0
    reference_load: float = 80.0

    def __post_init__(self) -> None:
        if self.law not in SEAT_LAWS:
            raise ValueError(f"seat.law={self.law!r}: choose one of {list(SEAT_LAWS)}")
        for key in ("exponent", "pan_mass", "reference_load") + (
            ("c3_exponent",) if self.c3_exponent is not None else ()
        ):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"seat.{key}={value!r}: a finite number")
        if self.pan_mass < 0:
            raise ValueError(f"seat.pan_mass={self.pan_mass!r}: a mass >= 0 kg")
        if not self.reference_load > 0:
            raise ValueError(f"seat.reference_load={self.reference_load!r}: a load > 0 kg")
        if self.law == "power" and not self.exponent < 1:
            # p2 = K3(M)/M must fall with M, or no mass is identifiable from it
            raise ValueError(f"seat.exponent={self.exponent!r}: below 1 (K3 / M must fall with the load)")

    @property
    def is_reference(self) -> bool:
        return self.law == "reference" and self.pan_mass == 0

    def factors(self, total_mass: Tensor) -> tuple[Tensor, Tensor]:
        """(K3(M) / K3, C3(M) / C3) at the static masses ``total_mass`` [n] kg."""
        if self.law == "reference":
            return torch.ones_like(total_mass), torch.ones_like(total_mass)
        ratio = total_mass / self.reference_load
        c3_exponent = self.exponent if self.c3_exponent is None else self.c3_exponent
        return ratio**self.exponent, ratio**c3_exponent

    def apply(self, params: Tensor, occupant: Tensor, K3: float, C3: float) -> Tensor:
        """params [n, 10] of vehicles with the seat constants K3, C3 -> those with this seat under occupants
        of ``occupant`` [n] kg: p1, p2 from the law at M = occupant + pan, p3, p5 scaled by the law."""
        total = occupant.to(torch.float64) + self.pan_mass
        k, c = self.factors(total)
        out = params.clone()
        out[:, 0] = C3 * c / total
        out[:, 1] = K3 * k / total
        out[:, 2] = params[:, 2] * c
        out[:, 4] = params[:, 4] * k
        return out

    def as_dict(self) -> dict:
        return {
            "law": self.law,
            "exponent": float(self.exponent),
            "c3_exponent": float(self.exponent if self.c3_exponent is None else self.c3_exponent),
            "pan_mass": float(self.pan_mass),
            "reference_load": float(self.reference_load),
        }


@dataclass
class SeatDraw(PriorDraw):
    """A prior draw with its occupants: ``occupant`` [n] kg (the occupant alone, not the pan)."""

    occupant: Tensor | None = None


class SeatLawPrior(_RejectionPrior):
    """``base``'s vehicles with ``seat`` under occupants from base's mass range or ``known_loads`` (cycled
    over the samples drawn by this prior, in order: each split of a file restarts the cycle via reset())."""

    def __init__(self, base: _RejectionPrior, seat: LoadedSeat, known_loads=None) -> None:
        if getattr(base, "perturb_seat", False):
            raise ValueError(
                "seat.law / seat.pan_mass with prior_options.perturb_seat=true: the seat's law sets K3 and C3; "
                "drop one of them"
            )
        self.base, self.seat = base, seat
        self.h, self.mass_range, self.sigma, self.vehicle = base.h, base.mass_range, base.sigma, base.vehicle
        self.name = getattr(base, "name", "custom")
        self.known_loads = None if known_loads is None else torch.as_tensor(known_loads, dtype=torch.float64)
        if self.known_loads is not None:
            loads = [float(x) for x in self.known_loads]
            if not loads or any(not (math.isfinite(x) and x >= 0) for x in loads):
                raise ValueError(f"seat.known_loads={loads}: loads >= 0 kg")
            if min(loads) + seat.pan_mass <= 0:
                raise ValueError(
                    f"seat.known_loads={loads} with seat.pan_mass={seat.pan_mass}: an empty seat without a pan "
                    "has no mass on its spring; give a pan mass or loads > 0"
                )
        self._cursor = 0

    def reset(self) -> None:
        """Restart the cycle of known loads (a new split)."""
        self._cursor = 0

    def _occupants(self, n: int, generator: torch.Generator) -> Tensor:
        if self.known_loads is None:
            return self._occupant_mass(n, generator)
        k = self.known_loads.shape[0]
        out = self.known_loads[(self._cursor + torch.arange(n)) % k]
        self._cursor = (self._cursor + n) % k
        return out

    def sample(self, n: int, generator: torch.Generator | None = None) -> SeatDraw:
        if n < 0:
            raise ValueError(f"number of samples must be >= 0, got {n}")
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        occupant = self._occupants(n, generator)
        params = torch.zeros(n, 10, dtype=torch.float64)
        todo, n_drawn = torch.arange(n), 0
        for _ in range(self.max_rounds):
            if todo.numel() == 0:
                break
            candidates = self.base._candidates(todo.numel(), generator)  # their own m3 is replaced below
            candidates = self.seat.apply(candidates, occupant[todo], self.vehicle.K3, self.vehicle.C3)
            ok = (candidates > 0).all(-1) & is_stable(candidates, self.h)
            params[todo[ok]] = candidates[ok]
            n_drawn += todo.numel()
            todo = todo[~ok]
        if todo.numel():
            raise RuntimeError(f"{type(self).__name__}: acceptance too low, {todo.numel()}/{n} draws stay unstable")
        return SeatDraw(params=params, n_drawn=n_drawn, occupant=occupant)


__all__ = ["SEAT_LAWS", "LoadedSeat", "SeatDraw", "SeatLawPrior"]
