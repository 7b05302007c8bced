"""Exact discretisation of a continuous-time linear model, with forward-mode sensitivities.

Model (physics.linear_models.LinearModel): dx/dt = A x + B w(t), y = C x + E w, all matrices
functions of p. On the sampling grid t_k = k h (k = 0..T-1), with the input sampled as w_k::

    x_{k+1} = Phi x_k + G_k,      y_k = C x_k + E w_k,      Phi = exp(A h)

where G_k is the exact response over [t_k, t_{k+1}] to the *held* input:

* ``"zoh"``:  w held at w_k:                          G_k = Gamma w_k
* ``"foh"``:  w linear between w_k and w_{k+1}:       G_k = Gamma0 w_k + Gamma1 w_{k+1}
* ``"spline"`` (default): w is the interpolating spline of degree ``spline_degree`` (5, default,
  or 3; not-a-knot end conditions; the cubic falls back to natural for T = 3 and linear for T = 2,
  the quintic to the cubic below 6 samples) through the samples, sampled at m = ``substeps``
  sub-steps per interval (a fixed linear map [(T-1) m + 1, T] for a uniform grid, built once),
  and first-order hold is applied on every sub-step tau = h/m. The m sub-steps fold into one
  step: with (phi, g0, g1) the FOH maps of tau and s_{k,j} = w(t_k + j tau),

      x_{k+1} = phi^m x_k + sum_{j=0..m} Lambda_j s_{k,j},
      Lambda_j = [j < m] phi^(m-1-j) g0 + [j >= 1] phi^(m-j) g1,

  so the time recursion costs the same as FOH.

Windows and margins: the outputs are for the samples start .. start + n_steps - 1 of an input
[b, T_in, m], x0 is the state at sample ``start``, and the spline runs through the samples on both
sides of the window too (up to 64 of them, beyond which their weight is below round-off). A
spline's end conditions are what makes it inaccurate near its ends; with margins the window's
edges are interior points and as accurate as the middle (tests: against continuous time).

Van Loan: for the normalised interval sigma in [0, 1], (x, w, Delta) with Delta = w_1 - w_0
obeys d/dsigma (x, w, Delta) = M (x, w, Delta), M = [[A tau, B tau, 0], [0, 0, I], [0, 0, 0]], so
exp(M) = [[phi, F1, F2], [0, I, I], [0, 0, I]] and x(1) = phi x_0 + F1 w_0 + F2 (w_1 - w_0):
g0 = F1 - F2, g1 = F2 (ZOH: Gamma = F1). ONE exponential per sample gives all three.

Derivatives. With dM_j = dM/dp_j, d exp(M)[dM_j] is the Fréchet derivative, the top-right block
of exp([[M, dM_j], [0, M]]). We compute exactly the same quantity more cheaply by carrying the
tangents through a balanced scaling-and-squaring Taylor evaluation of exp (forward mode: every
product S T becomes (S T, dS T + S dT)); tests compare it with torch.linalg.matrix_exp of the
block matrix and with torch.func.jvp. Only the n state rows of the Van Loan matrix depend on p,
so the tangents carry those rows only. The folding of the sub-steps is differentiated by the
product rule.

Sensitivities. Outputs are linear in x0, so dy_k/dx0 = H_k = C Phi^k (H_{k+1} = H_k Phi). For p:
dx_{k+1} = Phi dx_k + dPhi x_k + sum_j dLambda_j s_{k,j} and dy_k = C dx_k + dC x_k + dE w_k.
exact_sensitivities evaluates these by default in modal coordinates (estimation._modal: per
sample A = V diag(lambda) V^-1, every column a combination of a few scalar sequences per mode, one
small product per sample); the step recursion below (method="recursion") is the reference, and
the fallback for samples with nearly repeated eigenvalues (for up to _STACKED_MAX of them the same
recursion batch first, _stacked_sensitivities). exact_outputs has the same two methods and picks
the faster one for the batch size (method="auto").

Layout. Every per-sample quantity is held batch innermost (matrices [r, c, b], tangents
[r, P, c, b]) and every per-sample product is written as broadcast multiply-adds over contiguous
batch rows: 3.5x faster than torch.bmm over 512 tiny matrices for the exponential's tangent
products, and the only fast form of the per-step recursion. Each step's [o, 1 + P + n, b] block
of the result is transposed (a 2-D transpose, PyTorch's fast path) into the batch-first
[b, T, o, 1 + P + n] result while still in cache. Timings: docs/measurements/exact_discretisation.md.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybridqcm.physics.linear_models import LinearModel

from ._blas import batched_matmul as _matmul
from ._expm import balance, van_loan_maps, van_loan_maps_batch_first
from ._host import on_host
from ._kernels import applies as _compiled_applies
from ._kernels import linear_states as _compiled_states
from ._kernels import tangent_states as _compiled_tangent_states
from ._modal import modal_outputs, modal_sensitivities
from .hold import (
    check_held,
    check_hold_and_window,
    held_window,
    input_forcing,
    input_forcing_batch_first,
    sub_samples,
)

METHODS = ("modal", "recursion")
OUTPUT_METHODS = ("auto",) + METHODS
_DTYPE = torch.float64
# The modal path's fallback takes _stacked_sensitivities up to this many samples (per-sample
# products, ~1 ms + 0.3 ms per quarter car at 16 sub-steps, T = 100), the batch-innermost recursion
# above (~19 ms for any small batch).
_STACKED_MAX = 32
# exact_outputs(method="auto") in torch's ops takes the modal path up to this many samples and the recursion
# above: the modal path costs fewer ops (1.6 vs 3.1 ms for 16 quarter cars, 16 sub-steps, T = 100), but
# its eigen-decompositions (~10 us per sample) make it the slower one from about 190 samples on
# (8.5 vs 6.8 ms for 384). With the compiled loops the recursion is the faster one at every batch size
# (its Van Loan maps and steps are two loops; the modal path keeps LAPACK's eigen-decomposition): 0.48 vs
# 0.94 ms for 1 seat, 1.10 vs 1.48 ms for 16 quarter cars, 14.3 vs 31.6 ms for 1024 (T = 100, 16 sub-steps;
# docs/measurements/roofline.md, eleventh session).
_MODAL_OUTPUTS_MAX = 160


# ----------------------------------------------------------------------------- validation
def _check(
    model,
    params: Tensor,
    x0,
    inputs: Tensor,
    h: float,
    hold: str,
    substeps: int,
    start: int = 0,
    n_steps: int | None = None,
    spline_degree: int = 5,
) -> tuple[Tensor, int]:
    """Validate; return inputs as [b, T_in, m] (a [b, T_in] input is accepted for one-input models)
    and the window length n_steps (default T_in - start)."""
    if not isinstance(model, LinearModel):
        raise ValueError(f"exact: model must be a LinearModel, got {type(model).__name__}")
    if not (isinstance(h, (int, float)) and math.isfinite(h) and h > 0):
        raise ValueError(f"exact: step h must be a finite number > 0, got {h!r}")
    n_params, n, m = model.n_params, model.n_state, model.n_input
    if params.ndim != 2 or params.shape[1] != n_params:
        raise ValueError(f"exact: params must be [batch, {n_params}] for {model.name}, got {tuple(params.shape)}")
    batch = params.shape[0]
    if inputs.ndim == 2 and m == 1:
        inputs = inputs.unsqueeze(-1)
    if inputs.ndim != 3 or inputs.shape[0] != batch or inputs.shape[2] != m or inputs.shape[1] < 1:
        raise ValueError(
            f"exact: inputs must be [batch={batch}, time>=1, {m}] for {model.name}, got {tuple(inputs.shape)}"
        )
    if x0 is not None and (x0.ndim != 2 or x0.shape != (batch, n)):
        raise ValueError(
            f"exact: x0 must be [batch={batch}, {n}] ({', '.join(model.state_names)}) or None, got {tuple(x0.shape)}"
        )
    return inputs, check_hold_and_window(inputs, hold, substeps, start, n_steps, spline_degree)


# ----------------------------------------------------------------------------- recursions
def _primal_states(phi, forcing, x0: Tensor | None, batch: int, n: int, T: int, device) -> Tensor:
    """x_k for k = 0..T-1 as [T, n, b] (batch innermost). phi [n, n, b], forcing [T-1, n, b]."""
    states = torch.empty(T, n, batch, dtype=_DTYPE, device=device)
    if x0 is None:
        states[0].zero_()
    else:
        states[0].copy_(x0.t())
    if T == 1:
        return states
    if _compiled_applies(phi):  # the same steps compiled (_kernels.py)
        _compiled_states(phi, forcing, states)
        return states
    phi_cols = phi.permute(1, 0, 2).contiguous().unbind(0)  # column l of every Phi, [i, b]
    rows = states.unbind(0)
    for k in range(T - 1):
        nxt, cur = rows[k + 1], rows[k].unbind(0)
        nxt.copy_(forcing[k])  # (addcmul with out= is 5x slower than copy + in place)
        for l in range(n):
            nxt.addcmul_(phi_cols[l], cur[l])
    return states


def _outputs_inner(states: Tensor, window: Tensor, C: Tensor, E: Tensor) -> Tensor:
    """y_k = C x_k + E w_k as [T, o, b]: states [T, n, b], window [b, T, m], C [b, o, n], E [b, o, m]."""
    c_cols, e_cols = C.permute(2, 1, 0).contiguous(), E.permute(2, 1, 0).contiguous()  # [l, o, b]
    w = window.permute(2, 1, 0)  # [c, T, b]
    y = states[:, 0, None, :] * c_cols[0]
    for l in range(1, C.shape[2]):
        y.addcmul_(states[:, l, None, :], c_cols[l])
    for c in range(E.shape[2]):
        y.addcmul_(w[c][:, None, :], e_cols[c])
    return y


def _prepare(model, params, x0, inputs, h, hold, substeps, start, n_steps, spline_degree):
    inputs, n_steps = _check(model, params, x0, inputs, h, hold, substeps, start, n_steps, spline_degree)
    inputs = inputs.to(_DTYPE)
    params = params.to(_DTYPE)
    x0 = None if x0 is None else x0.to(_DTYPE)
    return params, x0, inputs, int(start), n_steps


def _held(held, inputs, hold, substeps, start, T, spline_degree, window: bool = True):
    """The held input of the window (hold.held_window's layout): ``held`` checked against the inputs, then cast, or
    made from the inputs where None; with ``window`` False only checked (a one-step output needs none)."""
    check_held(held, inputs, hold, substeps, T)
    if not window:
        return held
    return held_window(inputs, hold, substeps, start, T, spline_degree) if held is None else held.to(_DTYPE)


@torch.no_grad()
def exact_outputs(
    model: LinearModel,
    params: Tensor,
    x0: Tensor | None,
    inputs: Tensor,
    h: float,
    hold: str = "spline",
    substeps: int = 4,
    start: int = 0,
    n_steps: int | None = None,
    spline_degree: int = 5,
    held: Tensor | None = None,
    method: str = "auto",
) -> Tensor:
    """params [b, P], x0 [b, n] (None = rest), inputs [b, T_in, m] -> y [b, n_steps, o] (float64).

    The outputs are for the samples start .. start + n_steps - 1 (n_steps default T_in - start) and
    x0 is the state at sample ``start`` in the model's state coordinates. The spline hold
    interpolates all T_in samples, so samples outside the window (margins) make the held input
    near the window's edges as accurate as inside it. ``held``: held_input of the same inputs and
    window, if the caller has it (the same result, without recomputing it). ``method``: "modal"
    (as in exact_sensitivities: a few hundred ops per call where the recursion takes about a
    thousand, which is what a line search's small batches cost in torch), "recursion", or "auto" (default:
    whichever is faster: the recursion where the compiled loops run, else by the batch size, _MODAL_OUTPUTS_MAX);
    they agree to round-off.
    """
    if method not in OUTPUT_METHODS:
        raise ValueError(f"exact: unknown method {method!r}; choose one of {OUTPUT_METHODS}")
    params, x0, inputs, start, T = _prepare(model, params, x0, inputs, h, hold, substeps, start, n_steps, spline_degree)
    held = _held(held, inputs, hold, substeps, start, T, spline_degree, window=T > 1)
    if method == "auto":
        small = params.shape[0] <= _MODAL_OUTPUTS_MAX and not _compiled_applies(params)
        method = "modal" if small else "recursion"
    if method == "recursion" or T == 1:
        return _recursion_outputs(model, params, x0, inputs, h, hold, substeps, start, T, held)
    A, B, C, E = model.matrices(params)
    out, ok = modal_outputs((A, B, C, E), balance(A), x0, held.permute(2, 1, 0), inputs[:, start : start + T], h, hold)
    if not bool(ok.all()):
        bad = (~ok).nonzero()[:, 0]
        out[bad] = _recursion_outputs(
            model,
            params[bad],
            None if x0 is None else x0[bad],
            inputs[bad],
            h,
            hold,
            substeps,
            start,
            T,
            held[..., bad],
        )
    return out


def _recursion_outputs(model, params, x0, inputs, h, hold, substeps, start, T, held) -> Tensor:
    """exact_outputs by the step recursion (validated float64 arguments, held from held_window; None for T = 1)."""
    batch = inputs.shape[0]
    _, _, C, E = model.matrices(params)
    if T > 1:
        phi, lam = van_loan_maps(model, params, h, hold, substeps, False)
        if held.stride(2) != 1 and held.stride(0) == 1:  # stored batch first (PreparedInputs)
            forcing = input_forcing_batch_first(lam, held, T)  # [T-1, n, b]
        else:
            forcing = input_forcing(lam, sub_samples(held, T))
    else:
        phi, forcing = None, None
    states = _primal_states(phi, forcing, x0, batch, model.n_state, T, params.device)
    y = _outputs_inner(states, inputs[:, start : start + T], C, E)  # [T, o, b]
    return y.view(T * model.n_output, batch).t().contiguous().view(batch, T, model.n_output)  # 2-D transpose


@torch.no_grad()
def exact_sensitivities(
    model: LinearModel,
    params: Tensor,
    x0: Tensor | None,
    inputs: Tensor,
    h: float,
    hold: str = "spline",
    substeps: int = 4,
    with_x0: bool = True,
    start: int = 0,
    n_steps: int | None = None,
    spline_degree: int = 5,
    method: str = "modal",
    held: Tensor | None = None,
    defer_fallback: bool = False,
    targets: Tensor | None = None,
) -> Tensor | tuple[Tensor, Tensor]:
    """Prediction and Jacobian in one forward pass.

    -> [b, n_steps, o, 1 + P (+ n if with_x0)]: [..., 0] the prediction, [..., 1 + j] = dy/dp_j,
    [..., 1 + P + i] = dy/dx0_i (x0 = the state at sample ``start``). Window and margins as in
    exact_outputs. Same layout convention as euler_sensitivities ([b, T, 3, 11]).

    ``method``: "modal" (default) evaluates the same quantities in eigen-coordinates of A, one
    small matrix product per sample (estimation._modal; samples with nearly repeated eigenvalues
    or ill-conditioned eigenvectors go to the recursion); "recursion" runs the step recursion
    below for every sample. They agree to round-off (tests/test_exact.py). ``held`` as in exact_outputs.
    ``defer_fallback``: return (result, rows) instead, rows [r] the samples that the modal path left to the
    recursion, whose result rows are not valid: the caller evaluates them with fallback_sensitivities,
    gathered over many calls (its cost is mostly per call: ~15 % of a chunk of 512 for its ~8 such samples).
    ``targets`` [b, n_steps, o]: column 0 is the residual y - targets instead of y (the modal path
    subtracts them inside its final product, which saves a pass over the result).
    """
    if method not in METHODS:
        raise ValueError(f"exact: unknown method {method!r}; choose one of {METHODS}")
    params, x0, inputs, start, T = _prepare(model, params, x0, inputs, h, hold, substeps, start, n_steps, spline_degree)
    held = _held(held, inputs, hold, substeps, start, T, spline_degree)
    if method == "recursion" or T == 1:
        out = _recursion_sensitivities(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held)
        if targets is not None:
            out[..., 0] -= targets
        return (out, torch.zeros(0, dtype=torch.long, device=out.device)) if defer_fallback else out
    A, B, C, E = model.matrices(params)
    out, ok = modal_sensitivities(
        (A, B, C, E),
        model.matrix_derivatives(params),
        balance(A),
        x0,
        held.permute(2, 1, 0),
        inputs[:, start : start + T],
        h,
        hold,
        with_x0,
        None if targets is None else targets.to(_DTYPE),
    )
    bad = (~ok).nonzero()[:, 0]
    if defer_fallback:
        return out, bad
    if bad.numel():
        fixed = _fallback(
            model,
            params[bad],
            None if x0 is None else x0[bad],
            inputs[bad],
            h,
            hold,
            substeps,
            with_x0,
            start,
            T,
            held[..., bad],
        )
        if targets is not None:
            fixed[..., 0] -= targets[bad]
        out[bad] = fixed
    return out


def _fallback(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held) -> Tensor:
    """The step recursion for the samples the modal path leaves: stacked for a few, batch-innermost above;
    on the host for a batch on another device (a few samples' T steps: one compiled loop there, _host.py)."""
    if params.device.type != "cpu":
        return on_host(
            lambda p, x, w, d: _fallback(model, p, x, w, h, hold, substeps, with_x0, start, T, d),
            params,
            x0,
            inputs,
            held,
        )
    fallback = _stacked_sensitivities if params.shape[0] <= _STACKED_MAX else _recursion_sensitivities
    return fallback(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held)


@torch.no_grad()
def fallback_sensitivities(
    model: LinearModel,
    params: Tensor,
    x0: Tensor | None,
    inputs: Tensor,
    h: float,
    hold: str = "spline",
    substeps: int = 4,
    with_x0: bool = True,
    start: int = 0,
    n_steps: int | None = None,
    spline_degree: int = 5,
    held: Tensor | None = None,
) -> Tensor:
    """exact_sensitivities by the step recursion alone (the rows that ``defer_fallback`` left), with the
    variant for the batch size that the modal path's own fallback takes; same arguments and result."""
    params, x0, inputs, start, T = _prepare(model, params, x0, inputs, h, hold, substeps, start, n_steps, spline_degree)
    held = _held(held, inputs, hold, substeps, start, T, spline_degree)
    if T == 1:
        return _recursion_sensitivities(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held)
    return _fallback(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held)


def _stacked_sensitivities(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held) -> Tensor:
    """exact_sensitivities by the same step recursion as _recursion_sensitivities, for a few samples
    (the modal path's fallback, up to _STACKED_MAX). The state and its tangents are one matrix per
    sample, X_k = [x_k | dx_k/dp | dx_k/dx0] [n, 1 + P (+ n)], and a step is

        X_{k+1} = Phi X_k + [G_k | dPhi_j x_k + dG_k | 0],   G_k = sum_j Lam_j s_{k,j},

    with G and dG for all k from one product before the loop and the maps from
    van_loan_maps_batch_first: 3 ops per step instead of ~50, which is what a handful of samples costs
    (their arithmetic is negligible)."""
    batch, n, n_params, m = params.shape[0], model.n_state, model.n_params, model.n_input
    _, _, C, E = model.matrices(params)
    _, _, dC, dE = model.matrix_derivatives(params)
    n_col = 1 + n_params + (n if with_x0 else 0)
    X = torch.zeros(T, batch, n, n_col, dtype=_DTYPE, device=params.device)  # [k, b, i, column]
    if x0 is not None:
        X[0, :, :, 0] = x0
    if with_x0:
        X[0, :, :, 1 + n_params :] = torch.eye(n, dtype=_DTYPE, device=params.device)
    if T > 1:
        phi, lam, dphi, dlam = van_loan_maps_batch_first(model, params, h, hold, substeps)
        m_sub = lam.shape[1] - 1
        # s [b, T-1, (j, c)] and the weights [b, (j, c), (i, q)] of G (q = 0) and dG_p (q = 1 + p)
        s = sub_samples(held, T).permute(3, 2, 0, 1).reshape(batch, T - 1, (m_sub + 1) * m)
        weights = torch.cat([lam[:, None], dlam], 1)  # [b, q, j, i, c]
        weights = weights.permute(0, 2, 4, 3, 1).reshape(batch, (m_sub + 1) * m, n * (1 + n_params))
        forcing = _matmul(s, weights).view(batch, T - 1, n * (1 + n_params), 1).transpose(0, 1).contiguous()
        # dPhi as [b, (i, q), l] with zero rows for q = 0: dPhi x_k lands in the tangent columns
        dphi_q = torch.zeros(batch, n, 1 + n_params, n, dtype=_DTYPE, device=params.device)
        dphi_q[:, :, 1:] = dphi.transpose(1, 2)
        if _compiled_applies(X):  # the same steps compiled (_kernels.py)
            _compiled_tangent_states(phi, forcing.view(T - 1, batch, n, 1 + n_params), dphi_q, X)
        else:
            dphi_q = dphi_q.view(batch, n * (1 + n_params), n)
            for k in range(T - 1):  # torch.bmm: for a few samples its per-call cost is the lowest (3 us)
                torch.bmm(phi, X[k], out=X[k + 1])
                X[k + 1, ..., : 1 + n_params] += torch.baddbmm(forcing[k], dphi_q, X[k, ..., :1]).view(
                    batch, n, 1 + n_params
                )
    # y_k = C x_k + E w_k, dy_k/dp = C dx_k + dC x_k + dE w_k, dy_k/dx0 = C dx_k/dx0: all k at once
    states = X.transpose(0, 1)  # [b, T, n, column]
    window = inputs[:, start : start + T]  # [b, T, m]
    out = torch.einsum("bon,btnc->btoc", C, states)  # [b, T, o, column]
    out[..., 0] += torch.einsum("bom,btm->bto", E, window)
    out[..., 1 : 1 + n_params] += torch.einsum("bpon,btn->btop", dC, states[..., 0]) + torch.einsum(
        "bpom,btm->btop", dE, window
    )
    return out


def _recursion_sensitivities(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held) -> Tensor:
    """exact_sensitivities by the step recursion (validated float64 arguments, held from held_window)."""
    batch = inputs.shape[0]
    n, o, n_params, n_in = model.n_state, model.n_output, model.n_params, model.n_input
    _, _, C, E = model.matrices(params)
    _, _, dC, dE = model.matrix_derivatives(params)
    window = inputs[:, start : start + T]
    if T > 1:
        phi, lam, dphi, dlam = van_loan_maps(model, params, h, hold, substeps, True)  # batch innermost
        s = sub_samples(held, T)
        forcing = input_forcing(lam, s)  # [T-1, n, b]
    else:
        phi = forcing = None
    states = _primal_states(phi, forcing, x0, batch, n, T, params.device)
    primal = _outputs_inner(states, window, C, E)  # [T, o, b]

    # dy_k/dp = C dx_k + dC x_k + dE w_k with dx_{k+1} = Phi dx_k + dPhi x_k + sum_j dLam_j s_{k,j},
    # and dy_k/dx0 = H_k = C Phi^k, H_{k+1} = H_k Phi: [i, j, b] blocks with per-sample scalars,
    # multiply-adds on data that stays in cache. Each step's [o, 1 + P + n, b] block is transposed
    # into the batch-first result while it is still in cache (one transposition of the whole result
    # at the end costs 3x more).
    n_col = 1 + n_params + (n if with_x0 else 0)
    out = torch.empty(batch, T, o, n_col, dtype=_DTYPE, device=params.device)
    out_rows = out.view(batch, T, o * n_col)
    dc_cols = dC.permute(3, 2, 1, 0).contiguous().unbind(0)  # [l][o, j, b]
    de_cols = dE.permute(3, 2, 1, 0).contiguous().unbind(0)  # [c][o, j, b]
    w_rows = window.permute(1, 2, 0).contiguous()  # [T, c, b]
    x_rows = states.unbind(0)
    blocks = [torch.empty(o, n_col, batch, dtype=_DTYPE, device=params.device) for _ in range(2)]  # ping-pong
    if with_x0:
        blocks[1][:, 1 + n_params :] = C.permute(1, 2, 0)  # H_0, moved to blocks[0] at k = 0 below
    if T > 1:
        phi_rows = phi.unbind(0)  # [l][j, b]: row l of every Phi
        phi_cols = phi.permute(1, 0, 2)[:, :, None, :].contiguous().unbind(0)  # [l][i, 1, b]
        dphi_cols = dphi.permute(2, 0, 1, 3).contiguous().unbind(0)  # [l][i, j, b]
        dlam_t = dlam.permute(0, 3, 1, 2, 4).contiguous()  # [q, c, i, j, b]
        c_cols = C.permute(2, 1, 0)[:, :, None, :].contiguous().unbind(0)  # [l][o, 1, b]
        forcing_terms = [(dlam_t[q, c], s[q, c]) for q in range(s.shape[0]) for c in range(n_in)]
    explicit = None
    if dC.stride(0) == 0 and dE.stride(0) == 0:  # the same dC, dE for every sample: one GEMM for all k
        coef = torch.cat([dC[0], dE[0]], -1).permute(1, 0, 2).reshape(o * n_params, n + n_in)  # [(o, j), l]
        xw = torch.cat([states, w_rows], 1).permute(1, 0, 2).reshape(n + n_in, T * batch)
        explicit = torch.mm(coef, xw).view(o, n_params, T, batch)
    z = torch.zeros(n, n_params, batch, dtype=_DTYPE, device=params.device)  # dx_k/dp, [i, j, b]
    z_next = torch.empty_like(z)
    for k in range(T):
        block, previous = blocks[k % 2], blocks[(k + 1) % 2]
        block[:, 0] = primal[k]
        tangent = block[:, 1 : 1 + n_params]
        if k:
            x_prev, z_rows = x_rows[k - 1].unbind(0), z.unbind(0)
            torch.mul(dphi_cols[0], x_prev[0], out=z_next)
            for l in range(1, n):
                z_next.addcmul_(dphi_cols[l], x_prev[l])
            for l in range(n):
                z_next.addcmul_(phi_cols[l], z_rows[l])
            for weight, samples in forcing_terms:
                z_next.addcmul_(weight, samples[k - 1])
            z, z_next = z_next, z
        if explicit is not None:
            tangent.copy_(explicit[:, :, k])
        else:
            x_k, w_k = x_rows[k].unbind(0), w_rows[k].unbind(0)
            torch.mul(dc_cols[0], x_k[0], out=tangent)
            for l in range(1, n):
                tangent.addcmul_(dc_cols[l], x_k[l])
            for c in range(n_in):
                tangent.addcmul_(de_cols[c], w_k[c])
        if k:
            z_rows = z.unbind(0)
            for l in range(n):
                tangent.addcmul_(c_cols[l], z_rows[l])
        if with_x0:
            H, H_prev = block[:, 1 + n_params :], previous[:, 1 + n_params :]
            if k:
                torch.mul(H_prev[:, 0, None, :], phi_rows[0], out=H)
                for l in range(1, n):
                    H.addcmul_(H_prev[:, l, None, :], phi_rows[l])
            else:
                H.copy_(H_prev)
        out_rows[:, k] = block.view(o * n_col, batch).t().contiguous()  # 2-D copies: PyTorch's fast paths
    return out
