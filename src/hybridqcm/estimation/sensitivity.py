"""Forward-mode sensitivities of the semi-explicit Euler recursion (the Gauss-Newton model).

Convention (ARCHITECTURE.md, SPEC §4), from rest v_0 = q_0 = 0, state order (3, 2, 1)::

    a_k     = D(p) v_k + S(p) q_k + b_k,   b_k = (0, 0, p_u u_k),  p_u = p10 - p9
    v_{k+1} = v_k + h a_k
    q_{k+1} = q_k + h v_{k+1}

Why the formulation below is fast: every acceleration is a *linear* combination of the
parameters with state-dependent coefficients,

    a3 = p1 c1 + p2 c2,                 c1 = v2 - v3, c2 = q2 - q3
    a2 = p3 c3 + p4 c4 + p5 c5 + p6 c6, c3 = v3 - v2, c4 = v1 - v2, c5 = q3 - q2, c6 = q1 - q2
    a1 = p7 c7 + ... + p10 c10 (+ f),   c7 = v2, c8 = -v1, c9 = q2 - u, c10 = u - q1

(with a *scaled* road the forcing f = p_u u is a given input and c9 = q2, c10 = -q1).
The coefficients c = M x are one constant [10, 7] matrix applied to the augmented state
x = (v3, v2, v1, q3, q2, q1, u). Carrying the primal and the 10 tangents d/dp_j side by side
as an axis of width 11 (column 0 primal, column j the derivative w.r.t. p_j), one Euler
step is: one small matmul for c, one multiply by p, one scatter of the explicit terms
∂a/∂p_j = c_j, one matmul summing into (a3, a2, a1), two axpy's for v and q. No autograd graph,
no per-sample bmm.

Initial state: a window cut from a drive starts at x0 = (v_0, q_0) ≠ 0. Every column of the
recursion is linear in the state, so x0 enters as the primal's initial value, and its 6
tangents ∂/∂x0_i are 6 more columns started at the unit vectors (width 17 instead of 11).

On the CPU in float64 the same recursion runs compiled, one sample at a time (_kernels.py: 4-8x
less time a chunk); the torch recursion below serves other devices and dtypes and is the kernel's
reference in the tests.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ._kernels import applies as _compiled_applies
from ._kernels import euler_recursion as _compiled_recursion

N_PARAMS = 10
# Which acceleration row (0 = a3, 1 = a2, 2 = a1) each parameter p1..p10 acts on.
_PARAM_ROW = (0, 0, 1, 1, 1, 1, 2, 2, 2, 2)


def _coefficient_matrix(scaled_road: bool, dtype: torch.dtype, device) -> Tensor:
    """[10, 7] map from the augmented state (v3, v2, v1, q3, q2, q1, u) to c1..c10."""
    rows = [
        [-1, 1, 0, 0, 0, 0, 0],  # c1 = v2 - v3
        [0, 0, 0, -1, 1, 0, 0],  # c2 = q2 - q3
        [1, -1, 0, 0, 0, 0, 0],  # c3 = v3 - v2
        [0, -1, 1, 0, 0, 0, 0],  # c4 = v1 - v2
        [0, 0, 0, 1, -1, 0, 0],  # c5 = q3 - q2
        [0, 0, 0, 0, -1, 1, 0],  # c6 = q1 - q2
        [0, 1, 0, 0, 0, 0, 0],  # c7 = v2
        [0, 0, -1, 0, 0, 0, 0],  # c8 = -v1
        [0, 0, 0, 0, 1, 0, -1],  # c9 = q2 - u   (p_u = p10 - p9 multiplies u)
        [0, 0, 0, 0, 0, -1, 1],  # c10 = u - q1
    ]
    m = torch.tensor(rows, dtype=dtype, device=device)
    if scaled_road:  # forcing p_u u given: it does not depend on p9, p10
        m[:, 6] = 0.0
    return m


def _row_sum_matrix(dtype, device) -> Tensor:
    """[3, 10] 0/1 matrix summing the weighted coefficients into (a3, a2, a1)."""
    g = torch.zeros(3, N_PARAMS, dtype=dtype, device=device)
    g[torch.tensor(_PARAM_ROW), torch.arange(N_PARAMS)] = 1.0
    return g


def _check_inputs(params: Tensor, road: Tensor) -> None:
    if params.ndim != 2 or params.shape[-1] != N_PARAMS:
        raise ValueError(f"params must be [batch, 10], got {tuple(params.shape)}")
    if road.ndim != 2 or road.shape[0] != params.shape[0]:
        raise ValueError(f"road must be [batch, time] with batch {params.shape[0]}, got {tuple(road.shape)}")


@torch.no_grad()
def euler_accelerations(
    params: Tensor, road: Tensor, h: float, scaled_road: bool = False, x0: Tensor | None = None
) -> Tensor:
    """Model accelerations without tangents (forward only, the line-search evaluation).

    params [batch, 10], road [batch, time] (u in metres, or p_u·u when ``scaled_road``), x0
    [batch, 6] = (v3, v2, v1, q3, q2, q1) at the first sample (None: rest)
    -> accelerations [batch, time, 3] columns (a3, a2, a1), in the dtype of ``params``.
    """
    return _recursion(params, road, h, scaled_road, with_tangents=False, x0=x0)[..., 0]


@torch.no_grad()
def euler_sensitivities(
    params: Tensor,
    road: Tensor,
    h: float,
    scaled_road: bool = False,
    x0: Tensor | None = None,
    with_x0: bool = False,
    targets: Tensor | None = None,
) -> Tensor:
    """Accelerations and their derivatives w.r.t. all 10 parameters (and x0) in one forward pass.

    Returns ``[batch, time, 3, 11]`` (``[batch, time, 3, 17]`` with ``with_x0``): [..., 0] the
    accelerations, [..., j] = ∂a/∂p_j (j = 1..10), [..., 10 + i] = ∂a/∂x0_i (i = 1..6).
    Viewed as [batch, time*3, width] it is the Jacobian with the prediction as an extra first
    column, which is how the solver forms JᵀJ, JᵀR and RᵀR with a single bmm. ``targets`` [batch, time, 3]:
    column 0 is the residual a - targets instead (subtracted per step while the block is in cache).
    """
    return _recursion(params, road, h, scaled_road, with_tangents=True, x0=x0, with_x0=with_x0, targets=targets)


def accelerations_and_jacobian(
    params: Tensor, road: Tensor, h: float, scaled_road: bool = False
) -> tuple[Tensor, Tensor]:
    """Accelerations [batch, time, 3] and Jacobian [batch, time, 3, 10]."""
    out = euler_sensitivities(params, road, h, scaled_road)
    return out[..., 0], out[..., 1:]


def _recursion(
    params: Tensor,
    road: Tensor,
    h: float,
    scaled_road: bool,
    with_tangents: bool,
    x0: Tensor | None = None,
    with_x0: bool = False,
    targets: Tensor | None = None,
) -> Tensor:
    """The Euler recursion on the augmented state; returns [batch, time, 3, width] (column 0 less ``targets``)."""
    _check_inputs(params, road)
    dtype, device = params.dtype, params.device
    batch, n_steps = road.shape
    if x0 is not None and tuple(x0.shape) != (batch, 6):
        raise ValueError(f"x0 must be [batch, 6] = [{batch}, 6] (v3, v2, v1, q3, q2, q1), got {tuple(x0.shape)}")
    width = (N_PARAMS + 1 + (6 if with_x0 else 0)) if with_tangents else 1
    if _compiled_applies(params):  # the same recursion compiled, per sample (_kernels.py)
        return _compiled_recursion(params, road, h, scaled_road, width, x0, with_tangents and with_x0, targets)
    coeff = _coefficient_matrix(scaled_road, dtype, device)  # [10, 7]
    row_sum = _row_sum_matrix(dtype, device)  # [3, 10]
    weights = params.t().contiguous().unsqueeze(1)  # [10, 1, batch]
    road_t = road.to(dtype).t().contiguous()  # [time, batch]
    targets_t = None if targets is None else targets.to(dtype).permute(1, 2, 0).contiguous()  # [time, 3, batch]

    # Augmented state (v3, v2, v1, q3, q2, q1, u) x (primal, tangents) x batch: [7, width, batch].
    # Batch innermost keeps every slice below contiguous (strided column access was 10x slower).
    state = torch.zeros(7, width, batch, dtype=dtype, device=device)
    if x0 is not None:
        state[0:6, 0] = x0.to(dtype).t()
    if with_tangents and with_x0:  # ∂x_0/∂x0_i = e_i
        state[torch.arange(6), N_PARAMS + 1 + torch.arange(6)] = 1.0
    accel_k = torch.empty(3, width, batch, dtype=dtype, device=device)
    weighted = torch.empty(N_PARAMS, width, batch, dtype=dtype, device=device)
    # Output batch-major: each step's [3, width, batch] block is transposed while it is in cache
    # (one big transposition at the end cost more than the whole recursion).
    out = torch.empty(batch, n_steps, 3, width, dtype=dtype, device=device)
    vel, disp = state[0:3], state[3:6]
    flat_state = state.view(7, width * batch)
    flat_weighted = weighted.view(N_PARAMS, width * batch)
    flat_accel = accel_k.view(3, width * batch)
    if with_tangents:
        # weighted[j, j+1, :]: where the explicit term ∂a/∂p_j = c_j (primal) is added.
        explicit_slots = weighted.as_strided((N_PARAMS, batch), ((width + 1) * batch, 1), batch)
    for k in range(n_steps):
        state[6, 0] = road_t[k]
        coefficients = torch.mm(coeff, flat_state).view(N_PARAMS, width, batch)  # c = M x
        torch.mul(coefficients, weights, out=weighted)  # p_j c_j (primal and tangents)
        if with_tangents:
            explicit_slots.add_(coefficients[:, 0])
        torch.mm(row_sum, flat_weighted, out=flat_accel)
        if scaled_road:
            accel_k[2, 0] += road_t[k]
        vel.add_(accel_k, alpha=h)
        disp.add_(vel, alpha=h)
        if targets_t is not None:  # the residual, on the [3, batch] primal rows while they are in cache
            accel_k[:, 0].sub_(targets_t[k])
        out[:, k].copy_(accel_k.permute(2, 0, 1))
    return out


class EulerSensitivity(nn.Module):
    """Sensitivity (tangent) version of the semi-explicit Euler layer.

    forward(params [batch, 10], road [batch, time]) -> (accel [batch, time, 3],
    jacobian [batch, time, 3, 10]); identical recursion to ``physics.integrators``.
    """

    def __init__(self, h: float = 0.01, scaled_road: bool = False):
        super().__init__()
        self.h = float(h)
        self.scaled_road = bool(scaled_road)

    def forward(self, params: Tensor, road: Tensor) -> tuple[Tensor, Tensor]:
        return accelerations_and_jacobian(params, road, self.h, self.scaled_road)
