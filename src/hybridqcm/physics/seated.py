"""The road-driven quarter car with a seated person (SPEC § 1, § 10; physics/occupant.py).

The rigid occupant m3 becomes the seat PAN: a rigid part m_s (the pan and the part of the body
that moves with it) on the seat spring K3 and damper C3, with up to two body masses m_i hung on it
by k_i, c_i (in parallel). The chassis and the wheel are today's. Newton per body, absolute
displacements q_pan (= q3), q2, q1, q_i, pan deflection z = q3 - q2, body deflections y_i = q_i - q3:

    m_s q3'' = -C3 z' - K3 z + Σ_i (c_i y_i' + k_i y_i)                 (pan)
    m_i q_i'' = -(c_i y_i' + k_i y_i)                                    (body i)
    m2 q2'' = C3 z' + K3 z - C2 (q2' - q1') - K2 (q2 - q1)               (chassis: unchanged)
    m1 q1'' = C2 (q2' - q1') + K2 (q2 - q1) - C1 q1' - K1 (q1 - u)       (wheel: unchanged)

With the static mass M = m_s + Σ m_i and occupant.py's parameters (p1 = C3/M, p2 = K3/M,
r_i = m_i/m_s, k_i = k_i/m_i = ω_i², c_i = c_i/m_i = 2 ζ_i ω_i, R = 1 + Σ r_i, m_s = M/R):

    a3 = R (-p1 z' - p2 z) + Σ_i r_i (c_i y_i' + k_i y_i)
    y_i'' = -(c_i y_i' + k_i y_i) - a3

and the chassis row keeps p3 = C3/m2, p5 = K3/m2 on the pan's deflection. The state is today's
(v3, v2, v1, q3, q2, q1) followed by (y_1', ..., y_n', y_1, ..., y_n); with no body mode the system
matrix is exactly parameters.system_matrix. a3 (the seat pan) over a2 is then occupant.py's
closed-form transmissibility.

Body parameters per sample (`draw_body`): the literature's ranges (Fairley & Griffin 1989;
Wei & Griffin 1998; ISO 5982), drawn independently of the vehicle's p:

    body1: f1 ~ U(4, 6) Hz, ζ1 ~ U(0.3, 0.5), body fraction (m_1 [+ m_2]) / M ~ U(0.6, 0.8)
    body2: additionally f2 ~ U(8, 12) Hz, ζ2 ~ U(0.2, 0.5), m_2 / M ~ U(0.05, 0.2) taken from m_1
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybridqcm.physics.occupant import N_MODES, OCCUPANT_MODELS
from hybridqcm.physics.parameters import system_matrix

# (low, high) of the drawn quantities, per mode: natural frequency on a fixed pan [Hz], damping
# ratio, and the body's share of the static mass (mode 1: the whole body part; mode 2: the share
# of it that forms the second mode).
BODY_RANGES = (
    {"f_hz": (4.0, 6.0), "zeta": (0.3, 0.5), "fraction": (0.6, 0.8)},
    {"f_hz": (8.0, 12.0), "zeta": (0.2, 0.5), "fraction": (0.05, 0.2)},
)


def check_occupant(occupant, where: str = "occupant") -> str:
    """The occupant model's name, or a one-line ValueError naming `where` and the value."""
    if not isinstance(occupant, str) or occupant not in OCCUPANT_MODELS:
        raise ValueError(f"{where} = {occupant!r} is not known; choose one of {list(OCCUPANT_MODELS)}")
    return occupant


def draw_body(occupant: str, n: int, generator: torch.Generator) -> Tensor:
    """Body parameters (r_i, k_i, c_i) per mode, float64 [n, 3 n_modes] (occupant.py's convention);
    [n, 0] for the rigid occupant (nothing drawn). One torch.rand of [n, 3 n_modes] per call:
    columns (f1, ζ1, body fraction[, f2, ζ2, mode-2 fraction])."""
    n_modes = N_MODES[check_occupant(occupant)]
    if n_modes == 0:
        return torch.zeros(n, 0, dtype=torch.float64)
    u = torch.rand(n, 3 * n_modes, generator=generator, dtype=torch.float64)

    def uniform(column: int, bounds: tuple[float, float]) -> Tensor:
        return bounds[0] + (bounds[1] - bounds[0]) * u[:, column]

    body_fraction = uniform(2, BODY_RANGES[0]["fraction"])
    fractions = [body_fraction]
    if n_modes == 2:
        second = uniform(5, BODY_RANGES[1]["fraction"])
        fractions = [body_fraction - second, second]
    rigid_fraction = 1.0 - body_fraction
    columns = []
    for i in range(n_modes):
        omega = 2 * math.pi * uniform(3 * i, BODY_RANGES[i]["f_hz"])
        zeta = uniform(3 * i + 1, BODY_RANGES[i]["zeta"])
        columns += [fractions[i] / rigid_fraction, omega**2, 2 * zeta * omega]
    return torch.stack(columns, -1)


