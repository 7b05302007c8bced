"""ISO 8608 random road profiles by the sinusoidal approximation (SPEC §3).

    u(s) = sum_i A_i sin(Omega_i s - phi_i),  A_i = sqrt(Phi(Omega_i) dOmega / pi),
    Phi(Omega) = Phi0 (Omega / Omega0)^-2,    s = speed * t.

sin(Omega s - phi) = sin(Omega s) cos(phi) - cos(Omega s) sin(phi), so a batch of profiles on a
common time grid is two matrix products [batch, waves] @ [waves, time] instead of
batch x waves x time sines.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

ROAD_CLASSES = "ABCDEFGH"
# Phi0 for class A in m^3 (angular spatial frequency); x4 per class after that.
PHI0_CLASS_A = 1e-6


def road_class_index(name: str) -> int:
    """'A' -> 0, 'B' -> 1, ... (case-insensitive)."""
    key = str(name).strip().upper()
    if len(key) != 1 or key not in ROAD_CLASSES:
        raise ValueError(f"unknown road class {name!r}; ISO 8608 classes are {', '.join(ROAD_CLASSES)}")
    return ROAD_CLASSES.index(key)


def road_class_phi0(index: int | Tensor) -> Tensor:
    """Phi0 [m^3] for road class index 0 = A, 1 = B, ..."""
    index = torch.as_tensor(index)
    if ((index < 0) | (index >= len(ROAD_CLASSES))).any():
        raise ValueError(f"road class index out of range 0..{len(ROAD_CLASSES) - 1}: {index}")
    return PHI0_CLASS_A * 4.0 ** index.to(torch.float64)


class RoadProfile:
    """Sampler of road profiles u [batch, n_steps] in metres on the grid t_k = k h."""

    def __init__(
        self,
        n_waves: int = 1000,
        omega_min: float = 0.02 * math.pi,
        omega_max: float = 6 * math.pi,
        omega0: float = 1.0,
        waviness: float = 2.0,
    ) -> None:
        if n_waves < 2:
            raise ValueError(f"road n_waves must be >= 2, got {n_waves}")
        if not 0 < omega_min < omega_max:
            raise ValueError(f"road needs 0 < omega_min < omega_max, got {omega_min}, {omega_max}")
        self.n_waves, self.omega0, self.waviness = n_waves, omega0, waviness
        self.omega = torch.linspace(omega_min, omega_max, n_waves, dtype=torch.float64)
        self.d_omega = (omega_max - omega_min) / (n_waves - 1)

    def amplitudes(self, road_class: Tensor) -> Tensor:
        """A_i [batch, waves] for class indices [batch]."""
        phi0 = road_class_phi0(road_class)[:, None]
        psd = phi0 * (self.omega[None, :] / self.omega0) ** (-self.waviness)
        return torch.sqrt(psd * self.d_omega / math.pi)

    def draw(self, road_class: Tensor, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """(amplitudes A_i, phases phi_i), both [batch, waves]: one profile per class index [batch]
        (the same generator draws as `sample`, which evaluates them on a grid)."""
        road_class = torch.as_tensor(road_class, dtype=torch.long).reshape(-1)
        phase = 2 * math.pi * torch.rand(road_class.shape[0], self.n_waves, generator=generator, dtype=torch.float64)
        return self.amplitudes(road_class), phase

    _draw = draw  # the earlier private name

    @staticmethod
    def _distance(n_steps: int, h: float, speed_mps: float) -> Tensor:
        if n_steps < 1 or h <= 0 or speed_mps <= 0:
            raise ValueError(f"road grid needs n_steps >= 1, h > 0, speed > 0; got {n_steps}, {h}, {speed_mps}")
        return speed_mps * h * torch.arange(n_steps, dtype=torch.float64)

    def sample(
        self, road_class: Tensor, n_steps: int, h: float, speed_mps: float, generator: torch.Generator | None = None
    ) -> Tensor:
        """Profiles u [batch, n_steps] (float64) by two matrix products."""
        amplitude, phase = self.draw(road_class, generator)
        return self.evaluate(amplitude, phase, self._distance(n_steps, h, speed_mps))

    def basis(self, distance: Tensor) -> Tensor:
        """[sin(Omega s); -cos(Omega s)] as [2 waves, n]; cached, since every chunk of a dataset shares its grid."""
        key = (distance.shape[0], float(distance[-1]) if distance.numel() else 0.0)
        if getattr(self, "_basis_key", None) != key:
            angle = self.omega[:, None] * distance[None, :]
            self._basis, self._basis_key = torch.cat([torch.sin(angle), -torch.cos(angle)]), key
        return self._basis

    def evaluate(self, amplitude: Tensor, phase: Tensor, distance: Tensor) -> Tensor:
        """u [batch, n] at distances s [n] for amplitudes and phases [batch, waves]: one matrix product."""
        weights = torch.cat([amplitude * torch.cos(phase), amplitude * torch.sin(phase)], -1)  # [batch, 2 waves]
        return weights @ self.basis(distance)

    def sample_direct(
        self, road_class: Tensor, n_steps: int, h: float, speed_mps: float, generator: torch.Generator | None = None
    ) -> Tensor:
        """Same profiles as `sample` (same generator state), by the direct sum of sines (reference, slow)."""
        amplitude, phase = self.draw(road_class, generator)
        s = self._distance(n_steps, h, speed_mps)
        out = torch.empty(amplitude.shape[0], n_steps, dtype=torch.float64)
        for b in range(amplitude.shape[0]):
            out[b] = (amplitude[b, :, None] * torch.sin(self.omega[:, None] * s[None, :] - phase[b, :, None])).sum(0)
        return out

    def variance(self, road_class: int) -> float:
        """Expected variance of u over time: 1/2 sum A_i^2."""
        return 0.5 * float((self.amplitudes(torch.tensor([road_class])) ** 2).sum())
