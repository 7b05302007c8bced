"""The matrix exponential with forward-mode tangents and the Van Loan maps of one sampling interval
(estimation/exact.py's module docstring: "Van Loan" and "Derivatives").

Everything per sample is held batch innermost: a matrix S as [r, c, b], its tangents in the P directions
as dS [r', P, c, b]; a product of per-sample matrices is then k broadcast multiply-adds over contiguous
[.., b] rows. ``van_loan_maps_batch_first`` is the batch-first form for a few samples.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybridqcm.physics.linear_models import LinearModel

from ._blas import batched_matmul as _matmul
from ._kernels import applies as _compiled_applies
from ._kernels import balance as _compiled_balance
from ._kernels import van_loan_maps as _compiled_van_loan_maps
from ._kernels import van_loan_tangent_maps as _compiled_van_loan_tangent_maps

_DTYPE = torch.float64
# Taylor degree 11 on ||X||_1 <= 1/4: truncation error <= 0.25^12/12! * e^0.25 < 2e-16 relative.
_TAYLOR_THETA = 0.25
_TAYLOR_DEGREE = 11


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


def balance(M: Tensor, sweeps: int = 2, damping: float = 0.35) -> Tensor:
    """Diagonal scaling d [b, N] (powers of two, so exact) making row and column norms of
    diag(d)^-1 M diag(d) comparable; it shrinks ||M|| (hence the squarings) for the quarter car,
    whose A mixes 1/s and 1/s^2 entries. exp(D^-1 M D) = D^-1 exp(M) D for any fixed D, so the
    scaling changes no result, only the cost. M [b, N, N].

    All indices are updated at once (damped: the undamped simultaneous update oscillates), a few
    vector operations instead of Osborne's index-by-index sweeps; for the quarter-car Van Loan
    matrices it needs the same number of squarings (one at tau = h/4). On the CPU in float64 a compiled loop
    (_kernels.py) does the same per sample (a dozen small ops a call here)."""
    if M.ndim == 3 and _compiled_applies(M):
        return _compiled_balance(M, sweeps, damping)
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
    d = balance(M.permute(2, 0, 1))  # [b, N]
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
    maps = van_loan_maps(model, params.to(_DTYPE), h, hold, substeps, tangents)
    phi, lam = maps[0].permute(2, 0, 1), maps[1].permute(3, 0, 1, 2)
    if not tangents:
        return phi, lam
    return phi, lam, maps[2].permute(3, 1, 0, 2), maps[3].permute(4, 2, 0, 1, 3)


def van_loan_maps(model, p, h, hold, substeps, tangents):
    """As discrete_maps, batch innermost: Phi [n, n, b], Lam [m_sub+1, n, m, b],
    dPhi [n, P, n, b], dLam [m_sub+1, n, P, m, b]."""
    A, B, _, _ = model.matrices(p)
    n, m = model.n_state, model.n_input
    m_sub = substeps if hold == "spline" else 1
    tau = h / m_sub
    M = _van_loan(A, B, tau)
    if not tangents and _compiled_applies(M):  # the same maps by a compiled loop over the samples (_kernels.py)
        d = balance(M.permute(2, 0, 1))
        return _compiled_van_loan_maps(M, d, n, hold == "zoh", m_sub, _TAYLOR_DEGREE, _TAYLOR_THETA)
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


def van_loan_maps_batch_first(model, p: Tensor, h: float, hold: str, substeps: int):
    """discrete_maps(..., tangents=True) for a few samples, batch first: (Phi [b, n, n],
    Lam [b, M+1, n, m], dPhi [b, P, n, n], dLam [b, P, M+1, n, m]). The Van Loan exponential and its
    Fréchet derivatives are the blocks of exp([[M, dM_j], [0, M]]) (torch.linalg.matrix_exp, one
    call for all j), the sub-steps are folded as in van_loan_maps with per-sample products (_matmul): a few
    dozen ops instead of the ~400 of the batch-innermost van_loan_maps, which only pay off for large
    batches."""
    A, B, _, _ = model.matrices(p)
    dA, dB, _, _ = model.matrix_derivatives(p)
    batch, n_params = p.shape
    n, m = model.n_state, model.n_input
    m_sub = substeps if hold == "spline" else 1
    tau = h / m_sub
    N = n + 2 * m
    M = _van_loan(A, B, tau).permute(2, 0, 1)  # [b, N, N]
    if _compiled_applies(M):  # the same maps by a compiled loop over the samples (_kernels.py)
        dM = torch.zeros(batch, n_params, N, N, dtype=_DTYPE, device=p.device)
        dM[..., :n, :n] = dA * tau
        dM[..., :n, n : n + m] = dB * tau
        return _compiled_van_loan_tangent_maps(
            M, dM, balance(M), n, hold == "zoh", m_sub, _TAYLOR_DEGREE, _TAYLOR_THETA
        )
    block = torch.zeros(batch, n_params, 2 * N, 2 * N, dtype=_DTYPE, device=p.device)
    block[..., :N, :N] = block[..., N:, N:] = M[:, None]
    block[..., :n, N : N + n] = dA * tau
    block[..., :n, N + n : N + n + m] = dB * tau
    d = balance(block.view(-1, 2 * N, 2 * N)).view(batch, n_params, 1, 2 * N)  # as in _expm_inner
    ratio = d / d.transpose(2, 3)  # exp(D^-1 X D) = D^-1 exp(X) D, D powers of two: exact
    F = torch.linalg.matrix_exp(block * ratio) / ratio
    phi, F1, F2 = F[:, 0, :n, :n], F[:, 0, :n, n : n + m], F[:, 0, :n, n + m : N]
    dphi, dF1, dF2 = F[..., :n, N : N + n], F[..., :n, N + n : N + n + m], F[..., :n, N + n + m :]
    g0, g1 = (F1, torch.zeros_like(F2)) if hold == "zoh" else (F1 - F2, F2)
    dg0, dg1 = (dF1, torch.zeros_like(dF2)) if hold == "zoh" else (dF1 - dF2, dF2)
    if m_sub == 1:
        return phi, torch.stack([g0, g1], 1), dphi, torch.stack([dg0, dg1], 2)
    # as van_loan_maps: Lam_m = g1, Lam_j = phi^(m-1-j) c (c = g0 + phi g1), Lam_0 = phi^(m-1) g0, Phi = phi^m
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
