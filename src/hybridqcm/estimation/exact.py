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
import numbers
from functools import lru_cache

import torch
from torch import Tensor

from hybridqcm.physics.linear_models import LinearModel

from ._blas import batched_matmul as _matmul
from ._modal import modal_outputs, modal_sensitivities

HOLDS = ("spline", "foh", "zoh")
METHODS = ("modal", "recursion")
OUTPUT_METHODS = ("auto",) + METHODS
SPLINE_DEGREES = (3, 5, 7)  # 7: for inputs with content near a quarter of the sampling rate (stiff tyres)
_DTYPE = torch.float64
# Taylor degree 11 on ||X||_1 <= 1/4: truncation error <= 0.25^12/12! * e^0.25 < 2e-16 relative.
_TAYLOR_THETA = 0.25
_TAYLOR_DEGREE = 11
# The modal path's fallback takes _stacked_sensitivities up to this many samples (per-sample
# products, ~1 ms + 0.3 ms per quarter car at 16 sub-steps, T = 100), the batch-innermost recursion
# above (~19 ms for any small batch).
_STACKED_MAX = 32
# exact_outputs(method="auto") takes the modal path up to this many samples and the recursion above:
# the modal path costs fewer ops (1.6 vs 3.1 ms for 16 quarter cars, 16 sub-steps, T = 100), but
# its eigen-decompositions (~10 us per sample) make it the slower one from about 190 samples on
# (8.5 vs 6.8 ms for 384).
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
    return inputs, _check_hold_and_window(inputs, hold, substeps, start, n_steps, spline_degree)


def _check_hold_and_window(
    inputs: Tensor, hold: str, substeps: int, start: int, n_steps: int | None, spline_degree: int
) -> int:
    """Validate the hold settings and the window of inputs [b, T_in, m]; return n_steps (default T_in - start)."""
    if hold not in HOLDS:
        raise ValueError(f"exact: unknown hold {hold!r}; choose one of {HOLDS}")
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ValueError(f"exact: substeps must be an integer >= 1, got {substeps!r}")
    if spline_degree not in SPLINE_DEGREES:
        raise ValueError(f"exact: spline_degree must be one of {SPLINE_DEGREES}, got {spline_degree!r}")
    n_in = inputs.shape[1]
    if isinstance(start, bool) or not isinstance(start, numbers.Integral) or not 0 <= start < n_in:
        raise ValueError(f"exact: start must be an integer in [0, {n_in}) for {n_in} input samples, got {start!r}")
    if n_steps is None:
        n_steps = n_in - start
    if isinstance(n_steps, bool) or not isinstance(n_steps, numbers.Integral) or not 1 <= n_steps <= n_in - start:
        raise ValueError(
            f"exact: n_steps must be an integer in [1, {n_in - start}] (start={start}, "
            f"{n_in} input samples), got {n_steps!r}"
        )
    return int(n_steps)


# ----------------------------------------------------------------------------- input hold
@lru_cache(maxsize=32)
def _spline_matrix_cached(n_samples: int, substeps: int, degree: int) -> Tensor:
    if degree == 3 or n_samples < degree + 1:  # too few samples for degree 5: the cubic below
        return _cubic_spline_matrix(n_samples, substeps)
    import numpy as np
    from scipy.interpolate import make_interp_spline

    # B-spline of odd degree k interpolating the identity: knots at the samples with (k-1)/2 interior
    # knots dropped at each end (not-a-knot), so column i is the spline through the unit vector e_i
    T = n_samples
    grid = np.arange(T, dtype=np.float64)
    fine = np.arange((T - 1) * substeps + 1, dtype=np.float64) / substeps
    matrix = make_interp_spline(grid, np.eye(T), k=degree)(fine)
    matrix[::substeps] = np.eye(T)  # at the knots the spline is the sample itself (removes round-off)
    return torch.from_numpy(np.ascontiguousarray(matrix)).to(_DTYPE)


