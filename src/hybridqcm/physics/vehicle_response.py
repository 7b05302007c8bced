"""Exact continuous-time response of a linear model to sum-of-sines inputs (the vehicles' simulator).

physics/continuous.py's algebra for any LinearModel x' = A x + B w(t), y = C x + E w, with every
input a sum of sines on one frequency grid: w_j(t) = Im Σ_i z_ji e^(i ω_i t) (physics/two_track_road.py:
each wheel's road height and, for damped tyres, its velocity i ω z). The system starts from rest
at t = 0 and is recorded at t_k = t0 + k h (t0 = the sample's warm-up).

Particular solution: X(ω) = (i ω I − A)⁻¹ B z(ω); with A = V Λ V⁻¹ all W frequencies cost
V diag(1/(i ω − λ)) V⁻¹ B z: one [n, n] x [n, W] product per sample. With Z = X e^(i ω t0), the window is
Im[Z e^(i ω k h)] = Re(Z) sin(ω k h) + Im(Z) cos(ω k h): one GEMM against physics.continuous.time_basis.
Homogeneous part: x(t) = x_p(t) − exp(A t) x_p(0) (from rest), x_p(0) = Im Σ_i X(ω_i).
A sample whose eigendecomposition reconstructs A poorly (nearly defective) takes a per-frequency
solve and matrix exponentials instead; both are exact up to round-off.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.continuous import EIG_TOL, time_basis


@dataclass
class LinearResponse:
    """states x [b, T, n], inputs w [b, T, m] at the recorded instants, x(t0) [b, n], all float64;
    n_fallback: samples that took the per-frequency solve."""

    states: Tensor
    inputs: Tensor
    state0: Tensor
    n_fallback: int = 0


def linear_response(
    A: Tensor,
    B: Tensor,
    z: Tensor,
    omega_t: Tensor,
    n_steps: int,
    h: float,
    warmup: Tensor,
    basis: Tensor | None = None,
    eig_tol: float = EIG_TOL,
    block: int = 128,
) -> LinearResponse:
    """Exact response for A [b, n, n], B [b, n, m], input amplitudes z [b, m, W] (complex), temporal
    frequencies omega_t [W] rad/s, warm-up [b] seconds; recorded at warmup + k h, k < n_steps.
    ``basis``: time_basis(omega_t, n_steps, h), when shared across calls. Samples go in blocks of
    ``block`` (the [block, n, W] complex intermediates stay small)."""
    A, B = A.to(torch.float64), B.to(torch.float64)
    z, omega_t = z.to(torch.complex128), omega_t.to(torch.float64)
    warmup = torch.as_tensor(warmup, dtype=torch.float64)
    b, n, m, w = A.shape[0], A.shape[-1], B.shape[-1], omega_t.shape[0]
    warmup = warmup.expand(b).clone() if warmup.ndim == 0 else warmup
    if A.shape != (b, n, n) or B.shape != (b, n, m) or z.shape != (b, m, w) or warmup.shape != (b,):
        raise ValueError(
            f"linear_response: need A [b, n, n], B [b, n, m], z [b, m, W], warmup [b]; got {tuple(A.shape)}, "
            f"{tuple(B.shape)}, {tuple(z.shape)}, {tuple(warmup.shape)}"
        )
    if not h > 0 or n_steps < 1 or bool((warmup < 0).any()) or not bool(torch.isfinite(warmup).all()):
        raise ValueError(f"linear_response: need h > 0, n_steps >= 1, finite warm-ups >= 0 (h = {h}, n = {n_steps})")
    if basis is None:
        basis = time_basis(omega_t, n_steps, h)
    parts = [
        _block(
            A[i : i + block],
            B[i : i + block],
            z[i : i + block],
            omega_t,
            n_steps,
            h,
            warmup[i : i + block],
            basis,
            eig_tol,
        )
        for i in range(0, b, max(1, int(block)))
    ]
    return LinearResponse(
        torch.cat([p.states for p in parts]),
        torch.cat([p.inputs for p in parts]),
        torch.cat([p.state0 for p in parts]),
        sum(p.n_fallback for p in parts),
    )


def _block(A, B, z, omega_t, n_steps, h, warmup, basis, eig_tol) -> LinearResponse:
    b, n, m = A.shape[0], A.shape[-1], B.shape[-1]
    lam, V = torch.linalg.eig(A)
    Vinv = torch.linalg.inv(V)
    rebuilt = (V * lam[:, None, :]) @ Vinv
    error = (rebuilt - A).abs().amax((-2, -1)) / A.abs().amax((-2, -1))
    bad = ~(error <= eig_tol)  # NaN (singular V) counts as bad
    forcing = B.to(torch.complex128) @ z  # B z(ω) [b, n, W]
    X = torch.empty(b, n, omega_t.shape[0], dtype=torch.complex128)
    good = ~bad
    if bool(good.any()):
        modal = (Vinv[good] @ forcing[good]) / (1j * omega_t[None, None, :] - lam[good][:, :, None])
        X[good] = V[good] @ modal
    if bool(bad.any()):
        eye = torch.eye(n, dtype=torch.complex128)
        lhs = 1j * omega_t[None, :, None, None] * eye - A[bad][:, None].to(torch.complex128)  # [bad, W, n, n]
        X[bad] = torch.linalg.solve(lhs, forcing[bad].transpose(1, 2)[..., None])[..., 0].transpose(1, 2)
    xp0 = X.imag.sum(-1)  # x_p(0) [b, n]
    shift = torch.polar(torch.ones_like(omega_t)[None, :].expand(b, -1), omega_t[None, :] * warmup[:, None])
    Z = torch.cat([X, z], 1) * shift[:, None, :]  # states and inputs at the window's phases
    series = (torch.view_as_real(Z).reshape(b * (n + m), -1) @ basis).reshape(b, n + m, n_steps)
    x, inputs = series[:, :n], series[:, n:]
    t = warmup[:, None] + h * torch.arange(n_steps, dtype=torch.float64)[None, :]  # [b, T]
    if bool(good.any()):
        d = Vinv[good] @ (-xp0[good]).to(torch.complex128)[:, :, None]  # [g, n, 1]
        x[good] += (V[good] @ (d * torch.exp(lam[good][:, :, None] * t[good][:, None, :]))).real
    if bool(bad.any()):
        A_bad, t_bad = A[bad], t[bad]
        state = torch.matrix_exp(A_bad * t_bad[:, :1, None]) @ (-xp0[bad])[:, :, None]
        step = torch.matrix_exp(A_bad * h)
        columns = []
        for _ in range(n_steps):
            columns.append(state[..., 0])
            state = step @ state
        x[bad] += torch.stack(columns, -1)
    return LinearResponse(
        x.transpose(1, 2).contiguous(), inputs.transpose(1, 2).contiguous(), x[:, :, 0].clone(), int(bad.sum())
    )


__all__ = ["LinearResponse", "linear_response"]
