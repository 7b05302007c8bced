"""The prior of the half and full cars: vehicles around the reference sedan, persons on its seats.

Per recording, independently:

* every mass, inertia, stiffness and damping of the vehicle (m1<w>, m2, I_pitch, I_roll, k1<w>,
  k2<w>, c2<w>, and c1<w> where tyres are damped): the sedan's value times exp(σ δ), δ ~ N(0, 1)
  (log-normal: relative spread σ, always positive; the `physical` prior of SPEC § 2 for the car);
* the geometry l_f, l_b, w_l, w_r: the sedan's times (1 + σ_geometry δ), δ ~ N(0, 1) clipped to ±3;
* each seat's occupant mass m3 ~ U(mass_range) (SPEC § 2: 30-150 kg), its seat's k3, c3 at the
  source's values (a seat's own stiffness and damping are the seat's specification; seat_sigma > 0
  perturbs them like the vehicle's);
* named seats sit where physics/sedan.py puts them; the source's seat above the back(-left) wheel
  of each drawn vehicle.

Draws whose system matrix has an eigenvalue with Re ≥ 0 are rejected and redrawn (none are, in
practice: a positive-definite M, K with damped suspensions is stable; the check guards the rest).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybridqcm.physics.prior import PriorDraw
from hybridqcm.physics.sedan import place_source_seats, reference_physical
from hybridqcm.physics.vehicle_geometry import VehicleLayout, check_physical
from hybridqcm.physics.vehicle_model import VehicleModel


class VehiclePrior:
    """Draws physical parameters [n, P] (layout.param_names) around the reference sedan."""

    name = "sedan"
    max_rounds = 100

    def __init__(
        self,
        layout: VehicleLayout,
        sigma: float = 0.1,
        geometry_sigma: float = 0.05,
        mass_range: tuple[float, float] = (30.0, 150.0),
        seat_sigma: float = 0.0,
    ) -> None:
        low, high = (float(v) for v in mass_range)
        if not 0 < low < high:
            raise ValueError(f"prior mass_range must satisfy 0 < low < high, got {list(mass_range)}")
        for key, value in (("sigma", sigma), ("geometry_sigma", geometry_sigma), ("seat_sigma", seat_sigma)):
            if not float(value) >= 0:
                raise ValueError(f"prior {key} must be >= 0, got {value}")
        if float(geometry_sigma) > 0.2:
            raise ValueError(f"prior geometry_sigma must be <= 0.2 (±3σ keeps the car a car), got {geometry_sigma}")
        self.layout, self.sigma, self.geometry_sigma = layout, float(sigma), float(geometry_sigma)
        self.mass_range, self.seat_sigma = (low, high), float(seat_sigma)
        self.reference = reference_physical(layout)
        self.model = VehicleModel(layout)
        names = layout.param_names
        self._vehicle = [j for j, n in enumerate(names) if n.startswith(("m1", "m2", "I_", "k1", "k2", "c2"))]
        if layout.tyre_damping:
            self._vehicle += [j for j, n in enumerate(names) if n.startswith("c1")]
        self._geometry = [names.index(n) for n in layout.geometry_names]
        self._mass = [names.index(n) for n in layout.seat_mass_names()]
        self._seat = [j for j, n in enumerate(names) if n.startswith(("k3", "c3"))]

    def _candidates(self, n: int, generator: torch.Generator) -> Tensor:
        out = self.reference.expand(n, -1).clone()
        normal = torch.randn(n, len(self._vehicle), generator=generator, dtype=torch.float64)
        out[:, self._vehicle] *= torch.exp(self.sigma * normal)
        normal = torch.randn(n, len(self._geometry), generator=generator, dtype=torch.float64).clamp(-3, 3)
        out[:, self._geometry] *= 1 + self.geometry_sigma * normal
        low, high = self.mass_range
        out[:, self._mass] = low + (high - low) * torch.rand(
            n, len(self._mass), generator=generator, dtype=torch.float64
        )
        if self.seat_sigma > 0:
            normal = torch.randn(n, len(self._seat), generator=generator, dtype=torch.float64)
            out[:, self._seat] *= torch.exp(self.seat_sigma * normal)
        return place_source_seats(self.layout, out)

    def stable(self, physical: Tensor) -> Tensor:
        """[n] bool: every eigenvalue of the system matrix has Re < 0."""
        A, _, _, _ = self.model.matrices(self.model.model_params(physical))
        return torch.linalg.eigvals(A).real.amax(-1) < 0

    def sample(self, n: int, generator: torch.Generator | None = None) -> PriorDraw:
        """PriorDraw(params = physical [n, P], n_drawn) of stable vehicles, in draw order."""
        if n < 0:
            raise ValueError(f"number of samples must be >= 0, got {n}")
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        kept, n_kept, n_drawn = [], 0, 0
        for _ in range(self.max_rounds):
            if n_kept >= n:
                break
            candidates = self._candidates(n - n_kept, generator)
            ok = self.stable(candidates)
            accepted = candidates[ok]
            kept.append(accepted)
            n_kept += accepted.shape[0]
            n_drawn += candidates.shape[0]
        if n_kept < n:
            raise RuntimeError(
                f"{self.name} prior: only {n_kept} of {n} stable vehicles after {self.max_rounds} rounds"
            )
        physical = torch.cat(kept)[:n] if kept else self.reference[None][:0]
        check_physical(self.layout, physical, "prior draw")
        return PriorDraw(physical, n_drawn)


__all__ = ["VehiclePrior"]
