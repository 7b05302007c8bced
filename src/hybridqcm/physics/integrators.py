"""Time integrators of the quarter-car model; semi-explicit Euler is the ground truth (SPEC §4).

Convention (used for data and for the Gauss-Newton model alike): from rest, v_0 = q_0 = 0,
the recorded acceleration at step k is

    a_k = D v_k + S q_k + b_k,   b_k = (0, 0, p_u u_k),

so (accel[k], vel[k], disp[k]) satisfy the equation of motion exactly at every k. The step
from k to k+1 depends on the method; the input is held constant over a step (zero-order hold).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hybridqcm.physics.parameters import road_gain, system_matrix

METHODS = ("semi_explicit_euler", "forward_euler", "implicit_midpoint", "rk4")


@dataclass
class Trajectory:
    """accel, vel, disp: [batch, time, 3] in the (3, 2, 1) order."""

    accel: Tensor
    vel: Tensor
    disp: Tensor


def _forcing(p: Tensor, road: Tensor, scaled_road: bool) -> Tensor:
    """Wheel forcing p_u u [batch, time] (road given in metres unless already scaled)."""
    if road.ndim != 2 or road.shape[0] != p.shape[0]:
        raise ValueError(f"road must be [batch, time] with batch {p.shape[0]}, got {tuple(road.shape)}")
    return road if scaled_road else road_gain(p)[:, None] * road


def _acceleration(p: Tensor, v: Tensor, q: Tensor, force: Tensor) -> Tensor:
    """a = D v + S q + b [batch, 3], written out component-wise (cheaper than tiny matmuls)."""
    p1, p2, p3, p4, p5, p6, p7, p8, p9, p10 = p.unbind(-1)
    v3, v2, v1 = v.unbind(-1)
    q3, q2, q1 = q.unbind(-1)
    dv32, dq32 = v3 - v2, q3 - q2
    a3 = -p1 * dv32 - p2 * dq32
    a2 = p3 * dv32 + p5 * dq32 - p4 * (v2 - v1) - p6 * (q2 - q1)
    a1 = p7 * v2 - p8 * v1 + p9 * q2 - p10 * q1 + force
    return torch.stack([a3, a2, a1], -1)


def simulate(
    p: Tensor, road: Tensor, h: float, method: str = "semi_explicit_euler", scaled_road: bool = False
) -> Trajectory:
    """Integrate from rest. p [batch, 10], road [batch, time] -> Trajectory of [batch, time, 3].

    Differentiable in p. `scaled_road=True` means `road` already is p_u u (the wheel forcing).
    """
    if method not in METHODS:
        raise ValueError(f"unknown integrator {method!r}; choose one of {METHODS}")
    if p.ndim != 2 or p.shape[-1] != 10:
        raise ValueError(f"p must be [batch, 10], got {tuple(p.shape)}")
    if h <= 0:
        raise ValueError(f"step h must be > 0, got {h}")
    force = _forcing(p, road.to(p.dtype), scaled_road)
    batch, n_steps = force.shape
    if n_steps < 1:
        raise ValueError(f"road must have at least one time step, got {tuple(road.shape)}")
    v = torch.zeros(batch, 3, dtype=p.dtype, device=p.device)
    q = torch.zeros_like(v)
    if method == "implicit_midpoint":
        step_map, input_map = _implicit_midpoint_maps(p, h)
        # columns [batch, 6] of the step map: a sum of small products stays clear of the slow
        # (and, on a busy CPU, erratic) multi-threaded path of batched 6x6 matmuls
        step_columns = [c.contiguous() for c in step_map.unbind(-1)]
    accel, vel, disp = [], [], []
    for k in range(n_steps):
        f = force[:, k]
        a = _acceleration(p, v, q, f)
        accel.append(a)
        vel.append(v)
        disp.append(q)
        if k == n_steps - 1:
            break
        if method == "semi_explicit_euler":
            v = v + h * a
            q = q + h * v
        elif method == "forward_euler":
            v, q = v + h * a, q + h * v
        elif method == "rk4":
            k1v, k1q = a, v
            k2v = _acceleration(p, v + 0.5 * h * k1v, q + 0.5 * h * k1q, f)
            k2q = v + 0.5 * h * k1v
            k3v = _acceleration(p, v + 0.5 * h * k2v, q + 0.5 * h * k2q, f)
            k3q = v + 0.5 * h * k2v
            k4v = _acceleration(p, v + h * k3v, q + h * k3q, f)
            k4q = v + h * k3v
            v, q = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v), q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
        else:  # implicit midpoint: the linear 6x6 step, solved once for all steps
            x = input_map * f[:, None]
            for column, component in zip(step_columns, (*v.unbind(-1), *q.unbind(-1))):
                x = x + column * component[:, None]
            v, q = x[:, :3], x[:, 3:]
    return Trajectory(torch.stack(accel, 1), torch.stack(vel, 1), torch.stack(disp, 1))


def _implicit_midpoint_maps(p: Tensor, h: float) -> tuple[Tensor, Tensor]:
    """x' = M x + n f for x = (v, q) and wheel forcing f held over the step:
    (I - h/2 A) x' = (I + h/2 A) x + h e_v1 f, so M = (I - h/2 A)^-1 (I + h/2 A), n = h (I - h/2 A)^-1 e_v1."""
    A = system_matrix(p)  # [batch, 6, 6]
    eye = torch.eye(6, dtype=p.dtype, device=p.device)
    lhs = eye - 0.5 * h * A
    M = torch.linalg.solve(lhs, eye + 0.5 * h * A)
    n = h * torch.linalg.solve(lhs, eye[:, 2].expand(p.shape[0], 6))
    return M, n.contiguous()


class SemiExplicitEuler(nn.Module):
    """Differentiable model accelerations y [batch, time, 3] for p [batch, 10] and a road [batch, time].

    The same recursion as the data generator, so the true p reproduces the stored accelerations.
    """

    def __init__(self, h: float = 0.01, scaled_road: bool = False) -> None:
        super().__init__()
        self.h, self.scaled_road = float(h), scaled_road

    def forward(self, p: Tensor, road: Tensor) -> Tensor:
        return simulate(p, road, self.h, "semi_explicit_euler", self.scaled_road).accel
