"""A start for the half car's and full car's GN: the equations of motion as linear regressions.

With every acceleration observed, each row of M ẍ + C ẋ + K x = F u + G u̇ divided by its mass is
linear in that row's coefficients:

    a_i(t) = Σ_j α_ij v_j(t) + Σ_j β_ij q_j(t) + γ_i u_w(t) (+ δ_i u̇_w(t)),   α = -M⁻¹C, β = -M⁻¹K, ...

The velocities and displacements are the accelerations integrated over the window (a quintic spline
through the samples, integrated exactly) plus the unknown initial state: v_j = V_j + v0_j,
q_j = Q_j + q0_j + v0_j t, so the initial state only adds a constant and a slope to each row,
c0_i + c1_i t, which join the regressors. Each row is one small linear least-squares problem on the
coordinates it couples to (a seat: itself and the body; a wheel: itself, the body and its road;
the body's rows: everything). This is the identifiability argument of docs/design/vehicles.md made
constructive: the rows give the mass-normalised coefficients, and one known scale (the seats' k3)
chains them into every physical parameter:

    seat s:   m3 = k3 / (-β_ss),  c3 = -α_ss m3,  x_s = -β_s,pitch / β_ss,  y_s = -β_s,roll / β_ss
    chassis:  m2 = k3 / β_2,s,  k2w = m2 β_2,w,  c2w = m2 α_2,w
    wheel w:  m1w = k2w / β_w,2,  k1w = m1w γ_w (c1w = m1w δ_w),  x_w = β_w,pitch / β_w,2,  y_w = β_w,roll / β_w,2
    angles:   I_pitch = Σ_w (k2w x_w)² / Σ_w (k2w x_w) β_pitch,w,  I_roll likewise with y_w

(averaged in the least-squares sense where several rows give the same quantity). Noise-free it lands
within the integration error of the truth; with sensor noise the integrated noise biases it (errors in
variables), which GN then removes. A value that is not finite, of the wrong sign, or out of the prior's
reach of the previous start (equation_error_start) keeps the previous start's (the reference vehicle's).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hybridqcm.physics.vehicle_geometry import VehicleLayout


def integrate_twice(accel: Tensor, h: float) -> tuple[Tensor, Tensor]:
    """(V, Q) [b, T, n]: the first and second integrals from the window's first sample of the quintic
    spline through accel [b, T, n] (sampled every h)."""
    from scipy.interpolate import make_interp_spline

    b, T, n = accel.shape
    t = h * np.arange(T, dtype=np.float64)
    y = accel.double().permute(1, 0, 2).reshape(T, b * n).cpu().numpy()
    spline = make_interp_spline(t, y, k=5 if T >= 6 else (3 if T >= 4 else 1), axis=0)
    first, second = spline.antiderivative(1), spline.antiderivative(2)
    V = torch.from_numpy(first(t) - first(t[:1])).reshape(T, b, n).permute(1, 0, 2)
    Q = torch.from_numpy(second(t) - second(t[:1]) - t[:, None] * first(t[:1])).reshape(T, b, n).permute(1, 0, 2)
    return V.contiguous(), Q.contiguous()


def _row_fit(target: Tensor, regressors: list[Tensor]) -> Tensor:
    """Least squares target [b, T] ≈ Σ_k c_k regressors[k] [b, T]; columns scaled to unit norm first.

    The SVD driver (gelsd), not the CPU default (gelsy): on nearly rank-deficient rows gelsy's answer
    changed from call to call on the same input (order one; its pivoting reads uninitialised memory), so
    two runs of one half car differed by 1e-8."""
    X = torch.stack(regressors, -1)  # [b, T, p]
    scale = X.square().sum(1).sqrt().clamp_min(1e-300)  # [b, p]
    solution = torch.linalg.lstsq(X / scale[:, None, :], target[..., None], driver="gelsd").solution[..., 0]
    return solution / scale


SEAT_QUANTITIES = ("m3", "c3", "x_s", "y_s")


def equation_error_start(
    layout: VehicleLayout,
    param_names: tuple[str, ...],
    accel: Tensor,
    inputs: Tensor,
    h: float,
    start: Tensor,
    known: Tensor,
    max_ratio: float = 1.5,
    seats_only: bool = False,
) -> Tensor:
    """Parameters [b, P] (``param_names``, a VehicleModel's) from accelerations accel [b, T, n_dof] and
    road inputs [b, T, n_in] (heights, then velocities with damped tyres) of one window. ``start``
    [b, P] is the previous start: its known entries (``known`` [P] bool) are kept and give the scale
    (the seats' k3), and it is the fallback for any value the regressions cannot give, or give out
    of the prior's reach of it: a vehicle quantity more than ``max_ratio`` (a length more than 20 %)
    from the start, an occupant mass more than 3x, a seat more than 0.5 m away (under sensor noise a
    row can come out far off; GN started there may settle in a wrong basin that restarts around the
    start do not leave).
    ``seats_only``: take only the seats' m3, c3, x_s, y_s from the regressions (their rows stay sharp
    under sensor noise; the body's and wheels' rows regress on doubly integrated noise and come out
    biased by tens of per cent at 5 % noise, worse than a start from the reference vehicle)."""
    accel, inputs, start = accel.double(), inputs.double(), start.double()
    b, T, _ = accel.shape
    V, Q = integrate_twice(accel, h)
    t = h * torch.arange(T, dtype=torch.float64).expand(b, T)
    ones = torch.ones(b, T, dtype=torch.float64)
    dof = {name: i for i, name in enumerate(layout.dofs)}
    body = ["z2", "pitch"] + (["roll"] if layout.full else [])
    seats = [f"z3{layout.suffix(s)}" for s in layout.seat_names]
    wheels = [f"z1{w}" for w in layout.wheels]
    value = {n: start[:, j].clone() for j, n in enumerate(param_names)}

    def fit(row: str, coupled: list[str], extra: list[Tensor]) -> dict[str, Tensor]:
        regressors = [V[..., dof[c]] for c in coupled] + [Q[..., dof[c]] for c in coupled] + extra + [ones, t]
        c = _row_fit(accel[..., dof[row]], regressors)
        n = len(coupled)
        out = {f"a_{x}": c[:, k] for k, x in enumerate(coupled)}
        out.update({f"b_{x}": c[:, n + k] for k, x in enumerate(coupled)})
        out.update({f"e{k}": c[:, 2 * n + k] for k in range(len(extra))})
        return out

    derived: dict[str, Tensor] = {}
    k3 = {s: value[layout.seat_param("k3", s)] for s in layout.seat_names}
    for s, z3 in zip(layout.seat_names, seats):  # seat rows
        r = fit(z3, [z3, *body], [])
        m3 = k3[s] / -r[f"b_{z3}"]
        derived[layout.seat_param("m3", s)] = m3
        derived[layout.seat_param("c3", s)] = -r[f"a_{z3}"] * m3
        derived[layout.seat_param("x_s", s)] = -r["b_pitch"] / r[f"b_{z3}"]
        if layout.full:
            derived[layout.seat_param("y_s", s)] = -r["b_roll"] / r[f"b_{z3}"]
    everything = seats + body + wheels
    r = fit("z2", everything, [])  # chassis row
    k3_all = torch.stack([k3[s] for s in layout.seat_names], -1)
    b_seats = torch.stack([r[f"b_{z}"] for z in seats], -1)
    m2 = k3_all.square().sum(-1) / (k3_all * b_seats).sum(-1)
    derived["m2"] = m2
    for w, z1 in zip(layout.wheels, wheels):
        derived[f"k2{w}"] = m2 * r[f"b_{z1}"]
        derived[f"c2{w}"] = m2 * r[f"a_{z1}"]
    n_w = len(layout.wheels)
    position = {}
    for i, (w, z1) in enumerate(zip(layout.wheels, wheels)):  # wheel rows
        extra = [inputs[..., i]] + ([inputs[..., n_w + i]] if layout.tyre_damping else [])
        r = fit(z1, [z1, *body], extra)
        m1 = derived[f"k2{w}"] / r["b_z2"]
        derived[f"m1{w}"] = m1
        derived[f"k1{w}"] = m1 * r["e0"]
        if layout.tyre_damping:
            derived[f"c1{w}"] = m1 * r["e1"]
        position[w] = (r["b_pitch"] / r["b_z2"], r["b_roll"] / r["b_z2"] if layout.full else None)
    front = [w for w in layout.wheels if w.startswith("f")]
    back = [w for w in layout.wheels if w.startswith("b")]
    derived["l_f"] = torch.stack([position[w][0] for w in front]).mean(0)
    derived["l_b"] = -torch.stack([position[w][0] for w in back]).mean(0)
    if layout.full:
        derived["w_r"] = torch.stack([position[w][1] for w in layout.wheels if w.endswith("r")]).mean(0)
        derived["w_l"] = -torch.stack([position[w][1] for w in layout.wheels if w.endswith("l")]).mean(0)
    for angle, axis in (("pitch", 0), ("roll", 1)) if layout.full else (("pitch", 0),):
        r = fit(angle, everything, [])
        lever = torch.stack([derived[f"k2{w}"] * position[w][axis] for w in layout.wheels], -1)  # k2w x_w
        slope = torch.stack([r[f"b_{z}"] for z in wheels], -1)
        derived["I_pitch" if angle == "pitch" else "I_roll"] = lever.square().sum(-1) / (lever * slope).sum(-1)
    out = start.clone()
    for j, name in enumerate(param_names):
        if bool(known[j]) or name not in derived:
            continue
        if seats_only and not name.startswith(SEAT_QUANTITIES):
            continue
        new, old = derived[name], start[:, j]
        if name.startswith(("x_s", "y_s")):
            ok = torch.isfinite(new) & ((new - old).abs() <= 0.5)  # metres
        else:
            bound = 3.0 if name.startswith("m3") else (1.2 if name.startswith(("l_", "w_")) else max_ratio)
            ratio = new / old
            ok = torch.isfinite(ratio) & (ratio > 1 / bound) & (ratio < bound)
        out[:, j] = torch.where(ok, new, old)
    return out


__all__ = ["equation_error_start", "integrate_twice", "SEAT_QUANTITIES"]
