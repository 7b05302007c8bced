"""The initial state's prior: its steady-state distribution under the measured input.

An initial state is a physical state of the system at the window's start: driven by the same input, its
covariance is the steady-state P = Σ_k c_k Re(X_k U_k U_kᴴ X_kᴴ) / T² (below). The occupant selection charges it
in each candidate's evidence (estimation/occupant_evidence.py), and the boundary test of nested models in the fit
(estimation/boundary.py): a body mode whose mass ratio r -> 0 keeps its transient's amplitude r·x0 by an initial
state growing as 1/r, which this prior rules out.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def initial_state_prior(
    response, problem, params: Tensor, x0: Tensor, posterior: Tensor, rows: Tensor | None = None
) -> Tensor:
    """[b] log N(x̂0; 0, P + Σ_x) without its 2π: the initial state's prior integrated against its Gaussian
    posterior (covariance ``posterior`` Σ_x [b, n, n], mean x̂0 = ``x0``; the outputs are linear in x0, so
    this is the exact marginal at the Laplace level). P is the state's covariance in steady state under
    the measured input (Parseval over the window's periodogram, P = Σ_k c_k Re(X_k U_k U_kᴴ X_kᴴ) / T²,
    X_k = (jω_k I − A)⁻¹ B). An initial state is informed by the window's first instants only (its
    transient decays): charging it the unit-information Occam factor ½ log N, as a parameter that every
    sample informs, would penalise a body model's two extra states by ~6 nats and hand light persons to
    the rigid model. ``rows``: the problem's samples that ``params`` are of (default: all)."""
    linear = response.model
    p = params[:, : linear.n_params].double()
    A, B, _, _ = linear.matrices(p)
    inputs = problem.inputs.samples if hasattr(problem.inputs, "samples") else problem.inputs
    inputs = inputs if rows is None else inputs[rows]
    start, n_steps = problem.window
    window = inputs[:, start : start + n_steps].double()
    window = window if window.ndim == 3 else window[..., None]
    U = torch.fft.rfft(window, dim=1).to(torch.complex128)  # [b, K, m]
    omega = 2 * math.pi * torch.fft.rfftfreq(n_steps, d=float(response.h), dtype=torch.float64)
    n = A.shape[-1]
    eye = torch.eye(n, dtype=torch.complex128)
    pencil = (1j * omega)[None, :, None, None] * eye - A.to(torch.complex128)[:, None]
    X = torch.linalg.solve(pencil, B.to(torch.complex128)[:, None] @ U[..., None])  # [b, K, n, 1]
    c = torch.full((omega.numel(),), 2.0, dtype=torch.float64)
    c[0] = 0.0
    if n_steps % 2 == 0:
        c[-1] = 1.0
    P = ((X @ X.conj().transpose(-1, -2)).real * c[None, :, None, None]).sum(1) / n_steps**2  # [b, n, n]
    P = (
        P
        + posterior.double()
        + 1e-12 * P.diagonal(dim1=1, dim2=2).mean(1).clamp_min(1e-300)[:, None, None] * torch.eye(n)
    )
    sign, log_det = torch.linalg.slogdet(P)
    quad = (x0.double()[:, None, :] @ torch.linalg.solve(P, x0.double()[:, :, None]))[:, 0, 0]
    value = -0.5 * log_det - 0.5 * quad
    return torch.where((sign > 0) & torch.isfinite(value), value, torch.full_like(value, -math.inf))
