"""The occupant equation's residual as a training signal: losses and per-sample least squares.

The seat equation a3 = -p1 (v3 - v2) - p2 (q3 - q2) is linear in (p1, p2): with the design
columns A_1 = -(v3 - v2), A_2 = -(q3 - q2) the residual of an estimate p̂ is r = a3 - A p̂.
Every function takes aux [B, 5, N] with channels (a3, v3, v2, q3, q2), the stored clean
triple that satisfies the equation of motion at every step (SPEC § 4), so r = 0 for the true p.
"""

from __future__ import annotations

import torch
from torch import Tensor


def rms(x: Tensor, dim: int = -1) -> Tensor:
    """Root mean square along ``dim``: [B, C, N] -> [B, C] for the default last axis."""
    return x.pow(2).mean(dim).sqrt()


def physics_residual(p12: Tensor, aux: Tensor) -> Tensor:
    """Occupant equation residual r = a3 - ã3 [B, N], ã3 = -p1 (v3 - v2) - p2 (q3 - q2).

    p12: [B, 2] (p1, p2); aux: [B, 5, N] channels (a3, v3, v2, q3, q2). Zero for the true p
    on clean data (the stored triple satisfies the equation of motion at every step).
    """
    a3, v3, v2, q3, q2 = aux.unbind(1)
    return a3 + p12[:, :1] * (v3 - v2) + p12[:, 1:2] * (q3 - q2)


def physics_residual_loss(p12: Tensor, aux: Tensor, eps: float = 1e-30) -> Tensor:
    """Per-sample relative residual energy sum_k r_k^2 / sum_k a3_k^2 [B].

    Dividing by the sample's own a3 energy makes samples of every road class (amplitudes
    differ by 4x per class) count alike; the minimiser per sample is unchanged.
    """
    r = physics_residual(p12, aux)
    return r.pow(2).sum(-1) / aux[:, 0].pow(2).sum(-1).clamp_min(eps)


def residual_design(aux: Tensor) -> tuple[Tensor, Tensor]:
    """(design [B, N, 2] with columns A_1 = -(v3 - v2), A_2 = -(q3 - q2), a3 [B, N]) in float64."""
    a3, v3, v2, q3, q2 = aux.double().unbind(1)
    return torch.stack([-(v3 - v2), -(q3 - q2)], -1), a3


def least_squares_p12(aux: Tensor) -> Tensor:
    """Per-sample minimiser of the residual (no labels): [B, 2] float64. Exact on clean data."""
    design, a3 = residual_design(aux)
    return torch.linalg.lstsq(design, a3[..., None]).solution[..., 0]


def balanced_residual_loss(p12: Tensor, aux: Tensor, eps: float = 1e-30) -> Tensor:
    """The residual in preconditioned parameter coordinates [B] (no labels needed).

    On clean data the residual is linear in p: r(p̂) = -sum_j A_j (p̂_j - p*_j) with columns
    A_1 = -(v3 - v2), A_2 = -(q3 - q2) and p* the per-sample least-squares minimiser (computed
    from the same a3, v, q). Writing it in relative deviations eps_j = p̂_j / p*_j - 1 with
    each term's column scaled to unit energy,

        r_bal = sum_j eps_j (A_j p*_j) / ||A_j p*_j||,    loss = sum_k r_bal,k^2,

    removes the ~20x imbalance between the damping term (p1) and the spring term (p2) of the
    plain residual energy, so p1 trains as fast as p2. Same minimiser as physics_residual_loss.
    """
    design, a3 = residual_design(aux)
    with torch.no_grad():
        p_star = torch.linalg.lstsq(design, a3[..., None]).solution[..., 0]  # [B, 2]
        terms = design * p_star[:, None, :]  # [B, N, 2]
        unit = terms / terms.norm(dim=1, keepdim=True).clamp_min(eps**0.5)
    rel = p12.double() / p_star - 1  # [B, 2]
    return (unit * rel[:, None, :]).sum(-1).pow(2).sum(-1)


__all__ = [
    "rms",
    "physics_residual",
    "physics_residual_loss",
    "residual_design",
    "least_squares_p12",
    "balanced_residual_loss",
]
