"""Variable-projection start of the initial state: x0 by linear least squares at a fixed p.

With an unknown initial state the model's outputs are affine in x0 (exact discretisation and
the Euler recursion alike: both are linear state recursions started from x0)::

    y(p, x0) = F(p) + H(p) x0,    F(p) = y(p, 0)  [b, T, o],    H(p) = dy/dx0  [b, T, o, n]

so for a given p the best x0 is a linear least-squares problem,

    x0*(p) = argmin_x0 ½ Σ_{k, c observed} w_c² (y_kc - F_kc(p) - H_kc(p) x0)².

Starting Gauss-Newton from (p0, x0*(p0)) instead of (p0, 0) removes the transient of a window
cut mid-drive (the true x0 is far from rest) from the first iterations' residual; only p's own
error is left there (docs/design/exact_discretisation.md, "x0 start by least squares").

F and H come from ONE sensitivity evaluation of the response model at (p0, x0 = 0): column 0 is
F, the columns after the physical parameters are H. The small problem [b, T·o_obs, n] is solved
in float64 by a column-scaled SVD with a relative cutoff: on short windows or a single output
channel some state directions can be (nearly) unobservable, and there the minimum-norm answer
(0 along the dropped direction: at rest) is what we want. (torch.linalg.lstsq's default CPU
driver returned 0 for a whole rank-deficient system; the SVD cutoff does not.)
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ._host import on_host

X0_STARTS = ("rest", "least_squares", "alternate")  # alternate: see GaussNewtonRefinement


def project_initial_state(
    model,
    theta: Tensor,
    inputs,
    targets: Tensor,
    observed: Sequence[bool],
    weights: Tensor | None = None,
    start: int = 0,
    rcond: float = 1e-10,
    chunk_size: int = 512,
) -> Tensor:
    """θ [b, n_theta] with its initial-state entries replaced by x0*(p) (module docstring).

    model: a response model (estimation.response) whose θ = (p [n_params], x0 [n_theta - n_params]);
    inputs: what drives it, sample-indexed (as the solver passes them); targets [b, T, n_out]
    (unobserved channels never read); observed [n_out] bool; weights [b, n_out] per-channel
    residual weights (None: 1); start: the input sample of the first target. Samples whose
    projection is not finite keep their x0. A model without initial-state entries returns θ.
    """
    n_params, n_theta = int(model.n_params), int(model.n_theta)
    theta = theta.to(torch.float64)
    if n_theta == n_params:
        return theta
    channels = [i for i, o in enumerate(observed) if o]
    if not channels:
        raise ValueError("project_initial_state: observed names no channel")
    at_rest = theta.clone()
    at_rest[:, n_params:] = 0.0
    n_steps = targets.shape[1]
    solutions = []
    for chunk in torch.arange(theta.shape[0]).split(max(1, int(chunk_size))):
        out = model.sensitivities(at_rest[chunk], inputs[chunk], start, n_steps)[:, :, channels]  # [b, T, o, 1 + θ]
        residual = targets[chunk][:, :, channels].to(torch.float64) - out[..., 0]  # y - F(p)   [b, T, o]
        design = out[..., 1 + n_params :]  # H(p)   [b, T, o, n]
        if weights is not None:
            w = weights[chunk][:, channels].to(torch.float64)
            residual = residual * w[:, None, :]
            design = design * w[:, None, :, None]
        b = chunk.numel()
        solutions.append(_min_norm_lstsq(design.reshape(b, -1, n_theta - n_params), residual.reshape(b, -1), rcond))
    x0 = torch.cat(solutions)
    ok = torch.isfinite(x0).all(1)
    result = theta.clone()
    result[:, n_params:] = torch.where(ok[:, None], x0, theta[:, n_params:])
    return result


def _min_norm_lstsq(design: Tensor, rhs: Tensor, rcond: float) -> Tensor:
    """argmin ‖design x - rhs‖ of minimum norm, design [b, r, n], rhs [b, r] -> x [b, n]; columns
    scaled to unit norm first, singular values below rcond·s_max dropped; NaN where the data are not finite.
    Off the CPU on the host's cores (_host.py: cuSOLVER's batched SVD of tall matrices is the slower)."""
    if design.device.type != "cpu":
        return on_host(lambda d, r: _min_norm_lstsq(d, r, rcond), design, rhs, rows=True)
    bad = ~(torch.isfinite(design).all(2).all(1) & torch.isfinite(rhs).all(1))
    design = torch.where(torch.isfinite(design), design, torch.zeros_like(design))
    rhs = torch.where(torch.isfinite(rhs), rhs, torch.zeros_like(rhs))
    scale = design.square().sum(1).sqrt()  # [b, n]
    safe = torch.where(scale > 0, scale, torch.ones_like(scale))
    u, s, vh = torch.linalg.svd(design / safe[:, None, :], full_matrices=False)
    keep = s > rcond * s[:, :1].clamp_min(1e-300)
    inverse = torch.where(keep, 1.0 / s.clamp_min(1e-300), torch.zeros_like(s))
    coefficients = inverse * (u.transpose(1, 2) @ rhs.unsqueeze(2)).squeeze(2)  # [b, n]
    x = (vh.transpose(1, 2) @ coefficients.unsqueeze(2)).squeeze(2) / safe
    return torch.where(bad[:, None], torch.full_like(x, float("nan")), x)
