"""Modal evaluation of the exact sensitivities: the same numbers as the step recursion of
``exact.exact_sensitivities``, written as one small matrix product per sample.

Notation as in ``exact`` (b samples, P params, n states, m inputs, o outputs, T window samples,
M sub-steps of length tau = h/M, s_{k,j} the held input at t_k + j tau). Per sample
A = V diag(lambda) V^-1 (distinct eigenvalues), modal state xi = V^-1 x:

    xi_i' = lambda_i xi_i + beta_i w,   beta = V^-1 B,   y = gamma xi + E w,   gamma = C V.

Everything is then a sum of four kinds of scalar sequences per mode i (and input channel c):

    e_{k,i} = mu_i^k, mu_i = exp(lambda_i h)       (free response, closed form)
    f_{k,i} = k h mu_i^k = d e_{k,i}/d lambda_i     (closed form)
    psi_{k,i,c}: psi' = lambda_i psi + w_c, psi_0 = 0, under the same hold as ``exact``
    chi_{k,i,c} = d psi_{k,i,c} / d lambda_i

psi is a scalar recursion psi_{k+1} = mu psi_k + sum_j l_j s_{k,j}, with the folded FOH weights
l_j = [j < M] phi^(M-1-j) g0 + [j >= 1] phi^(M-j) g1, phi = exp(z), z = lambda tau,
g0 = tau (phi_1(z) - phi_2(z)), g1 = tau phi_2(z) (ZOH: g0 = tau phi_1(z), g1 = 0), where
phi_k(z) = sum_r z^r / (r + k)! (so phi_k' = phi_k - k phi_{k+1}); chi_{k+1} = mu chi_k +
h mu psi_k + sum_j (d l_j / d lambda) s_{k,j}.

Derivatives in p_j. With K_j = V^-1 dA_j V, its diagonal d_j (= d lambda / d p_j) and
S_j,il = -K_j,il / (lambda_i - lambda_l) (i != l, 0 on the diagonal), the variable
eta_j = V^-1 dx/dp_j - S_j xi obeys eta_j' = diag(lambda) eta_j + diag(d_j) xi + beta''_j w with
beta''_j = V^-1 dB_j - S_j beta (the Sylvester part of K_j is absorbed by the change of
variables), so per mode eta_{j,i} = mu_i^k eta_{j,i}(0) + d_{j,i} zeta_i + beta''_{j,i} psi_i,
zeta_i = d xi_i / d lambda_i = xi0_i f_i + beta_i chi_i, eta_j(0) = -S_j xi0, and

    dy_k/dp_j = gamma (eta_j + S_j xi_k) + dC_j V xi_k + dE_j w_k,   dy_k/dx0 = gamma diag(e_k) V^-1.

Every column of the result [o, 1 + P (+ n)] is a fixed (per sample) combination of the basis
(e, f, psi, chi, w): result[b] = basis[b] [T, R] @ coef[b] [R, o (1 + P + n)], one bmm straight
into the batch-first layout. The result is real: with modes in conjugate pairs, sum_i c_i z_i =
sum_i omega_i Re(c_i z_i), omega = 2 for the member with Im lambda > 0, 0 for its partner, 1 for
a real eigenvalue (whose z is real), so each complex basis kind contributes exactly n real
columns (Re and Im of the upper members, Re of the real ones): R = 2 n (m + 1) + m.

Conditioning. Rounding errors grow like cond(V) max|lambda| / |lambda_i - lambda_l| (most for two
nearly equal real eigenvalues, whose terms cancel); samples with this ratio above _LIMIT
(_LIMIT_REAL for a real pair), or with non-finite values, are reported in ``ok`` and left to
the step recursion.
The eigenproblem is solved on the balanced D^-1 A D (D from _expm.balance, powers of two).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ._blas import batched_matmul as _matmul
from ._host import on_host
from ._kernels import applies as _compiled_applies
from ._kernels import hold_weights as _compiled_hold_weights
from ._kernels import modal_coefficients as _compiled_coefficients
from ._kernels import modal_scan as _compiled_scan
from ._kernels import modes as _compiled_modes

_CDTYPE = torch.complex128
# cond(V) max|lambda| / |lambda_i - lambda_l| above these: leave the sample to the recursion.
# Measured differences from the recursion (docs/measurements/exact_discretisation.md): two nearly equal real
# eigenvalues (an almost critically damped mode) cost ~6e-18 times the square of this ratio
# (2e-10 at 5.7e3), other pairs far less (< 1e-12 up to 1.4e6 for the quarter car).
_LIMIT = 1e5
_LIMIT_REAL = 1e3
# The outputs alone divide by no eigenvalue difference: their rounding grows like cond(V) eps
# (measured, seat near critical damping: 1.3e-12 relative at cond 1.6e4, 1.2e-13 at 1.8e3;
# exactly critical, cond 1e16: wrong), so modal_outputs keeps the samples with cond(V) up to this.
_LIMIT_OUTPUTS = 1e4
# _scan blocks the recursion where a row holds at most this many complex numbers: there the steps' fixed
# cost is the recursion's, and blocking (2x the arithmetic) took 2-4x less time at 2-16 recordings; at
# 96 and more recordings a call it took 1.1-2x more (measured on 2 cores, docs/measurements/persons.md)
_SCAN_ROW = 512
_SERIES_TERMS = 18  # phi_3(z) by its series for |z| <= 1: remainder < 1/21! < 2e-19 relative


def _phi123(z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """phi_1, phi_2, phi_3 of complex z (any shape). |z| <= 1: phi_3 by its series, then upwards
    phi_k = 1/k! + z phi_{k+1} (no cancellation); |z| > 1: phi_1 = (e^z - 1)/z and downwards
    phi_{k+1} = (phi_k - 1/k!)/z, which loses at most a few bits there."""
    small = z.abs() <= 1
    zs = torch.where(small, z, torch.zeros_like(z))
    p3 = torch.full_like(zs, 1.0 / math.factorial(_SERIES_TERMS + 3))
    for r in range(_SERIES_TERMS - 1, -1, -1):  # Horner
        p3 = p3 * zs + 1.0 / math.factorial(r + 3)
    p2 = p3 * zs + 0.5
    p1 = p2 * zs + 1.0
    zl = torch.where(small, torch.ones_like(z), z)
    q1 = (torch.exp(zl) - 1.0) / zl
    q2 = (q1 - 1.0) / zl
    q3 = (q2 - 0.5) / zl
    return torch.where(small, p1, q1), torch.where(small, p2, q2), torch.where(small, p3, q3)


def _hold_weights(lam: Tensor, h: float, hold: str, m_sub: int) -> tuple[Tensor, Tensor]:
    """l_j and d l_j / d lambda for the unit-gain mode lambda [...]: each [m_sub + 1, ...]. On the CPU in complex128
    by a compiled loop over the modes (_kernels.py: the same expressions; here ~40 small ops a call)."""
    if lam.ndim == 2 and _compiled_applies(lam):
        return _compiled_hold_weights(lam, h, hold, m_sub, _SERIES_TERMS)
    tau = h / m_sub
    z = lam * tau
    p1, p2, p3 = _phi123(z)
    if hold == "zoh":
        g0, g1 = tau * p1, torch.zeros_like(p1)
        dg0, dg1 = tau * tau * (p1 - p2), torch.zeros_like(p1)
    else:
        g0, g1 = tau * (p1 - p2), tau * p2
        dg0, dg1 = tau * tau * (p1 - 2 * p2 + 2 * p3), tau * tau * (p2 - 2 * p3)
    phi = torch.exp(z)
    powers = torch.cat([torch.ones_like(phi)[None], phi[None].expand(m_sub, *phi.shape)]).cumprod(0)  # phi^0..M
    j = torch.arange(m_sub + 1, device=lam.device)
    a, b = (m_sub - 1 - j).clamp_min(0), m_sub - j  # powers of phi multiplying g0 (j < M) and g1 (j >= 1)
    shape = (-1,) + (1,) * lam.ndim
    use0, use1 = (j < m_sub).view(shape), (j >= 1).view(shape)
    pa, pb = powers[a], powers[b]
    a, b = (a.to(torch.float64) * tau).view(shape), (b.to(torch.float64) * tau).view(shape)
    ell = torch.where(use0, pa * g0, 0) + torch.where(use1, pb * g1, 0)
    dell = torch.where(use0, pa * (a * g0 + dg0), 0) + torch.where(use1, pb * (b * g1 + dg1), 0)
    return ell, dell


def _real_times_complex(real: Tensor, cplx: Tensor) -> Tensor:
    """real [b, r, s] @ cplx [b, s, c] -> complex [b, r, c], as one real product with the real and
    imaginary parts of each column of ``cplx`` side by side (half the flops of a complex product)."""
    batch, s, c = cplx.shape
    pairs = torch.view_as_real(cplx.contiguous()).view(batch, s, 2 * c)
    return torch.view_as_complex(_matmul(real.contiguous(), pairs).view(batch, real.shape[1], c, 2))


def _eig(M: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The eigen-decomposition of [b, n, n] -> (lambda [b, n], V [b, n, n], converged [b]), by numpy's LAPACK
    (OpenBLAS' dgeev), not torch.linalg.eig: MKL's, which torch's CPU build calls, failed to converge on a line
    search's trial matrix with entries from 1e-76 to 1e172 and corrupted the heap as it did (the process
    aborted with `double free or corruption` a few calls later: tests/test_exact.py keeps that matrix);
    OpenBLAS' decomposes it. The QR iteration can still fail to converge on a trial step's ill-conditioned
    matrix, and the call raises for the whole batch then; such a matrix is one not-ok sample (identity
    eigenvectors, zero eigenvalues), not an error. Samples on another device are decomposed on the CPU:
    torch's CUDA eig is MAGMA's geev, a host routine called once per matrix, and the batch's copy costs less
    (in slices on the host's cores: _host.py)."""
    if M.device.type != "cpu":
        return on_host(_eig, M, rows=True)
    values = M.detach().numpy()
    kind = np.result_type(values.dtype, np.complex64)
    try:
        lam, V = np.linalg.eig(values)
        converged = np.ones(values.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        n = values.shape[-1]
        lam = np.zeros(values.shape[:-1], dtype=kind)
        V = np.broadcast_to(np.eye(n, dtype=kind), values.shape).copy()
        converged = np.zeros(values.shape[0], dtype=bool)
        for i in range(values.shape[0]):
            try:
                lam[i], V[i] = np.linalg.eig(values[i])
                converged[i] = True
            except np.linalg.LinAlgError:
                pass
    # numpy returns real arrays where every eigenvalue of the stack is real
    return torch.from_numpy(lam.astype(kind)), torch.from_numpy(V.astype(kind)), torch.from_numpy(converged)


def _decompose(A: Tensor, scale: Tensor, sort: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """_eigen, and with ``sort`` the modes in _modes' order; the count of the upper and real modes n_first [b] appended.
    After LAPACK's decomposition, the inverse, scaling, checks and order run as one compiled loop over the samples
    on the CPU (_kernels.py; here ~25 small ops a call, the cost of a line search's trial at a few recordings)."""
    ratio = scale[:, None, :] / scale[:, :, None]
    balanced = A * ratio
    finite = torch.isfinite(balanced).all(-1).all(-1)
    # a non-finite matrix (a failed trial step) or defective eigenvectors: not ok, left to the recursion
    balanced = torch.where(finite[:, None, None], balanced, torch.zeros_like(balanced))
    lam, Vb, converged = _eig(balanced)
    if _compiled_applies(Vb):
        lam, V, V_inv, cond, ok, n_first = _compiled_modes(lam, Vb, scale, sort)
        return lam, V, V_inv, cond, ok & finite & converged, n_first
    Vb_inv, info = torch.linalg.inv_ex(Vb)
    V, V_inv = Vb * scale[:, :, None], Vb_inv / scale[:, None, :]
    cond = Vb.abs().sum(1).amax(-1) * Vb_inv.abs().sum(1).amax(-1)
    ok = finite & converged & (info == 0) & torch.isfinite(cond) & ((lam.imag > 0).sum(-1) == (lam.imag < 0).sum(-1))
    n = lam.shape[1]
    upper, real = lam.imag > 0, lam.imag == 0
    n_first = n - upper.sum(1)
    if sort:
        order = torch.argsort(torch.where(upper, 0, torch.where(real, 1, 2)).to(torch.int8), dim=1, stable=True)
        lam = torch.gather(lam, 1, order)
        V = torch.gather(V, 2, order[:, None, :].expand(-1, n, -1))
        V_inv = torch.gather(V_inv, 1, order[:, :, None].expand(-1, -1, n))
    return lam, V, V_inv, cond, ok, n_first


def _eigen(A: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """A [b, n, n] = V diag(lambda) V^-1 from the balanced D^-1 A D (scale [b, n] = D):
    -> (lambda [b, n], V, V^-1 [b, n, n] complex, cond [b] the 1-norm condition number of the
    balanced eigenvectors, ok [b]: finite, and the complex eigenvalues in conjugate pairs)."""
    return _decompose(A, scale, sort=False)[:5]


def _modes(A: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """_eigen with the modes reordered so that the K propagated ones come first:
    -> (lambda [b, n], V, V^-1 [b, n, n], cond [b], ok [b], omega [b, K] float64).

    Real form. sum_i c_i z_i = sum_i omega_i Re(c_i z_i) (omega = 2 for the member of a pair with
    Im lambda > 0, 0 for its partner, 1 for a real eigenvalue, whose z is real), and
    Re(c z) = Re c Re z - Im c Im z: only the kept modes (upper members and real eigenvalues,
    n_first <= n per sample) are propagated, and Re z, Im z of each are the real basis columns.
    Slots: the kept modes first, padded to the chunk's largest n_first (K) with zero weight."""
    lam, V, V_inv, cond, ok, n_first = _decompose(A, scale, sort=True)
    n_slot = int(n_first.max())
    omega = torch.where(lam[:, :n_slot].imag > 0, 2.0, 1.0).to(torch.float64)
    omega = omega * (torch.arange(n_slot, device=lam.device) < n_first[:, None])
    return lam, V, V_inv, cond, ok, omega


def _basis_buffer(T: int, batch: int, width: int, device) -> Tensor:
    """The basis buffer as a time-first view [T, b, width]. Stored batch first where the compiled scan runs: its loop
    takes one sample's steps in order, and the final product reads each sample's rows contiguously (time first,
    that product ran 1.3x longer at 512 recordings a chunk); time first for torch's scan, where one step over the
    whole batch is one op."""
    if _compiled_applies(torch.empty(0, dtype=_CDTYPE, device=device)):
        return torch.empty(batch, T, width, dtype=torch.float64, device=device).transpose(0, 1)
    return torch.empty(T, batch, width, dtype=torch.float64, device=device)


def _held_rows(fine: Tensor, T: int) -> Tensor:
    """fine [b, m, M + (T - 1) M + 1] (M leading zeros) -> [b, T, (c, j)] (a copy): row k holds
    s_{k-1, 0..M} of every input channel (row 0: the padding, zeros)."""
    batch, m, width = fine.shape
    m_sub = (width - 1) // T
    sb, sc, st = fine.stride()
    return fine.as_strided((batch, T, m, m_sub + 1), (sb, m_sub * st, sc, st)).reshape(batch, T, m * (m_sub + 1))


def _derivative_terms(derivatives, V, V_inv, beta, gamma, diff, n_slot):
    """The p-derivative terms of modal_sensitivities (its notation): -> d lambda / dp [b, P, K], the kept rows
    of S_j [b, (K, P), n], beta''_j [b, K, P, m], Gam_j [b, o, P, K]."""
    dA, dB, dC, _ = derivatives
    batch, n_params, n = dA.shape[:3]
    m, o = dB.shape[-1], dC.shape[2]
    eye = torch.eye(n, dtype=torch.bool, device=dA.device)
    shared = dA.stride(0) == 0 and dB.stride(0) == 0 and dC.stride(0) == 0  # linear model: one dA for all
    # One product per sample with the P parameters side by side (layouts [b, row, P, col]), not one per
    # sample and parameter: 10x fewer calls of the same small products. A real matrix times a complex one
    # is a real product with the real and imaginary parts as adjacent columns (view_as_real).
    if shared:
        dAV = torch.einsum("pjs,bsl->bjpl", dA[0].to(_CDTYPE), V)  # [b, j, P, l] = (dA_p V)_jl
    else:
        dAV = _real_times_complex(dA.transpose(1, 2).reshape(batch, n * n_params, n), V).view(batch, n, n_params, n)
    K = _matmul(V_inv, dAV.reshape(batch, n, n_params * n)).view(batch, n, n_params, n)  # [b, i, P, l] V^-1 dA_p V
    dlam = torch.diagonal(K, dim1=1, dim2=3)[..., :n_slot]  # [b, P, K] d lambda / d p
    off = eye[:, None, :]  # [i, 1, l]
    S = -(K / diff[:, :, None].masked_fill(off, 1.0)).masked_fill(off, 0.0)  # [b, i, P, l]
    S_kept = S[:, :n_slot].reshape(batch, n_slot * n_params, n)  # [b, (K, P), n]
    if shared:
        beta2 = torch.einsum("bil,plc->bipc", V_inv[:, :n_slot], dB[0].to(_CDTYPE))  # [b, K, P, m]
        Gam = torch.einsum("pon,bnl->bopl", dC[0].to(_CDTYPE), V[:, :, :n_slot])  # [b, o, P, K]
    else:
        dB_rows = dB.to(_CDTYPE).transpose(1, 2).reshape(batch, n, n_params * m)
        beta2 = _matmul(V_inv[:, :n_slot], dB_rows).view(batch, n_slot, n_params, m)
        dC_rows = dC.transpose(1, 2).reshape(batch, o * n_params, n)
        Gam = _real_times_complex(dC_rows, V[:, :, :n_slot]).view(batch, o, n_params, n_slot)
    beta2 = beta2 - _matmul(S_kept, beta).view(batch, n_slot, n_params, m)  # [b, K, P, m]
    S_cols = S[..., :n_slot].reshape(batch, n, n_params * n_slot)
    Gam = Gam + _matmul(gamma, S_cols).view(batch, o, n_params, n_slot)  # [b, o, P, K]
    return dlam, S_kept, beta2, Gam


def _coefficients(lam, V, V_inv, cond, ok, matrices, derivatives, x0, with_x0, omega, n_t, width):
    """modal_sensitivities' coefficients (its notation and arguments; lam, V, V^-1, cond and ok from _modes) in
    torch: -> (coef_all [b, width, o (1 + P (+ n))] real, ok [b] with the spread and finiteness checks applied).
    Rows (channel, kind, slot, Re/Im) of the basis, then the inputs w, then the targets (coefficient -1 on their
    output's column 0), then zero padding."""
    A, B, C, E = matrices
    dA, dB, dC, dE = derivatives
    batch, n, m = B.shape
    o, n_params = C.shape[1], dA.shape[1]
    n_col = 1 + n_params + (n if with_x0 else 0)
    dev = A.device
    n_slot = omega.shape[1]
    diff = lam[:, :, None] - lam[:, None, :]  # [b, i, l] lambda_i - lambda_l
    eye = torch.eye(n, dtype=torch.bool, device=dev)
    both_real = (lam.imag == 0)[:, :, None] & (lam.imag == 0)[:, None, :]
    spread = (cond * lam.abs().amax(-1))[:, None, None] / diff.abs().masked_fill(eye, math.inf)  # [b, i, l]
    ok = ok & (spread <= torch.where(both_real, _LIMIT_REAL, _LIMIT)).all(-1).all(-1)

    # K_j = V^-1 dA_j V, S_j, and per kept mode l < K: beta''_j (rows l of S), Gam_j = gamma S_j +
    # dC_j V (columns l), eta_j(0) = -S_j xi0
    beta = _matmul(V_inv, B.to(_CDTYPE))  # [b, n, m]
    gamma = _matmul(C.to(_CDTYPE), V)  # [b, o, n]
    dlam, S_kept, beta2, Gam = _derivative_terms(derivatives, V, V_inv, beta, gamma, diff, n_slot)

    # Coefficients [b, channel, kind, slot, o, col], channels (e, f) then (psi_c, chi_c): every one
    # is gamma_l R[channel, kind, l, col] plus, in the p columns of kind 0, Gam_j,l Q[channel, l]
    # (the Sylvester term), so R and Q are built per slot and multiplied out once; the real form's
    # conjugate and weight omega go into the factors.
    R = torch.zeros(batch, 1 + m, 2, n_slot, n_col, dtype=_CDTYPE, device=dev)
    Q = torch.zeros(batch, 1 + m, n_slot, dtype=_CDTYPE, device=dev)
    beta_t = beta[:, :n_slot].transpose(1, 2)  # [b, c, K]
    if x0 is not None:
        xi0 = _matmul(V_inv, x0.to(_CDTYPE)[..., None])  # [b, n, 1]
        R[:, 0, 0, :, 0] = Q[:, 0] = xi0[:, :n_slot, 0]
        R[:, 0, 0, :, 1 : 1 + n_params] = -_matmul(S_kept, xi0).view(batch, n_slot, n_params)
        R[:, 0, 1, :, 1 : 1 + n_params] = (dlam * xi0[:, None, :n_slot, 0]).transpose(1, 2)
    if with_x0:
        R[:, 0, 0, :, 1 + n_params :] = V_inv[:, :n_slot]
    R[:, 1:, 0, :, 0] = Q[:, 1:] = beta_t
    R[:, 1:, 0, :, 1 : 1 + n_params] = beta2.permute(0, 3, 1, 2)
    R[:, 1:, 1, :, 1 : 1 + n_params] = dlam.transpose(1, 2)[:, None] * beta_t[..., None]
    g = gamma[:, :, :n_slot].conj().transpose(1, 2) * omega[:, :, None]  # [b, K, o]
    coef = g[:, None, None, :, :, None] * R.conj()[:, :, :, :, None, :]  # [b, 1 + m, 2, K, o, col]
    coef[:, :, 0, :, :, 1 : 1 + n_params] += (Gam.conj() * omega[:, None, None, :]).permute(0, 3, 1, 2)[
        :, None
    ] * Q.conj()[..., None, None]
    n_real = 4 * n_slot * (m + 1)
    coef_all = torch.zeros(batch, width, o * n_col, dtype=torch.float64, device=dev)  # rows: (Z | w | targets | 0)
    if n_t:
        coef_all[:, n_real + m : n_real + m + o].view(batch, o, o, n_col).diagonal(dim1=1, dim2=2)[:, 0] = -1.0
    coef_all[:, :n_real].view(batch, 1 + m, 2, n_slot, 2, o, n_col).copy_(
        torch.view_as_real(coef).permute(0, 1, 2, 3, 6, 4, 5)
    )
    coef_w = coef_all[:, n_real : n_real + m].view(batch, m, o, n_col)
    coef_w[..., : 1 + n_params] = torch.cat([E[:, None], dE], 1).permute(0, 3, 2, 1)  # y and dy/dp: E w, dE w
    ok &= torch.isfinite(coef_all.sum((1, 2)))
    return coef_all, ok


def modal_sensitivities(
    matrices: tuple[Tensor, Tensor, Tensor, Tensor],
    derivatives: tuple[Tensor, Tensor, Tensor, Tensor],
    scale: Tensor,
    x0: Tensor | None,
    fine: Tensor,
    window: Tensor,
    h: float,
    hold: str,
    with_x0: bool,
    targets: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """-> (result [b, T, o, 1 + P (+ n)] as exact_sensitivities, ok [b] bool); with ``targets`` [b, T, o]
    column 0 is the residual y - targets (they are columns of the basis with coefficient -1: the
    subtraction costs no pass over the result).

    matrices A [b, n, n], B [b, n, m], C [b, o, n], E [b, o, m]; derivatives dA [b, P, n, n],
    dB [b, P, n, m], dC [b, P, o, n], dE [b, P, o, m] (float64); scale [b, n] the balancing
    D; x0 [b, n] or None; fine [b, m, M + (T - 1) M + 1] (any strides): M zeros, then the held input
    at the sub-steps (hold.held_window, permuted), window [b, T, m] the input samples of the window. Rows of samples
    with ok False are not valid.
    """
    A, B, C, E = matrices
    dA, dB, dC, dE = derivatives
    batch, n, m = B.shape
    o, n_params, T = C.shape[1], dA.shape[1], window.shape[1]
    m_sub = (fine.shape[2] - 1) // T  # fine holds M leading zeros and (T - 1) M + 1 samples
    n_col = 1 + n_params + (n if with_x0 else 0)
    dev = A.device

    lam, V, V_inv, cond, ok, omega = _modes(A, scale)
    n_slot = omega.shape[1]  # K: the modes 0..K-1 are propagated
    n_real = 4 * n_slot * (m + 1)  # basis columns from the recursion: (channel, kind, slot, Re/Im)
    n_t = 0 if targets is None else o
    width = n_real + m + n_t + (m + n_t) % 2  # Z is a complex view of the buffer below: an even row width
    # rows of coef_all: (Z | w | targets | 0), columns (output, column of the result)
    if _compiled_applies(V):
        coef_all, ok = _compiled_coefficients(
            lam, V, V_inv, cond, ok, matrices, derivatives, x0, with_x0, omega, n_t, width, (_LIMIT, _LIMIT_REAL)
        )
    else:
        coef_all, ok = _coefficients(lam, V, V_inv, cond, ok, matrices, derivatives, x0, with_x0, omega, n_t, width)
    lam_s = lam[:, :n_slot]

    # The basis by one scalar recursion per slot: Z [T, b, 1 + m, 2, K] complex (time first: 5x
    # faster steps than batch first), channel 0 = (e, f) (start (1, 0), no
    # forcing), 1 + c = (psi_c, chi_c); in each, (z, dz/dlambda) obey z_{k+1} = mu z_k + F_k,
    # dz_{k+1} = mu dz_k + h z_{k+1} + (F'_k - h F_k). F_k for all k is one product per sample
    # (row k + 1; row 0, from the padding, is overwritten by the start) written straight into the
    # time-first buffer, and the final product reads the buffer batch first as it is; the input
    # samples w are columns of the same buffer (padded to an even width: Z is a complex view).
    ell, dell = _hold_weights(lam_s, h, hold, m_sub)  # [M + 1, b, K]
    # channel 0 has no forcing: the product fills the columns of the channels 1 + c alone
    n_free = 4 * n_slot  # columns of channel 0
    weights = torch.zeros(batch, m, m_sub + 1, m, 2, n_slot, 2, dtype=torch.float64, device=dev)
    for c in range(m):  # [b, (c, j), (channel - 1, kind, slot, re/im)]
        weights[:, c, :, c] = torch.view_as_real(torch.stack([ell, dell - h * ell], 2)).transpose(0, 1)
    buffer = _basis_buffer(T, batch, width, dev)  # [k, b, (Z | w | 0)]
    buffer[:, :, :n_free] = 0
    buffer[:, :, n_real : n_real + m] = window.transpose(0, 1)
    if n_t:
        buffer[:, :, n_real + m : n_real + m + o] = targets.transpose(0, 1)
    buffer[:, :, n_real + m + n_t :] = 0
    _matmul(
        _held_rows(fine, T),
        weights.view(batch, m * (m_sub + 1), n_real - n_free),
        out=buffer[:, :, n_free:n_real].transpose(0, 1),
    )
    Z = torch.view_as_complex(buffer[:, :, :n_real].view(T, batch, 1 + m, 2, n_slot, 2))
    Z[0] = 0
    Z[0, :, 0, 0] = 1
    # mu [b, 1 + m, 2, K], expanded: a broadcast operand makes the multiply-add 1.6x slower
    _scan(Z, (lam_s * h)[:, None, None, :].expand(-1, 1 + m, 2, -1), h)
    out = _matmul(buffer.transpose(0, 1), coef_all)
    return out.view(batch, T, o, n_col), ok


def modal_outputs(
    matrices: tuple[Tensor, Tensor, Tensor, Tensor],
    scale: Tensor,
    x0: Tensor | None,
    fine: Tensor,
    window: Tensor,
    h: float,
    hold: str,
) -> tuple[Tensor, Tensor]:
    """-> (y [b, T, o] as exact_outputs, ok [b] bool): modal_sensitivities' column 0 alone,

        y_k = gamma (e_k xi0 + sum_c beta_c psi_{k,c}) + E w_k,

    so only e and psi are propagated (no derivatives, one complex multiply-add per step). The
    arguments and ``ok`` as in modal_sensitivities."""
    A, B, C, E = matrices
    batch, n, m = B.shape
    o, T = C.shape[1], window.shape[1]
    m_sub = (fine.shape[2] - 1) // T
    dev = A.device
    lam, V, V_inv, cond, ok, omega = _modes(A, scale)
    ok &= cond <= _LIMIT_OUTPUTS
    n_slot = omega.shape[1]
    lam_s = lam[:, :n_slot]
    # complex coefficients [b, channel, slot, o]: channel 0 = e (only with x0), 1 + c = psi_c
    first = 0 if x0 is not None else 1
    gamma = _matmul(C.to(_CDTYPE), V[:, :, :n_slot]).transpose(1, 2)  # [b, K, o]
    V_inv_s = V_inv[:, :n_slot]  # [b, K, n]
    drive = [] if x0 is None else [V_inv_s @ x0.to(_CDTYPE)[..., None]]  # xi0 of the kept modes, [b, K, 1]
    drive = torch.cat(drive + [V_inv_s @ B.to(_CDTYPE)], 2).transpose(1, 2)  # [b, channel, K]
    coef = (drive[..., None] * gamma[:, None]).conj() * omega[:, None, :, None]
    n_ch = 1 + m - first
    n_real = 2 * n_slot * n_ch
    width = n_real + m + m % 2  # Z is a complex view of the buffer: an even row width
    coef_all = torch.zeros(batch, width, o, dtype=torch.float64, device=dev)
    coef_all[:, :n_real] = torch.view_as_real(coef).transpose(-1, -2).reshape(batch, n_real, o)
    coef_all[:, n_real : n_real + m] = E.transpose(1, 2)
    ok &= torch.isfinite(coef_all.sum((1, 2)))

    # psi by the recursion of modal_sensitivities (without chi), e = mu^k by the same recursion
    # started at 1 without forcing; the buffer [T, b, (Z | w | 0)] as there
    ell, _ = _hold_weights(lam_s, h, hold, m_sub)  # [M + 1, b, K]
    n_free = 2 * n_slot * (1 - first)  # columns of e (no forcing), left out of the product
    weights = torch.zeros(batch, m, m_sub + 1, m, n_slot, 2, dtype=torch.float64, device=dev)
    for c in range(m):  # [b, (c, j), (channel psi_c, slot, re/im)]
        weights[:, c, :, c] = torch.view_as_real(ell).transpose(0, 1)
    buffer = _basis_buffer(T, batch, width, dev)
    buffer[:, :, :n_free] = 0
    buffer[:, :, n_real : n_real + m] = window.transpose(0, 1)
    buffer[:, :, n_real + m :] = 0
    _matmul(
        _held_rows(fine, T),
        weights.view(batch, m * (m_sub + 1), n_real - n_free),
        out=buffer[:, :, n_free:n_real].transpose(0, 1),
    )
    Z = torch.view_as_complex(buffer[:, :, :n_real].view(T, batch, n_ch, n_slot, 2))
    Z[0] = 0
    if x0 is not None:
        Z[0, :, 0] = 1
    _scan(Z, (lam_s * h)[:, None, :].expand(-1, n_ch, -1))  # [b, channel, K], as there
    return _matmul(buffer.transpose(0, 1), coef_all), ok


def _scan(Z: Tensor, rate: Tensor, h: float | None = None) -> None:
    """In place: Z[k] <- mu Z[k - 1] + Z[k] for k = 1..T-1, mu = exp(``rate``) (Z [T, *shape] complex, rate
    [*shape]); with ``h`` each row holds pairs (z, dz) on its axis -2 and dz[k] <- dz[k] + h z[k] follows
    every step (dz = dz/d lambda of the same recursion, modal_sensitivities).

    Blocked, so that the Python loop runs ~3 sqrt(T) vector steps instead of T (at a few recordings a call
    the steps' overhead was the evaluation's cost): the recursion within blocks of L rows from a zero carry
    (L steps over all blocks at once), then the blocks' last rows in order (T / L steps: the true end of
    block j is its own plus M^L times block j - 1's), then every row's share of the previous block's end,
    M^(i+1) c, in one product, where M^i = mu^i [[1, 0], [i h, 1]] acts on (z, dz) (mu^i for z alone). The
    same sums as the step recursion in another order; the powers of mu are exp(i rate), not repeated
    products.

    On the CPU in complex128 the plain steps run compiled instead (_kernels.py), the steps' cost gone."""
    if _compiled_applies(Z):
        _compiled_scan(Z, rate, h)
        return
    T = Z.shape[0]
    block = max(1, math.isqrt(T))
    n_blocks = T // block if Z[0].numel() <= _SCAN_ROW else 0  # a long row: the plain steps are cheaper
    full = n_blocks * block
    mu = torch.exp(rate).contiguous()
    if n_blocks >= 2:
        body = Z[:full].unflatten(0, (n_blocks, block))  # [n_blocks, L, *shape] (a view)
        mu_blocks = mu.expand(n_blocks, *mu.shape).contiguous()  # a broadcast operand is 1.6x slower
        if h is not None:  # a block's first row is a step's result too: its dz takes h times its own z
            body[1:, 0, ..., 1, :].add_(body[1:, 0, ..., 0, :], alpha=h)
        for i in range(1, block):
            _step(body[:, i], body[:, i - 1], mu_blocks, h)
        steps = torch.arange(1, block + 1, dtype=torch.float64, device=Z.device).view(-1, *(1,) * mu.dim())
        powers = torch.exp(steps * rate)  # mu^(i+1) [L, *shape]
        ends = body[:, block - 1]  # [n_blocks, *shape]
        for j in range(1, n_blocks):
            ends[j] += _carry(ends[j - 1], powers[-1], block * h if h is not None else None)
        shares = _carry(ends[:-1, None], powers[None, :-1], None if h is None else steps[:-1] * h)
        body[1:, : block - 1] += shares
    start = full if n_blocks >= 2 else 1
    for k in range(start, T):
        _step(Z[k], Z[k - 1], mu, h)


def _step(nxt: Tensor, prev: Tensor, mu: Tensor, h: float | None) -> None:
    """In place, one step of _scan: nxt <- mu prev + nxt (then dz += h z with ``h``)."""
    nxt.addcmul_(prev, mu)
    if h is not None:
        nxt[..., 1, :].add_(nxt[..., 0, :], alpha=h)


def _carry(c: Tensor, power: Tensor, lag) -> Tensor:
    """M^i c of _scan: mu^i c, and with the pairs (``lag`` = i h, a number or broadcastable) dz gets
    mu^i i h z besides."""
    out = power * c
    if lag is not None:
        out[..., 1, :] += (lag[..., 0, :] if torch.is_tensor(lag) else lag) * out[..., 0, :]
    return out