def _cubic_spline_matrix(T: int, m: int) -> Tensor:
    """The not-a-knot cubic spline (natural for T = 3, linear for T <= 2) at m sub-steps per interval."""
    eye = torch.eye(T, dtype=_DTYPE)
    if T < 3:  # one interval at most: the spline is the straight line
        second = torch.zeros(T, T, dtype=_DTYPE)
    else:
        # second derivatives M (in units of 1/h^2): interior M_{i-1} + 4 M_i + M_{i+1} = 6 (y_{i-1} - 2 y_i + y_{i+1})
        lhs = torch.zeros(T, T, dtype=_DTYPE)
        rhs = torch.zeros(T, T, dtype=_DTYPE)
        for i in range(1, T - 1):
            lhs[i, i - 1 : i + 2] = torch.tensor([1.0, 4.0, 1.0], dtype=_DTYPE)
            rhs[i] = 6 * (eye[i - 1] - 2 * eye[i] + eye[i + 1])
        if T >= 4:  # not-a-knot: third derivative continuous at t_1 and t_{T-2}
            lhs[0, :3] = torch.tensor([1.0, -2.0, 1.0], dtype=_DTYPE)
            lhs[-1, -3:] = torch.tensor([1.0, -2.0, 1.0], dtype=_DTYPE)
        else:  # T = 3: not-a-knot is degenerate there; natural ends M_0 = M_2 = 0
            lhs[0, 0] = lhs[-1, -1] = 1.0
        second = torch.linalg.solve(lhs, rhs)  # [T, T]: M = second @ y
    theta = torch.arange(m, dtype=_DTYPE) / m  # sub-sample positions in an interval (the last comes next)
    a, c = 1 - theta, theta
    w_lin = torch.stack([a, c], -1)  # weights of y_i, y_{i+1}
    w_cub = torch.stack([(a**3 - a) / 6, (c**3 - c) / 6], -1)  # weights of M_i, M_{i+1}
    rows = []
    for i in range(T - 1):
        rows.append(
            w_lin[:, :1] * eye[i] + w_lin[:, 1:] * eye[i + 1] + w_cub[:, :1] * second[i] + w_cub[:, 1:] * second[i + 1]
        )
    rows.append(eye[T - 1 : T])
    return torch.cat(rows)


def spline_matrix(n_samples: int, substeps: int, degree: int = 5) -> Tensor:
    """[(T-1) m + 1, T] map from T uniform samples to the interpolating spline of odd ``degree``
    (3, 5 or 7, not-a-knot end conditions) at m sub-steps per interval (row k m + j is t_k + j h/m).
    Degree 5 is scipy's make_interp_spline(k=5) applied to the identity; with fewer than 6 samples
    it falls back to the cubic, which is natural for T = 3 and linear for T <= 2. Cached per (T, m, k).
    A spline of degree k reproduces polynomials of degree <= k exactly."""
    return _spline_matrix_cached(int(n_samples), int(substeps), int(degree))


# Input samples further than this from the window are not used by the spline hold: an interpolating
# spline's weights decay geometrically with the distance, 0.43^d for the quintic and 0.27^d for the
# cubic, so they weigh < 1e-23 there (the spline over the samples actually used differs from the one
# over all T_in samples, end conditions included, below round-off), and the cost of a window does
# not grow with the length of the recording.
_SPLINE_REACH = 64


@lru_cache(maxsize=64)
def _window_spline(n_local: int, substeps: int, degree: int, start: int, n_steps: int) -> Tensor:
    """Rows of spline_matrix(n_local, substeps, degree) for the fine samples of the window
    start .. start + n_steps - 1, [(n_steps - 1) m + 1, n_local]."""
    rows = spline_matrix(n_local, substeps, degree)[start * substeps : (start + n_steps - 1) * substeps + 1]
    return rows.contiguous()


