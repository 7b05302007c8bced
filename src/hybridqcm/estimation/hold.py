"""The input between samples: how the exact discretisation holds a sampled input w_k (estimation/exact.py).

* ``"zoh"``:  w held at w_k over each interval;
* ``"foh"``:  w linear between w_k and w_{k+1};
* ``"spline"`` (default): w is the interpolating spline of degree ``spline_degree`` (5, default, 3 or 7;
  not-a-knot end conditions; the cubic falls back to natural for T = 3 and linear for T = 2, the quintic
  to the cubic below 6 samples) through the samples, sampled at m = ``substeps`` sub-steps per interval
  (a fixed linear map [(T-1) m + 1, T] for a uniform grid, built once), on which first-order hold applies.

Windows and margins: the held input is for the samples start .. start + n_steps - 1 of an input
[b, T_in, m]; the spline runs through the samples on both sides of the window too (up to 64 of them,
beyond which their weight is below round-off), so that the window's edges are interior points.
The forcing G_k = sum_j Lambda_j s_{k,j} of the sub-samples s_{k,j} is built here too (input_forcing).
"""

from __future__ import annotations

import numbers
from functools import lru_cache

import torch
from torch import Tensor

from ._blas import batched_matmul as _matmul

HOLDS = ("spline", "foh", "zoh")
SPLINE_DEGREES = (3, 5, 7)  # 7: for inputs with content near a quarter of the sampling rate (stiff tyres)
_DTYPE = torch.float64


def check_hold_and_window(
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


def held_window(inputs: Tensor, hold: str, substeps: int, start: int, n_steps: int, degree: int = 5) -> Tensor:
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


def sub_samples(held: Tensor, n_steps: int) -> Tensor:
    """held [M + (n_steps - 1) M + 1, m, b] (held_window) -> s [M + 1, m, n_steps - 1, b], a strided view:
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
    n_steps = check_hold_and_window(inputs, hold, substeps, start, n_steps, spline_degree)
    return held_window(inputs.to(_DTYPE), hold, substeps, int(start), n_steps, spline_degree)


def check_held(held: Tensor | None, inputs: Tensor, hold: str, substeps: int, n_steps: int) -> None:
    m_sub = substeps if hold == "spline" else 1
    shape = (m_sub + (n_steps - 1) * m_sub + 1, inputs.shape[2], inputs.shape[0])
    if held is not None and tuple(held.shape) != shape:
        raise ValueError(f"exact: held input must be {list(shape)} (held_input of this window), got {list(held.shape)}")


def input_forcing_batch_first(lam: Tensor, held: Tensor, n_steps: int) -> Tensor:
    """input_forcing(lam, sub_samples(held, n_steps)) for a held input stored batch first (``held`` [W, m, b]
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


def input_forcing(lam: Tensor, s: Tensor) -> Tensor:
    """G_k = sum_j Lam_j s_{k,j} as [T-1, n, b]; lam [m_sub+1, n, m, b], s from sub_samples."""
    lam_t = lam.permute(0, 2, 1, 3).contiguous()  # [j, c, i, b]
    n_sub, n_in = s.shape[:2]
    forcing = torch.empty(s.shape[2], lam.shape[1], s.shape[3], dtype=_DTYPE, device=lam.device)
    torch.mul(s[0, 0][:, None, :], lam_t[0, 0], out=forcing)
    for j in range(n_sub):
        for c in range(n_in):
            if j or c:
                forcing.addcmul_(s[j, c][:, None, :], lam_t[j, c])
    return forcing
