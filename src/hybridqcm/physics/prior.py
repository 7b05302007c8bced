"""Parameter priors. Every prior returns only stable systems and reports its acceptance rate.

`thesis` (SPEC §2): m3 ~ U(mass_range), p1 = C3/m3, p2 = K3/m3 with the reference C3, K3, and
p3..p10 independently ~ N(p_ref, (sigma p_ref)^2). About a third of such draws are unstable
(an eigenvalue with Re >= 0, or an Euler step map with spectral radius >= 1), so they are
rejected and redrawn: an unstable sample is never returned.

`physical`: perturb the physical constants (C2, K2, K1, m1, m2 and optionally C3, K3) by the
same relative sigma and derive p, which keeps the parameters consistent (p7 = p8 when C1 = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.parameters import REFERENCE_VEHICLE, PhysicalConstants, is_stable, reference_params


@dataclass
class PriorDraw:
    """`params` [n, 10] float64 (all stable), how many candidates were drawn for them."""

    params: Tensor
    n_drawn: int

    @property
    def acceptance_rate(self) -> float:
        return self.params.shape[0] / max(self.n_drawn, 1)


class _RejectionPrior:
    """Draws candidates in rounds and keeps the stable, positive ones, in draw order."""

    max_rounds = 1000

    def __init__(
        self,
        h: float | None = 0.01,
        mass_range: tuple[float, float] = (30.0, 150.0),
        sigma: float = 0.1,
        vehicle: PhysicalConstants = REFERENCE_VEHICLE,
    ) -> None:
        low, high = float(mass_range[0]), float(mass_range[1])
        if not 0 < low < high:
            raise ValueError(f"prior mass_range must satisfy 0 < low < high, got {mass_range}")
        if sigma < 0:
            raise ValueError(f"prior sigma must be >= 0, got {sigma}")
        if h is not None and not float(h) > 0:
            raise ValueError(f"prior h must be > 0, got {h}")
        # h = None: continuous-time data, only the eigenvalues of A are checked (no Euler step map)
        self.h = None if h is None else float(h)
        self.mass_range, self.sigma, self.vehicle = (low, high), float(sigma), vehicle

    def _candidates(self, n: int, generator: torch.Generator) -> Tensor:
        raise NotImplementedError

    def sample(self, n: int, generator: torch.Generator | None = None) -> PriorDraw:
        if n < 0:
            raise ValueError(f"number of samples must be >= 0, got {n}")
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        kept: list[Tensor] = []
        n_kept = n_drawn = 0
        for _ in range(self.max_rounds):
            if n_kept >= n:
                break
            batch = max(64, int(1.6 * (n - n_kept)))
            candidates = self._candidates(batch, generator)
            ok = (candidates > 0).all(-1) & is_stable(candidates, self.h)
            accepted = candidates[ok]
            take = min(n - n_kept, accepted.shape[0])
            # Count candidates only up to the last one taken, so the rate is that of the stream.
            if take < accepted.shape[0]:
                last_taken = int(torch.nonzero(ok)[take - 1]) + 1 if take > 0 else 0
                n_drawn += last_taken
            else:
                n_drawn += batch
            kept.append(accepted[:take])
            n_kept += take
        else:
            if n_kept < n:
                raise RuntimeError(f"{type(self).__name__}: acceptance too low, only {n_kept}/{n} stable draws")
        params = torch.cat(kept) if kept else torch.zeros(0, 10, dtype=torch.float64)
        return PriorDraw(params=params, n_drawn=n_drawn)

    def _occupant_mass(self, n: int, generator: torch.Generator) -> Tensor:
        low, high = self.mass_range
        return low + (high - low) * torch.rand(n, generator=generator, dtype=torch.float64)


class ThesisPrior(_RejectionPrior):
    """The source study's prior (SPEC §2), with rejection of unstable draws."""

    name = "thesis"

    def _candidates(self, n: int, generator: torch.Generator) -> Tensor:
        p_ref = self.vehicle.to_params()
        m3 = self._occupant_mass(n, generator)
        noise = torch.randn(n, 8, generator=generator, dtype=torch.float64)
        rest = p_ref[2:] * (1.0 + self.sigma * noise)
        return torch.cat([(self.vehicle.C3 / m3)[:, None], (self.vehicle.K3 / m3)[:, None], rest], -1)


class PhysicalPrior(_RejectionPrior):
    """Perturbs physical constants by a relative sigma and derives p (consistent, practically always stable)."""

    name = "physical"

    def __init__(self, *args, perturb_seat: bool = False, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.perturb_seat = perturb_seat

    def _candidates(self, n: int, generator: torch.Generator) -> Tensor:
        v = self.vehicle
        names = ["C2", "K2", "K1", "m1", "m2"] + (["C3", "K3"] if self.perturb_seat else [])
        factors = 1.0 + self.sigma * torch.randn(n, len(names), generator=generator, dtype=torch.float64)
        const = {
            k: torch.full((n,), getattr(v, k), dtype=torch.float64)
            for k in ("C3", "C2", "C1", "K3", "K2", "K1", "m1", "m2")
        }
        for i, k in enumerate(names):
            const[k] = const[k] * factors[:, i]
        m3 = self._occupant_mass(n, generator)
        c = const
        return torch.stack(
            [
                c["C3"] / m3,
                c["K3"] / m3,
                c["C3"] / c["m2"],
                c["C2"] / c["m2"],
                c["K3"] / c["m2"],
                c["K2"] / c["m2"],
                c["C2"] / c["m1"],
                (c["C2"] + c["C1"]) / c["m1"],
                c["K2"] / c["m1"],
                (c["K2"] + c["K1"]) / c["m1"],
            ],
            -1,
        )


PRIORS = {"thesis": ThesisPrior, "physical": PhysicalPrior}


def build_prior(name: str, **kwargs) -> _RejectionPrior:
    """Prior by name ('thesis' or 'physical'); kwargs: h, mass_range, sigma (and perturb_seat)."""
    if name not in PRIORS:
        raise ValueError(f"unknown prior {name!r}; choose one of {sorted(PRIORS)}")
    return PRIORS[name](**kwargs)


def reference_draw(n: int) -> PriorDraw:
    """n copies of the reference vehicle (a degenerate prior, for tests and demos)."""
    return PriorDraw(params=reference_params().expand(n, 10).clone(), n_drawn=n)


__all__ = ["PriorDraw", "ThesisPrior", "PhysicalPrior", "build_prior", "PRIORS", "reference_draw"]
