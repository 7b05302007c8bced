"""Exact continuous-time response of the quarter car to a sum-of-sines road (SPEC §3, §9).

Between samples the vehicle obeys x' = A x + B u(t), x = (v3, v2, v1, q3, q2, q1),
B u = (0, 0, p_u u, 0, 0, 0), and the road is u(t) = sum_i a_i sin(w_i t - phi_i) with
w_i = Omega_i * speed. The car starts from rest at t = 0 and the logger records
t_k = t0 + k h, t0 = the sample's warm-up.

Particular (steady-state) solution: for the forcing Im[a e^{i(w t - phi)}] it is
Im[G(w) a e^{i(w t - phi)}] with G(w) = (i w I - A)^{-1} B. With A = V L V^{-1},
G(w) = V diag(1 / (i w - lambda)) V^{-1} B, so all 1000 frequencies cost one [6, 6] x [6, W]
product per sample. With Z = G a e^{-i psi}, psi = phi - w t0 (the warm-up folded into the phase),

    Im[Z e^{i w k h}] = Re(Z) sin(w k h) + Im(Z) cos(w k h),

so the window is one GEMM of per-sample coefficients [b 7, 2 W] (six states and the road, whose
Z is a e^{-i psi}) against the shared basis of rows (sin(w_i k h), cos(w_i k h)) interleaved per
wave, [2 W, T], as in RoadProfile.evaluate; (Re Z, Im Z) interleaved is view_as_real(Z).

Homogeneous part: x(t) = x_p(t) + exp(A t)(x(0) - x_p(0)) with x(0) = 0, i.e.
x_h(t) = -Re[V diag(e^{lambda t}) V^{-1} x_p(0)].

Seated person (physics/seated.py): with `body` [b, 3 n] the state gains the n body modes,
x = (v3, v2, v1, q3, q2, q1, y', y), n = 6 + 2 n states; the same algebra applies with A the
seated system matrix, and a3 is the seat pan's acceleration. body = None (the rigid occupant) runs
exactly today's arithmetic.

A sample whose eigendecomposition reconstructs A poorly (a nearly defective A) falls back to a
solve of (i w I - A) per frequency and to matrix exponentials for the homogeneous part; both
paths are exact up to round-off, the fallback is only slower.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.parameters import road_gain, system_matrix
from hybridqcm.physics.seated import seated_system_matrix

# relative reconstruction error ||V L V^-1 - A|| / ||A|| above which a sample takes the fallback
EIG_TOL = 1e-9


@dataclass
class ContinuousResponse:
    """accel, vel, disp [b, T, 3] (order 3, 2, 1), road u [b, T] in metres, state0 x(t0) [b, 6]
    (v3 v2 v1 q3 q2 q1), all float64; `n_fallback` samples used the per-frequency solve;
    `body_state0` [b, 2 n] (y', y at t0) with a seated person's n body modes, else None."""

    accel: Tensor
    vel: Tensor
    disp: Tensor
    road: Tensor
    state0: Tensor
    n_fallback: int = 0
    body_state0: Tensor | None = None


def time_basis(omega_t: Tensor, n_steps: int, h: float) -> Tensor:
    """Rows sin(w_i k h), cos(w_i k h) interleaved per wave, [2 W, n_steps] (float64), w = temporal
    frequencies [W] in rad/s."""
    angle = omega_t.to(torch.float64)[:, None] * (h * torch.arange(n_steps, dtype=torch.float64))[None, :]
    return torch.stack([torch.sin(angle), torch.cos(angle)], 1).reshape(2 * omega_t.shape[0], n_steps)


def _check(
    p: Tensor, amplitude: Tensor, phase: Tensor, omega_t: Tensor, n_steps: int, h: float, warmup: Tensor
) -> None:
    if p.ndim != 2 or p.shape[-1] != 10:
        raise ValueError(f"p must be [batch, 10], got {tuple(p.shape)}")
    b, w = p.shape[0], omega_t.shape[0]
    if amplitude.shape != (b, w) or phase.shape != (b, w):
        raise ValueError(
            f"amplitude and phase must be [batch, waves] = [{b}, {w}], got {tuple(amplitude.shape)}, {tuple(phase.shape)}"
        )
    if warmup.shape != (b,):
        raise ValueError(f"warmup must be [batch] = [{b}], got {tuple(warmup.shape)}")
    if not h > 0 or n_steps < 1:
        raise ValueError(f"need h > 0 and n_steps >= 1, got h = {h}, n_steps = {n_steps}")
    if bool((warmup < 0).any()) or not bool(torch.isfinite(warmup).all()):
        raise ValueError(f"warmup must be finite and >= 0 seconds, got min {float(warmup.min())}")


def _gains_eig(V: Tensor, lam: Tensor, Vinv: Tensor, gain: Tensor, omega_t: Tensor) -> Tensor:
    """G(w) [b, n, W] complex = V diag(1/(i w - lambda)) V^{-1} e_v1 p_u."""
    c = Vinv[:, :, 2] * gain[:, None].to(Vinv.dtype)  # [b, 6]
    modal = c[:, :, None] / (1j * omega_t[None, None, :] - lam[:, :, None])  # [b, 6, W]
    return V @ modal


def _gains_solve(A: Tensor, gain: Tensor, omega_t: Tensor) -> Tensor:
    """G(w) [b, n, W] by one complex n x n solve per frequency (the fallback)."""
    b, w, n = A.shape[0], omega_t.shape[0], A.shape[-1]
    eye = torch.eye(n, dtype=torch.complex128)
    lhs = 1j * omega_t[None, :, None, None] * eye - A[:, None].to(torch.complex128)  # [b, W, n, n]
    rhs = torch.zeros(b, w, n, 1, dtype=torch.complex128)
    rhs[:, :, 2, 0] = gain[:, None]
    return torch.linalg.solve(lhs, rhs)[..., 0].transpose(1, 2)


def simulate_continuous(
    p: Tensor,
    amplitude: Tensor,
    phase: Tensor,
    omega_t: Tensor,
    n_steps: int,
    h: float,
    warmup: Tensor | float = 0.0,
    basis: Tensor | None = None,
    eig_tol: float = EIG_TOL,
    block: int = 256,
    body: Tensor | None = None,
) -> ContinuousResponse:
    """Exact response, recorded at t_k = warmup + k h, for p [b, 10], road amplitudes/phases [b, W]
    (u(t) = sum_i amplitude_i sin(omega_t_i t - phase_i)), temporal frequencies omega_t [W] rad/s,
    warmup [b] seconds (the car starts from rest at t = 0). `basis` = time_basis(omega_t, n_steps, h)
    when the caller shares it across chunks. Samples go through in blocks of `block`: the
    [block, 6, W] complex intermediates then stay small enough to be cheap to stream.
    `body` [b, 3 n] (r_i, k_i, c_i per mode, physics/occupant.py): a seated person with n = 1 or 2
    body modes on the seat pan (physics/seated.py); None or [b, 0]: the rigid occupant."""
    p = p.to(torch.float64)
    b = p.shape[0]
    amplitude, phase, omega_t = amplitude.to(torch.float64), phase.to(torch.float64), omega_t.to(torch.float64)
    warmup = torch.as_tensor(warmup, dtype=torch.float64)
    warmup = warmup.expand(b).clone() if warmup.ndim == 0 else warmup
    _check(p, amplitude, phase, omega_t, n_steps, h, warmup)
    if body is not None:
        body = body.to(torch.float64)
        if body.ndim != 2 or body.shape[0] != b or body.shape[1] not in (0, 3, 6):
            raise ValueError(f"body must be [batch, 3 n_modes] = [{b}, 0|3|6], got {tuple(body.shape)}")
        if body.shape[1] == 0:
            body = None
    if basis is None:
        basis = time_basis(omega_t, n_steps, h)
    parts = [
        _block(
            p[i : i + block],
            amplitude[i : i + block],
            phase[i : i + block],
            omega_t,
            n_steps,
            h,
            warmup[i : i + block],
            basis,
            eig_tol,
            None if body is None else body[i : i + block],
        )
        for i in range(0, b, max(1, int(block)))
    ]
    if len(parts) == 1:
        return parts[0]
    return ContinuousResponse(
        *(torch.cat([getattr(r, k) for r in parts]) for k in ("accel", "vel", "disp", "road", "state0")),
        n_fallback=sum(r.n_fallback for r in parts),
        body_state0=None if body is None else torch.cat([r.body_state0 for r in parts]),
    )


def _block(
    p: Tensor,
    amplitude: Tensor,
    phase: Tensor,
    omega_t: Tensor,
    n_steps: int,
    h: float,
    warmup: Tensor,
    basis: Tensor,
    eig_tol: float,
    body: Tensor | None = None,
) -> ContinuousResponse:
    b = p.shape[0]
    A = system_matrix(p) if body is None else seated_system_matrix(p, body)
    n = A.shape[-1]
    gain = road_gain(p)
    lam, V = torch.linalg.eig(A)
    Vinv = torch.linalg.inv(V)
    rebuilt = (V * lam[:, None, :]) @ Vinv
    error = (rebuilt - A).abs().amax((-2, -1)) / A.abs().amax((-2, -1))
    bad = ~(error <= eig_tol)  # NaN (singular V) counts as bad
    good = ~bad
    all_good = bool(good.all())
    road_z = torch.polar(amplitude, omega_t[None, :] * warmup[:, None] - phase)  # a e^{-i psi} [b, W]
    start_z = torch.polar(amplitude, -phase)  # a e^{-i phi}: t = 0
    if all_good:
        # G never formed: V (modal z) per sample, and x_p(0) = Im[V (modal @ z0)] by one small bmm
        modal = (Vinv[:, :, 2] * gain[:, None])[:, :, None] / (1j * omega_t[None, None, :] - lam[:, :, None])
        states_z = V @ (modal * road_z[:, None, :])  # [b, 6, W]
        xp0 = (V @ (modal @ start_z[:, :, None]))[..., 0].imag  # [b, 6]
    else:
        G = torch.empty(b, n, omega_t.shape[0], dtype=torch.complex128)
        if good.any():
            G[good] = _gains_eig(V[good], lam[good], Vinv[good], gain[good], omega_t)
        G[bad] = _gains_solve(A[bad], gain[bad], omega_t)
        states_z = G * road_z[:, None, :]
        xp0 = (G * start_z[:, None, :]).imag.sum(-1)  # x_p(0) [b, n]

    # Particular part at the window: the warm-up folded into the phases, one GEMM for states and road.
    Z = torch.cat([states_z, road_z[:, None, :]], 1)  # [b, n + 1, W]
    series = (torch.view_as_real(Z).reshape(b * (n + 1), -1) @ basis).reshape(b, n + 1, n_steps)
    x = series[:, :n]  # [b, n, T]
    road = series[:, n]  # [b, T]

    # Homogeneous part from rest at t = 0: x(t) = x_p(t) - exp(A t) x_p(0).
    t = warmup[:, None] + h * torch.arange(n_steps, dtype=torch.float64)[None, :]  # [b, T]
    if all_good:
        d = Vinv @ (-xp0).to(torch.complex128)[:, :, None]  # V^{-1}(-x_p(0)) [b, n, 1]
        x += (V @ (d * torch.exp(lam[:, :, None] * t[:, None, :]))).real
    elif good.any():
        d = Vinv[good] @ (-xp0[good]).to(torch.complex128)[:, :, None]
        x[good] += (V[good] @ (d * torch.exp(lam[good][:, :, None] * t[good][:, None, :]))).real
    if bad.any():
        A_bad, t_bad = A[bad], t[bad]
        start = torch.matrix_exp(A_bad * t_bad[:, :1, None])  # exp(A t0)
        step = torch.matrix_exp(A_bad * h)
        state = start @ (-xp0[bad])[:, :, None]  # [bad, n, 1]
        columns = []
        for _ in range(n_steps):
            columns.append(state[..., 0])
            state = step @ state
        x[bad] += torch.stack(columns, -1)

    vel, disp = x[:, :3].transpose(1, 2), x[:, 3:6].transpose(1, 2)  # [b, T, 3]
    accel = vel @ A[:, :3, :3].transpose(1, 2) + disp @ A[:, :3, 3:6].transpose(1, 2)
    if n > 6:  # the body modes pull on the seat pan
        accel = accel + x[:, 6:].transpose(1, 2) @ A[:, :3, 6:].transpose(1, 2)
    accel[..., 2] += gain[:, None] * road
    return ContinuousResponse(
        accel=accel,
        vel=vel.contiguous(),
        disp=disp.contiguous(),
        road=road,
        state0=x[:, :6, 0].clone(),
        n_fallback=int(bad.sum()),
        body_state0=x[:, 6:, 0].clone() if n > 6 else None,
    )


__all__ = ["ContinuousResponse", "simulate_continuous", "time_basis", "EIG_TOL"]