def _bands(n_fine: int, n_local: int, m_sub: int, start: int, steps: int = 64):
    """Blocks (r0, r1, c0, c1) of a window's spline matrix [n_fine, n_local] that hold all its
    weights above round-off: fine rows of `steps` samples at a time, against the input samples
    within _SPLINE_REACH of them (the rest weigh < 1e-23, see _SPLINE_REACH). A long window then
    costs O(T) instead of the O(T^2) of the dense product."""
    blocks = []
    for r0 in range(0, n_fine, steps * m_sub):
        r1 = min(n_fine, r0 + steps * m_sub)
        c0 = max(0, start + r0 // m_sub - _SPLINE_REACH)
        c1 = min(n_local, start + (r1 - 1) // m_sub + 2 + _SPLINE_REACH)
        blocks.append((r0, r1, c0, c1))
    return blocks


def _held(inputs: Tensor, hold: str, substeps: int, start: int, n_steps: int, degree: int = 5) -> Tensor:
    """inputs [b, T_in, m] -> held [M + (n_steps - 1) M + 1, m, b] (time first, batch innermost): M
    zero rows, then the held input at the sub-steps of the window (M = substeps for "spline", 1
    otherwise): the spline through the samples (all of them up to _SPLINE_REACH beyond each end of
    the window) for "spline", the samples themselves otherwise. The leading zeros let
    estimation._modal read step k - 1's sub-samples as row k of one strided view."""
    batch, n_in, n_ch = inputs.shape
    m_sub = substeps if hold == "spline" else 1
    out = inputs.new_zeros(m_sub + (n_steps - 1) * m_sub + 1, n_ch * batch)
    if m_sub > 1:
        lo, hi = max(0, start - _SPLINE_REACH), min(n_in, start + n_steps + _SPLINE_REACH)
        weights = _window_spline(hi - lo, m_sub, degree, start - lo, n_steps).to(inputs.device)
        columns = inputs[:, lo:hi].permute(1, 2, 0).reshape(hi - lo, n_ch * batch)  # [T, (c, b)]
        fine = out[m_sub:]
        for r0, r1, c0, c1 in _bands(weights.shape[0], hi - lo, m_sub, start - lo):
            torch.mm(weights[r0:r1, c0:c1], columns[c0:c1], out=fine[r0:r1])
    else:
        out[1:] = inputs[:, start : start + n_steps].permute(1, 2, 0).reshape(n_steps, n_ch * batch)
    return out.view(-1, n_ch, batch)


def _sub_samples(held: Tensor, n_steps: int) -> Tensor:
    """held [M + (n_steps - 1) M + 1, m, b] (_held) -> s [M + 1, m, n_steps - 1, b], a strided view:
    s[j, c, k] = w_c(t_{start+k} + j h/M)."""
    width, n_ch, batch = held.shape
    m_sub = (width - 1) // n_steps
    if held.stride(2) != 1:  # a batch-first chunk (PreparedInputs): the recursion reads batch rows
        held = held.contiguous()
    st, sc, sb = held.stride()
    return held[m_sub:].as_strided((m_sub + 1, n_ch, n_steps - 1, batch), (st, sc, m_sub * st, sb))


def held_input(
    inputs: Tensor,
    hold: str = "spline",
    substeps: int = 4,
    start: int = 0,
    n_steps: int | None = None,
    spline_degree: int = 5,
) -> Tensor:
    """The held input of a window, [M + (n_steps - 1) M + 1, m, b] (time first, batch innermost; M =
    substeps for "spline", else 1, and M leading zero rows): what exact_outputs and
    exact_sensitivities compute from ``inputs`` [b, T_in, m] at every call. It does not depend on the
    parameters, so an iterative solver computes it once per window and passes it back as ``held=``
    (for the spline hold it is about a third of an output evaluation's cost); a subset of samples is
    ``held[..., index]``, and any strides are accepted (e.g. a permuted batch-first copy)."""
    if inputs.ndim != 3 or inputs.shape[1] < 1:
        raise ValueError(f"exact: inputs must be [batch, time>=1, n_in], got {tuple(inputs.shape)}")
    n_steps = _check_hold_and_window(inputs, hold, substeps, start, n_steps, spline_degree)
    return _held(inputs.to(_DTYPE), hold, substeps, int(start), n_steps, spline_degree)


def _check_held(held: Tensor | None, inputs: Tensor, hold: str, substeps: int, n_steps: int) -> None:
    m_sub = substeps if hold == "spline" else 1
    shape = (m_sub + (n_steps - 1) * m_sub + 1, inputs.shape[2], inputs.shape[0])
    if held is not None and tuple(held.shape) != shape:
        raise ValueError(f"exact: held input must be {list(shape)} (held_input of this window), got {list(held.shape)}")


def _forcing_batch_first(lam: Tensor, held: Tensor, n_steps: int) -> Tensor:
    """_forcing(lam, _sub_samples(held, n_steps)) for a held input stored batch first (``held`` [W, m, b]
    a permuted view of [b, m, W] with W = M + (n_steps - 1) M + 1, e.g. PreparedInputs): per sample and
    input channel, the sub-samples of step k are row k of the non-overlapping [n_steps - 1, M] view
    (j = 0..M-1) plus the next row's first (j = M), so G = S Lam is one bmm of views and the
    time-first copy is of the forcing [T-1, n, b] instead of the M-times larger held input."""
    width, n_in, batch = held.shape
    m_sub = (width - 1) // n_steps
    by_sample = held.permute(2, 1, 0)  # [b, m, W]
    lam_b = lam.permute(2, 3, 0, 1)  # [m, b, M + 1, n]
    forcing = None
    for c in range(n_in):
        rows = by_sample[:, c, m_sub : m_sub + (n_steps - 1) * m_sub].unflatten(1, (n_steps - 1, m_sub))
        last = by_sample[:, c, 2 * m_sub :: m_sub]  # s_{k, M} = s_{k+1, 0}, [b, T - 1]
        weights = lam_b[c].contiguous()  # [b, M + 1, n]
        term = _matmul(rows, weights[:, :m_sub]).addcmul_(last[:, :, None], weights[:, m_sub : m_sub + 1])
        forcing = term if forcing is None else forcing.add_(term)
    return forcing.permute(1, 2, 0).contiguous()  # [T-1, n, b]


def _forcing(lam: Tensor, s: Tensor) -> Tensor:
    """G_k = sum_j Lam_j s_{k,j} as [T-1, n, b]; lam [m_sub+1, n, m, b], s from _sub_samples."""
    lam_t = lam.permute(0, 2, 1, 3).contiguous()  # [j, c, i, b]
    n_sub, n_in = s.shape[:2]
    forcing = torch.empty(s.shape[2], lam.shape[1], s.shape[3], dtype=_DTYPE, device=lam.device)
    torch.mul(s[0, 0][:, None, :], lam_t[0, 0], out=forcing)
    for j in range(n_sub):
        for c in range(n_in):
            if j or c:
                forcing.addcmul_(s[j, c][:, None, :], lam_t[j, c])
    return forcing


# ----------------------------------------------------------------------------- matrix exponential
# Everything per sample is held batch innermost: a matrix S as [r, c, b], its tangents in the P
# directions as dS [r', P, c, b]. A product of per-sample matrices is then k broadcast multiply-adds
# over contiguous [.., b] rows (3.5x faster than bmm over 512 tiny matrices, notes/estimation.md).
def _iprod(S: Tensor, dS: Tensor | None, T: Tensor, dT: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """(S T, dS T + S dT) batch innermost: S [r, k, b], T [k, c, b], dS [r', P, k, b], dT [k', P, c, b].

    Tangents may keep only their first rows (r' <= r, k' <= k: the rest are zero); the result's
    tangent then has r' rows, which is exact when S[r':, :k'] = 0 (block upper triangular, as for
    the Van Loan matrices, whose tangents live in the n state rows)."""
    k = S.shape[1]
    out = S[:, 0, None, :] * T[0]
    for l in range(1, k):
        out.addcmul_(S[:, l, None, :], T[l])
    if dS is None and dT is None:
        return out, None
    if dS is not None:
        dout = dS[:, :, 0, None, :] * T[0]
        for l in range(1, k):
            dout.addcmul_(dS[:, :, l, None, :], T[l])
    if dT is not None:
        S_top = S[: dT.shape[0] if dS is None else dS.shape[0]]
        if dS is None:
            dout = S_top[:, 0, None, None, :] * dT[0]
        for l in range(0 if dS is not None else 1, dT.shape[0]):
            dout.addcmul_(S_top[:, l, None, None, :], dT[l])
    return out, dout


def _balance(M: Tensor, sweeps: int = 2, damping: float = 0.35) -> Tensor:
    """Diagonal scaling d [b, N] (powers of two, so exact) making row and column norms of
    diag(d)^-1 M diag(d) comparable; it shrinks ||M|| (hence the squarings) for the quarter car,
    whose A mixes 1/s and 1/s^2 entries. exp(D^-1 M D) = D^-1 exp(M) D for any fixed D, so the
    scaling changes no result, only the cost. M [b, N, N].

    All indices are updated at once (damped: the undamped simultaneous update oscillates), a few
    vector operations instead of Osborne's index-by-index sweeps; for the quarter-car Van Loan
    matrices it needs the same number of squarings (one at tau = h/4)."""
    N = M.shape[-1]
    off = (M.abs() * (1 - torch.eye(N, dtype=M.dtype, device=M.device))).contiguous()
    log_d = torch.zeros(M.shape[:-1], dtype=M.dtype, device=M.device)
    for _ in range(sweeps):
        d = torch.exp2(log_d)
        scaled = off * d[:, None, :] / d[:, :, None]
        col, row = scaled.sum(-2), scaled.sum(-1)
        ok = (col > 0) & (row > 0)
        log_d += damping * torch.log2(torch.where(ok, row / torch.where(ok, col, 1.0), 1.0))
    return torch.exp2(torch.round(log_d))


def expm_with_tangents(M: Tensor, dM: Tensor) -> tuple[Tensor, Tensor]:
    """exp(M) [b, N, N] and its Fréchet derivatives d exp(M)[dM_j] for dM [b, P, N, N] -> [b, P, N, N]."""
    F, dF = _expm_inner(M.permute(1, 2, 0), dM.permute(2, 1, 3, 0))
    return F.permute(2, 0, 1), dF.permute(3, 1, 0, 2)


def _expm_inner(M: Tensor, dM: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """exp(M) [N, N, b] and its tangents [r, P, N, b] for dM [r, P, N, b] (first r rows; the rest
    zero, r < N needs M block upper triangular with M[r:, :r] = 0), or None without tangents.

    Balance (exact diagonal similarity), scale by 2^-s to ||X||_1 <= 1/4, degree-11 Taylor by
    Paterson-Stockmeyer (X^2, X^3, then three Horner steps in X^3: 5 products instead of 11),
    square s times; every product carries its tangents (_iprod)."""
    N = M.shape[0]
    d = _balance(M.permute(2, 0, 1))  # [b, N]
    ratio = (d[:, None, :] / d[:, :, None]).permute(1, 2, 0)  # D^-1 M D: entry (i, l) times d_l / d_i
    X = M * ratio
    norm = float(X.abs().sum(0).amax()) if X.numel() else 0.0
    s = max(0, math.ceil(math.log2(norm / _TAYLOR_THETA))) if norm > _TAYLOR_THETA else 0
    X = X * 2.0**-s
    dX = None if dM is None else dM * (ratio[: dM.shape[0]] * 2.0**-s)[:, None]
    eye = torch.eye(N, dtype=M.dtype, device=M.device)[:, :, None]
    X2, dX2 = _iprod(X, dX, X, dX)
    X3, dX3 = _iprod(X2, dX2, X, dX)
    coef = [1.0 / math.factorial(k) for k in range(_TAYLOR_DEGREE + 1)]

    def block(i):  # sum_{r<3} coef[3i + r] X^r and its tangent
        a, b, c = coef[3 * i : 3 * i + 3]
        tangent = None if dX is None else torch.mul(dX2, c).add_(dX, alpha=b)
        return (a * eye + b * X).add_(X2, alpha=c), tangent

    S, dS = block(_TAYLOR_DEGREE // 3)
    for i in range(_TAYLOR_DEGREE // 3 - 1, -1, -1):
        S, dS = _iprod(X3, dX3, S, dS)
        Bi, dBi = block(i)
        S.add_(Bi)
        if dS is not None:
            dS.add_(dBi)
    for _ in range(s):
        S, dS = _iprod(S, dS, S, dS)
    inverse = 1.0 / ratio  # back: D exp(X) D^-1
    return S * inverse, None if dS is None else dS * inverse[: dS.shape[0], None]


def expm_taylor(M: Tensor) -> Tensor:
    """exp(M) [b, N, N] by the same balanced scaling-and-squaring Taylor scheme (no tangents)."""
    F, _ = _expm_inner(M.permute(1, 2, 0), None)
    return F.permute(2, 0, 1)


# ----------------------------------------------------------------------------- discrete maps
def _van_loan(A: Tensor, B: Tensor, tau: float) -> Tensor:
    """[N, N, b] (batch innermost), N = n + 2m."""
    batch, n, m = B.shape
    M = torch.zeros(n + 2 * m, n + 2 * m, batch, dtype=A.dtype, device=A.device)
    M[:n, :n] = A.permute(1, 2, 0) * tau
    M[:n, n : n + m] = B.permute(1, 2, 0) * tau
    M[n : n + m, n + m :] = torch.eye(m, dtype=A.dtype, device=A.device)[:, :, None]
    return M


def discrete_maps(
    model: LinearModel, params: Tensor, h: float, hold: str = "spline", substeps: int = 4, tangents: bool = False
):
    """Per-sample maps of one sampling interval.

    Returns (Phi [b, n, n], Lam [b, m_sub+1, n, m]) and, with ``tangents``, also
    (dPhi [b, P, n, n], dLam [b, P, m_sub+1, n, m]); x_{k+1} = Phi x_k + sum_j Lam_j s_{k,j}.
    m_sub = substeps for "spline", 1 otherwise (FOH: Lam = (Gamma0, Gamma1); ZOH: (Gamma, 0)).
    """
    maps = _maps(model, params.to(_DTYPE), h, hold, substeps, tangents)
    phi, lam = maps[0].permute(2, 0, 1), maps[1].permute(3, 0, 1, 2)
    if not tangents:
        return phi, lam
    return phi, lam, maps[2].permute(3, 1, 0, 2), maps[3].permute(4, 2, 0, 1, 3)


def _maps(model, p, h, hold, substeps, tangents):
    """As discrete_maps, batch innermost: Phi [n, n, b], Lam [m_sub+1, n, m, b],
    dPhi [n, P, n, b], dLam [m_sub+1, n, P, m, b]."""
    A, B, _, _ = model.matrices(p)
    n, m = model.n_state, model.n_input
    m_sub = substeps if hold == "spline" else 1
    tau = h / m_sub
    M = _van_loan(A, B, tau)
    dM = None
    if tangents:  # only the n state rows of the Van Loan matrix depend on p
        dA, dB, _, _ = model.matrix_derivatives(p)
        dM = torch.zeros(n, p.shape[1], n + 2 * m, p.shape[0], dtype=_DTYPE, device=p.device)
        dM[:, :, :n] = dA.permute(2, 1, 3, 0) * tau
        dM[:, :, n : n + m] = dB.permute(2, 1, 3, 0) * tau
    F, dF = _expm_inner(M, dM)
    # exp(Van Loan) = [[phi, F1, F2], ...]; FOH: g0 = F1 - F2, g1 = F2; ZOH: g0 = F1, g1 = 0
    phi, F1, F2 = F[:n, :n], F[:n, n : n + m], F[:n, n + m :]
    g0, g1 = (F1, torch.zeros_like(F2)) if hold == "zoh" else (F1 - F2, F2)
    if dF is not None:
        dphi, dF1, dF2 = dF[:, :, :n], dF[:, :, n : n + m], dF[:, :, n + m :]
        dg0, dg1 = (dF1, torch.zeros_like(dF2)) if hold == "zoh" else (dF1 - dF2, dF2)
    if m_sub == 1:
        if dF is None:
            return phi.contiguous(), torch.stack([g0, g1])
        return phi.contiguous(), torch.stack([g0, g1]), dphi.contiguous(), torch.stack([dg0, dg1])
    # Fold the sub-steps: with c = g0 + phi g1, Lam_m = g1, Lam_j = phi^(m-1-j) c (1 <= j < m),
    # Lam_0 = phi^(m-1) g0 and Phi = phi^m: repeated left products of W = [c | g0 | phi] by phi.
    phi = phi.contiguous()
    dphi = None if dF is None else dphi.contiguous()
    c, dc = _iprod(phi, dphi, g1, None if dF is None else dg1)
    c.add_(g0)
    W = torch.cat([c, g0, phi], 1)
    lam = [None] * (m_sub + 1)
    lam[m_sub], lam[m_sub - 1] = g1, c
    if dF is None:
        for i in range(1, m_sub):
            W, _ = _iprod(phi, None, W, None)
            if i < m_sub - 1:
                lam[m_sub - 1 - i] = W[:, :m]
        lam[0] = W[:, m : 2 * m]
        return W[:, 2 * m :].contiguous(), torch.stack(lam)
    dc.add_(dg0)
    dW = torch.cat([dc, dg0, dphi], 2)
    dlam = [None] * (m_sub + 1)
    dlam[m_sub], dlam[m_sub - 1] = dg1, dc
    for i in range(1, m_sub):
        W, dW = _iprod(phi, dphi, W, dW)
        if i < m_sub - 1:
            lam[m_sub - 1 - i], dlam[m_sub - 1 - i] = W[:, :m], dW[:, :, :m]
    lam[0], dlam[0] = W[:, m : 2 * m], dW[:, :, m : 2 * m]
    return W[:, 2 * m :].contiguous(), torch.stack(lam), dW[:, :, 2 * m :].contiguous(), torch.stack(dlam)


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
    thousand, which is what a line search's small batches cost), "recursion", or "auto" (default:
    whichever is faster for the batch size, _MODAL_OUTPUTS_MAX); they agree to round-off.
    """
    if method not in OUTPUT_METHODS:
        raise ValueError(f"exact: unknown method {method!r}; choose one of {OUTPUT_METHODS}")
    params, x0, inputs, start, T = _prepare(model, params, x0, inputs, h, hold, substeps, start, n_steps, spline_degree)
    _check_held(held, inputs, hold, substeps, T)
    if T > 1:
        held = _held(inputs, hold, substeps, start, T, spline_degree) if held is None else held.to(_DTYPE)
    if method == "auto":
        method = "modal" if params.shape[0] <= _MODAL_OUTPUTS_MAX else "recursion"
    if method == "recursion" or T == 1:
        return _recursion_outputs(model, params, x0, inputs, h, hold, substeps, start, T, held)
    A, B, C, E = model.matrices(params)
    out, ok = modal_outputs((A, B, C, E), _balance(A), x0, held.permute(2, 1, 0), inputs[:, start : start + T], h, hold)
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
    """exact_outputs by the step recursion (validated float64 arguments, held from _held; None for T = 1)."""
    batch = inputs.shape[0]
    _, _, C, E = model.matrices(params)
    if T > 1:
        phi, lam = _maps(model, params, h, hold, substeps, False)
        if held.stride(2) != 1 and held.stride(0) == 1:  # stored batch first (PreparedInputs)
            forcing = _forcing_batch_first(lam, held, T)  # [T-1, n, b]
        else:
            forcing = _forcing(lam, _sub_samples(held, T))
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
) -> Tensor:
    """Prediction and Jacobian in one forward pass.

    -> [b, n_steps, o, 1 + P (+ n if with_x0)]: [..., 0] the prediction, [..., 1 + j] = dy/dp_j,
    [..., 1 + P + i] = dy/dx0_i (x0 = the state at sample ``start``). Window and margins as in
    exact_outputs. Same layout convention as euler_sensitivities ([b, T, 3, 11]).

    ``method``: "modal" (default) evaluates the same quantities in eigen-coordinates of A, one
    small matrix product per sample (estimation._modal; samples with nearly repeated eigenvalues
    or ill-conditioned eigenvectors go to the recursion); "recursion" runs the step recursion
    below for every sample. They agree to round-off (tests/test_exact.py). ``held`` as in exact_outputs.
    """
    if method not in METHODS:
        raise ValueError(f"exact: unknown method {method!r}; choose one of {METHODS}")
    params, x0, inputs, start, T = _prepare(model, params, x0, inputs, h, hold, substeps, start, n_steps, spline_degree)
    _check_held(held, inputs, hold, substeps, T)
    held = _held(inputs, hold, substeps, start, T, spline_degree) if held is None else held.to(_DTYPE)
    if method == "recursion" or T == 1:
        return _recursion_sensitivities(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held)
    A, B, C, E = model.matrices(params)
    out, ok = modal_sensitivities(
        (A, B, C, E),
        model.matrix_derivatives(params),
        _balance(A),
        x0,
        held.permute(2, 1, 0),
        inputs[:, start : start + T],
        h,
        hold,
        with_x0,
    )
    if not bool(ok.all()):
        bad = (~ok).nonzero()[:, 0]
        fallback = _stacked_sensitivities if bad.numel() <= _STACKED_MAX else _recursion_sensitivities
        out[bad] = fallback(
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
    return out


def _maps_batch_first(model, p: Tensor, h: float, hold: str, substeps: int):
    """discrete_maps(..., tangents=True) for a few samples, batch first: (Phi [b, n, n],
    Lam [b, M+1, n, m], dPhi [b, P, n, n], dLam [b, P, M+1, n, m]). The Van Loan exponential and its
    Fréchet derivatives are the blocks of exp([[M, dM_j], [0, M]]) (torch.linalg.matrix_exp, one
    call for all j), the sub-steps are folded as in _maps with per-sample products (_matmul): a few
    dozen ops instead of the ~400 of the batch-innermost _maps, which only pay off for large
    batches."""
    A, B, _, _ = model.matrices(p)
    dA, dB, _, _ = model.matrix_derivatives(p)
    batch, n_params = p.shape
    n, m = model.n_state, model.n_input
    m_sub = substeps if hold == "spline" else 1
    tau = h / m_sub
    N = n + 2 * m
    block = torch.zeros(batch, n_params, 2 * N, 2 * N, dtype=_DTYPE, device=p.device)
    M = _van_loan(A, B, tau).permute(2, 0, 1)  # [b, N, N]
    block[..., :N, :N] = block[..., N:, N:] = M[:, None]
    block[..., :n, N : N + n] = dA * tau
    block[..., :n, N + n : N + n + m] = dB * tau
    d = _balance(block.view(-1, 2 * N, 2 * N)).view(batch, n_params, 1, 2 * N)  # as in _expm_inner
    ratio = d / d.transpose(2, 3)  # exp(D^-1 X D) = D^-1 exp(X) D, D powers of two: exact
    F = torch.linalg.matrix_exp(block * ratio) / ratio
    phi, F1, F2 = F[:, 0, :n, :n], F[:, 0, :n, n : n + m], F[:, 0, :n, n + m : N]
    dphi, dF1, dF2 = F[..., :n, N : N + n], F[..., :n, N + n : N + n + m], F[..., :n, N + n + m :]
    g0, g1 = (F1, torch.zeros_like(F2)) if hold == "zoh" else (F1 - F2, F2)
    dg0, dg1 = (dF1, torch.zeros_like(dF2)) if hold == "zoh" else (dF1 - dF2, dF2)
    if m_sub == 1:
        return phi, torch.stack([g0, g1], 1), dphi, torch.stack([dg0, dg1], 2)
    # as _maps: Lam_m = g1, Lam_j = phi^(m-1-j) c (c = g0 + phi g1), Lam_0 = phi^(m-1) g0, Phi = phi^m
    phi, dphi = phi.contiguous(), dphi.contiguous()
    c = _matmul(phi, g1.contiguous()) + g0
    dc = _matmul(dphi, g1[:, None].contiguous()) + _matmul(phi[:, None], dg1.contiguous()) + dg0
    W, dW = torch.cat([c, g0, phi], 2), torch.cat([dc, dg0, dphi], 3)
    lam, dlam = [None] * (m_sub + 1), [None] * (m_sub + 1)
    lam[m_sub], lam[m_sub - 1], dlam[m_sub], dlam[m_sub - 1] = g1, c, dg1, dc
    for i in range(1, m_sub):
        W, dW = _matmul(phi, W), _matmul(dphi, W[:, None]) + _matmul(phi[:, None], dW)
        if i < m_sub - 1:
            lam[m_sub - 1 - i], dlam[m_sub - 1 - i] = W[..., :m], dW[..., :m]
    lam[0], dlam[0] = W[..., m : 2 * m], dW[..., m : 2 * m]
    return W[..., 2 * m :], torch.stack(lam, 1), dW[..., 2 * m :], torch.stack(dlam, 2)


def _stacked_sensitivities(model, params, x0, inputs, h, hold, substeps, with_x0, start, T, held) -> Tensor:
    """exact_sensitivities by the same step recursion as _recursion_sensitivities, for a few samples
    (the modal path's fallback, up to _STACKED_MAX). The state and its tangents are one matrix per
    sample, X_k = [x_k | dx_k/dp | dx_k/dx0] [n, 1 + P (+ n)], and a step is

        X_{k+1} = Phi X_k + [G_k | dPhi_j x_k + dG_k | 0],   G_k = sum_j Lam_j s_{k,j},

    with G and dG for all k from one product before the loop and the maps from
    _maps_batch_first: 3 ops per step instead of ~50, which is what a handful of samples costs
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
        phi, lam, dphi, dlam = _maps_batch_first(model, params, h, hold, substeps)
        m_sub = lam.shape[1] - 1
        # s [b, T-1, (j, c)] and the weights [b, (j, c), (i, q)] of G (q = 0) and dG_p (q = 1 + p)
        s = _sub_samples(held, T).permute(3, 2, 0, 1).reshape(batch, T - 1, (m_sub + 1) * m)
        weights = torch.cat([lam[:, None], dlam], 1)  # [b, q, j, i, c]
        weights = weights.permute(0, 2, 4, 3, 1).reshape(batch, (m_sub + 1) * m, n * (1 + n_params))
        forcing = _matmul(s, weights).view(batch, T - 1, n * (1 + n_params), 1).transpose(0, 1).contiguous()
        # dPhi as [b, (i, q), l] with zero rows for q = 0: dPhi x_k lands in the tangent columns
        dphi_q = torch.zeros(batch, n, 1 + n_params, n, dtype=_DTYPE, device=params.device)
        dphi_q[:, :, 1:] = dphi.transpose(1, 2)
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
    """exact_sensitivities by the step recursion (validated float64 arguments, held from _held)."""
    batch = inputs.shape[0]
    n, o, n_params, n_in = model.n_state, model.n_output, model.n_params, model.n_input
    _, _, C, E = model.matrices(params)
    _, _, dC, dE = model.matrix_derivatives(params)
    window = inputs[:, start : start + T]
    if T > 1:
        phi, lam, dphi, dlam = _maps(model, params, h, hold, substeps, True)  # batch innermost
        s = _sub_samples(held, T)
        forcing = _forcing(lam, s)  # [T-1, n, b]
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