def _check(p: Tensor, body: Tensor) -> int:
    if p.ndim != 2 or p.shape[-1] != 10:
        raise ValueError(f"p must be [batch, 10], got {tuple(p.shape)}")
    if body.ndim != 2 or body.shape[0] != p.shape[0] or body.shape[1] % 3 or body.shape[1] > 6:
        raise ValueError(
            f"body must be [batch, 3 n_modes] with batch {p.shape[0]}, n_modes <= 2, got {tuple(body.shape)}"
        )
    return body.shape[1] // 3


def seated_system_matrix(p: Tensor, body: Tensor) -> Tensor:
    """A [b, 6 + 2n, 6 + 2n] of x = (v3, v2, v1, q3, q2, q1, y', y) for p [b, 10] and body [b, 3n];
    the input enters as in parameters.road_gain (row v1). n = 0 gives system_matrix(p)."""
    n = _check(p, body)
    A6 = system_matrix(p)
    if n == 0:
        return A6
    b, N = p.shape[0], 6 + 2 * n
    modes = body.to(A6.dtype).reshape(b, n, 3)
    r, k, c = modes[..., 0], modes[..., 1], modes[..., 2]
    R = 1.0 + r.sum(-1)
    A = torch.zeros(b, N, N, dtype=A6.dtype, device=A6.device)
    A[:, :6, :6] = A6
    A[:, 0, :6] = R[:, None] * A6[:, 0]  # the seat spring acts on the pan m_s = M / R
    A[:, 0, 6 : 6 + n] = r * c
    A[:, 0, 6 + n :] = r * k
    idx = torch.arange(n)
    A[:, 6 + idx, :] = -A[:, :1, :]  # y_i'' = -(c_i y_i' + k_i y_i) - a3
    A[:, 6 + idx, 6 + idx] -= c
    A[:, 6 + idx, 6 + n + idx] -= k
    A[:, 6 + n + idx, 6 + idx] = 1.0
    return A


def is_stable_seated(p: Tensor, body: Tensor, margin: float = 0.0) -> Tensor:
    """[b] bool: every eigenvalue of seated_system_matrix has real part < -margin."""
    return torch.linalg.eigvals(seated_system_matrix(p, body)).real.amax(-1) < -margin


def physical_matrices(
    m_s: float,
    masses,
    k_body,
    c_body,
    m2: float,
    m1: float,
    C3: float,
    K3: float,
    C2: float,
    K2: float,
    C1: float,
    K1: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Mass, damping and stiffness matrices [N, N] of the bodies (pan, chassis, wheel, body 1..n) in
    absolute displacements, straight from Newton's law (for tests; physical constants)."""
    n = len(masses)
    N = 3 + n
    M = torch.diag(torch.tensor([m_s, m2, m1, *masses], dtype=torch.float64))
    C = torch.zeros(N, N, dtype=torch.float64)
    K = torch.zeros(N, N, dtype=torch.float64)

    def couple(matrix: Tensor, i: int, j: int | None, value: float) -> None:
        matrix[i, i] += value
        if j is not None:
            matrix[j, j] += value
            matrix[i, j] -= value
            matrix[j, i] -= value

    for matrix, (v3, v2, v1) in ((C, (C3, C2, C1)), (K, (K3, K2, K1))):
        couple(matrix, 0, 1, v3)
        couple(matrix, 1, 2, v2)
        couple(matrix, 2, None, v1)  # to the road
    for i in range(n):
        couple(C, 0, 3 + i, c_body[i])
        couple(K, 0, 3 + i, k_body[i])
    return M, C, K


__all__ = [
    "BODY_RANGES",
    "check_occupant",
    "draw_body",
    "seated_system_matrix",
    "is_stable_seated",
    "physical_matrices",
]
