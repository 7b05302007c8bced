"""The ten parameters p1..p10, the reference vehicle and the bijection p <-> (D, S).

State order everywhere is (3, 2, 1): occupant, chassis, wheel. With v = (v3, v2, v1) and
q = (q3, q2, q1) the model is dv/dt = D v + S q + b(t), dq/dt = v, b = (0, 0, p_u u).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

PARAM_NAMES: tuple[str, ...] = tuple(f"p{i}" for i in range(1, 11))
# The measured accelerations of occupant, chassis, wheel: the column order of every accel array [..., 3].
CHANNELS: tuple[str, ...] = ("a3", "a2", "a1")
PARAM_MEANINGS: dict[str, str] = {
    "p1": "C3/m3  seat damping / occupant mass [1/s]",
    "p2": "K3/m3  seat stiffness / occupant mass [1/s^2]",
    "p3": "C3/m2  seat damping / chassis mass [1/s]",
    "p4": "C2/m2  suspension damping / chassis mass [1/s]",
    "p5": "K3/m2  seat stiffness / chassis mass [1/s^2]",
    "p6": "K2/m2  suspension stiffness / chassis mass [1/s^2]",
    "p7": "C2/m1  suspension damping / wheel mass [1/s]",
    "p8": "(C2+C1)/m1  total damping / wheel mass [1/s]",
    "p9": "K2/m1  suspension stiffness / wheel mass [1/s^2]",
    "p10": "(K2+K1)/m1  total stiffness / wheel mass [1/s^2]",
}


@dataclass(frozen=True)
class PhysicalConstants:
    """Physical constants of one vehicle (SI units)."""

    C3: float = 615.0
    C2: float = 4761.0
    C1: float = 0.0
    K3: float = 98935.0
    K2: float = 149171.0
    K1: float = 40000.0
    m3: float = 80.0
    m2: float = 2160.0
    m1: float = 145.0

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            floor_ok = value >= 0 if name == "C1" else value > 0
            if not floor_ok:
                raise ValueError(f"PhysicalConstants.{name} must be {'>= 0' if name == 'C1' else '> 0'}, got {value}")

    def to_params(self, dtype: torch.dtype = torch.float64) -> Tensor:
        """p [10] from the physical constants."""
        c = self
        return torch.tensor(
            [
                c.C3 / c.m3,
                c.K3 / c.m3,
                c.C3 / c.m2,
                c.C2 / c.m2,
                c.K3 / c.m2,
                c.K2 / c.m2,
                c.C2 / c.m1,
                (c.C2 + c.C1) / c.m1,
                c.K2 / c.m1,
                (c.K2 + c.K1) / c.m1,
            ],
            dtype=dtype,
        )


REFERENCE_VEHICLE = PhysicalConstants()


def reference_params(dtype: torch.dtype = torch.float64) -> Tensor:
    """p_ref [10] of the reference vehicle."""
    return REFERENCE_VEHICLE.to_params(dtype)


def _check_params(p: Tensor) -> None:
    if p.shape[-1] != 10:
        raise ValueError(f"parameters must have a last dimension of 10 (p1..p10), got shape {tuple(p.shape)}")


def params_to_matrices(p: Tensor) -> tuple[Tensor, Tensor]:
    """p [..., 10] -> (D [..., 3, 3], S [..., 3, 3])."""
    _check_params(p)
    p1, p2, p3, p4, p5, p6, p7, p8, p9, p10 = p.unbind(-1)
    zero = torch.zeros_like(p1)
    D = torch.stack(
        [
            torch.stack([-p1, p1, zero], -1),
            torch.stack([p3, -(p3 + p4), p4], -1),
            torch.stack([zero, p7, -p8], -1),
        ],
        -2,
    )
    S = torch.stack(
        [
            torch.stack([-p2, p2, zero], -1),
            torch.stack([p5, -(p5 + p6), p6], -1),
            torch.stack([zero, p9, -p10], -1),
        ],
        -2,
    )
    return D, S


def matrices_to_params(D: Tensor, S: Tensor, atol: float = 1e-9) -> Tensor:
    """(D, S) [..., 3, 3] -> p [..., 10]; rejects matrices outside the model's structure."""
    if D.shape[-2:] != (3, 3) or S.shape[-2:] != (3, 3) or D.shape != S.shape:
        raise ValueError(f"D and S must both be [..., 3, 3], got {tuple(D.shape)} and {tuple(S.shape)}")
    p = torch.stack(
        [
            D[..., 0, 1],
            S[..., 0, 1],
            D[..., 1, 0],
            D[..., 1, 2],
            S[..., 1, 0],
            S[..., 1, 2],
            D[..., 2, 1],
            -D[..., 2, 2],
            S[..., 2, 1],
            -S[..., 2, 2],
        ],
        -1,
    )
    D_back, S_back = params_to_matrices(p)
    scale = max(1.0, float(torch.cat([D.abs().flatten(), S.abs().flatten()]).max()))
    if not (
        torch.allclose(D_back, D, atol=atol * scale, rtol=0) and torch.allclose(S_back, S, atol=atol * scale, rtol=0)
    ):
        raise ValueError(
            "D, S do not have the quarter-car structure (zeros at (1,3)/(3,1), rows of D and S consistent)"
        )
    if (p <= 0).any():
        bad = [PARAM_NAMES[i] for i in range(10) if bool((p[..., i] <= 0).any())]
        raise ValueError(f"parameters must be > 0; non-positive: {', '.join(bad)}")
    return p


def road_gain(p: Tensor) -> Tensor:
    """p_u = p10 - p9 = K1/m1 [...], the gain of the road on the wheel's acceleration."""
    _check_params(p)
    return p[..., 9] - p[..., 8]


def system_matrix(p: Tensor) -> Tensor:
    """Continuous-time matrix [..., 6, 6] of d(v, q)/dt = [[D, S], [I, 0]] (v, q)."""
    D, S = params_to_matrices(p)
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand_as(D)
    return torch.cat([torch.cat([D, S], -1), torch.cat([eye, torch.zeros_like(D)], -1)], -2)


def euler_step_matrix(p: Tensor, h: float) -> Tensor:
    """Step map [..., 6, 6] of semi-explicit Euler: v' = v + h(Dv + Sq), q' = q + h v'."""
    D, S = params_to_matrices(p)
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand_as(D)
    top = torch.cat([eye + h * D, h * S], -1)
    bottom = torch.cat([h * (eye + h * D), eye + h * h * S], -1)
    return torch.cat([top, bottom], -2)


def is_stable(p: Tensor, h: float | None = None, margin: float = 0.0) -> Tensor:
    """bool [...]: all continuous eigenvalues have Re < -margin and, given h, the Euler map's
    spectral radius is < 1 (both are needed: a stable ODE can still blow up under the integrator)."""
    eig = torch.linalg.eigvals(system_matrix(p.to(torch.float64)))
    stable = (eig.real < -margin).all(-1)
    if h is not None:
        radius = torch.linalg.eigvals(euler_step_matrix(p.to(torch.float64), h)).abs().amax(-1)
        stable &= radius < 1.0
    return stable


def occupant_mass(p: Tensor, K3: float = REFERENCE_VEHICLE.K3) -> Tensor:
    """m3 = K3 / p2 [...] in kg, for a known seat stiffness K3 [N/m]."""
    _check_params(p)
    return K3 / p[..., 1]
