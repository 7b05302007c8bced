"""The residual's noise model in the frequency domain: weighting, whitening and errors in variables.

A fit's residual at the true parameters is the measurement noise *as the model sees it*. With
white noise n_o on the outputs and a noise-free input that is n_o itself; when the driving input
is measured too (the road-free base-excitation models: the seat driven by the measured a2), the
input noise n_i passes through the model, and at a candidate p the residual is

    r = y~ - H(p) * w~   =   (y - H(p) * w)   +   n_o - H(p) * n_i,

whose noise part is coloured with spectral density matrix (per frequency, [o, o])

    S_k(p) = diag(v_out) + H_k(p) diag(v_in) H_k(p)^H,     H_k(p) = C (j w_k I - A)^-1 B + E

(v_out, v_in: per-sample noise variances of each output and input channel, w_k = 2 pi k / (T h)).
An output-error fit that ignores this weights every frequency alike: its standard deviations are
wrong and its residual fails any whiteness test. The errors-in-variables maximum-likelihood cost in
the frequency domain (Pintelon & Schoukens, *System Identification*, ch. 10, "sample maximum
likelihood")

    L(p) = 1/2 sum_{k >= 1} c_k R_k^H S_k(p)^-1 R_k / T,       R_k = DFT(r)_k

is consistent: E[R_k R_k^H] = T (S_k(p) + signal misfit), so the noise part of E[L] does not depend
on p and the minimum sits at the truth — provided S keeps its p-dependence. (Freezing S at the
previous iterate brings back a bias towards smaller |H|, as in the output-error fit.) c_k are the
Parseval weights of the one-sided spectrum (2, and 1 at Nyquist). The DC term is left out (c_0 = 0):
a constant accelerometer bias on any channel reaches the residual only there — an output bias
directly, an input bias as H(0) b after the transient that the estimated initial state absorbs —
so the fit is exactly invariant to sensor offsets.

Least-squares form. With the Cholesky factor S_k = L_k L_k^H the cost is 1/2 ||e||^2 for the
whitened residual e_k = L_k^-1 R_k, whose derivative (dL from the Cholesky derivative
dL = L Phi(L^-1 dS L^-H), Phi = lower triangle with half the diagonal) is

    de_k = L_k^-1 dR_k - Phi(M_k) e_k,       M_k = L_k^-1 dS_k L_k^-H,
    dS_k = dH_k V_in H_k^H + H_k V_in dH_k^H,   dH = Y dA X + Y dB + dC X + dE,
    X = (j w I - A)^-1 B,  Y = C (j w I - A)^-1,

so Gauss-Newton, Armijo, the status tests and the Laplace covariance of the solver all work
unchanged on the real stack of (Re e_k, Im e_k) sqrt(c_k / T). Back in the time domain (inverse
DFT of e with its DC set to zero) the whitened residual of a model that fits is white with the
same variance in every channel, which is what the solver's Ljung-Box misfit test assumes.
Without input noise S_k = diag(v_out) at every frequency, and the stack's sums of squares and
products are those of the time-domain rows (r_t - mean r) / sqrt(v_out) (Parseval, c_0 = 0): the
normal equations and the losses use these (``frequency_rows=False``), without a DFT; only the
spectral score groups of the sandwich covariance need the stack's rows themselves.

The variances are not known to a user; :func:`estimate_variances` fits them to the residual's
periodogram P_k = R_k R_k^H / T at a preliminary estimate by Whittle's likelihood
(sum_k tr(S_k^-1 P_k) + log det S_k; Fisher scoring, S linear in v). They are identifiable because
|H_k| varies over frequency: the seat passes a2 below its resonance and blocks it above, so the
high band measures v_out and the low band v_out + v_in. Circularity: the DFT treats the window as
periodic; the linear-convolution edge effect is O(impulse-response length / T) and shrinks with T.

Shapes: b batch, T samples in the window, K = T // 2 + 1 frequencies, o outputs, m inputs,
P physical parameters, Q = n_theta >= P (the rest are initial states, on which S does not depend).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybridqcm.physics.linear_models import LinearModel

from ._expm import balance
from ._kernels import applies as _compiled_applies
from ._kernels import one_channel_response as _compiled_response
from ._modal import _eigen

_COMPLEX = torch.complex128
# cond(V) (balanced, 1-norm) above which frequency_response solves per frequency: the modal form's rounding is
# about cond(V) eps, 2e-10 relative here (the noise model's weights need far less)
_RESPONSE_COND = 1e6


def parseval_weights(n_steps: int, dtype=torch.float64) -> Tensor:
    """c_k [K]: weight of frequency k in sum_t r_t^2 = (1/T) sum_k c_k |R_k|^2, with c_0 = 0 (DC dropped)."""
    K = n_steps // 2 + 1
    c = torch.full((K,), 2.0, dtype=dtype)
    c[0] = 0.0
    if n_steps % 2 == 0:
        c[-1] = 1.0
    return c


def frequency_response(
    model: LinearModel, params: Tensor, omega: Tensor, derivatives: bool = False
) -> tuple[Tensor, Tensor | None]:
    """H [b, K, o, m] = C (j w I - A)^-1 B + E at the angular frequencies ``omega`` [K] (rad/s),
    and with ``derivatives`` dH [b, P, K, o, m] = dH/dp_j (else None).

    dH_j = Y dA_j X + Y dB_j + dC_j X + dE_j with X = (j w I - A)^-1 B, Y = C (j w I - A)^-1. Beyond the
    2-state seat (closed form) both come from A = V diag(lambda) V^-1, once per sample instead of a
    solve per sample and frequency: X = V diag(g) V^-1 B, Y = C V diag(g) V^-1, g_i = 1 / (j w - lambda_i),
    and Y dA_j X = (C V) diag(g) (V^-1 dA_j V) diag(g) (V^-1 B). Its rounding grows like cond(V) eps only
    (no eigenvalue differences are divided by); samples whose eigenvectors are worse conditioned than
    _RESPONSE_COND (near a defective A, a critically damped mode) are solved per frequency by LU."""
    A, B, C, E = model.matrices(params.double())
    jw = (1j * omega.to(torch.float64)).to(_COMPLEX)
    if A.shape[-1] == 2:
        return _response_2x2(model, params, A, B, C, E, jw, derivatives)
    lam, V, V_inv, cond, ok = _eigen(A, balance(A))
    good = ok & (cond <= _RESPONSE_COND)
    rows = torch.nonzero(good).flatten()
    if rows.numel() == A.shape[0]:
        return _response_modal(model, params, lam, V, V_inv, (B, C, E), jw, derivatives)
    H = torch.empty(A.shape[0], jw.numel(), C.shape[-2], B.shape[-1], dtype=_COMPLEX, device=A.device)
    dH = torch.empty(A.shape[0], model.n_params, *H.shape[1:], dtype=_COMPLEX, device=A.device) if derivatives else None
    rest = torch.nonzero(~good).flatten()
    parts = [(rest, _response_lu(model, params[rest], (A[rest], B[rest], C[rest], E[rest]), jw, derivatives))]
    if rows.numel():
        sub = (B[rows], C[rows], E[rows])
        parts.append(
            (rows, _response_modal(model, params[rows], lam[rows], V[rows], V_inv[rows], sub, jw, derivatives))
        )
    for index, (h, dh) in parts:
        H[index] = h
        if derivatives:
            dH[index] = dh
    return H, dH


def _response_2x2(model, params, A, B, C, E, jw, derivatives):
    """frequency_response of a 2-state model by the adjugate, elementwise (a batched LAPACK call per 2x2 costs more)."""
    A, B, C, E = (x.to(_COMPLEX) for x in (A, B, C, E))
    a, b_, c, d = (-A[:, None, i, j] for i in range(2) for j in range(2))  # [b, 1] off-diagonals
    a, d = a + jw, d + jw  # [b, K]
    inv_det = 1.0 / (a * d - b_ * c)
    rows = ((d * inv_det, -b_ * inv_det), (-c * inv_det, a * inv_det))  # (j w I - A)^-1, [b, K] each
    Bk, Ck = B[:, None], C[:, None]  # [b, 1, n, m], [b, 1, o, n]
    X = torch.stack([r[0][..., None] * Bk[:, :, 0] + r[1][..., None] * Bk[:, :, 1] for r in rows], 2)
    if not derivatives:
        return Ck[..., 0:1] * X[:, :, None, 0] + Ck[..., 1:2] * X[:, :, None, 1] + E[:, None], None
    Y = torch.stack([Ck[..., 0] * rows[0][l][..., None] + Ck[..., 1] * rows[1][l][..., None] for l in range(2)], -1)
    return C[:, None] @ X + E[:, None], _derivative_products(model, params, Y, X)


def _response_lu(model, params, matrices, jw, derivatives):
    """frequency_response by one LU per sample and frequency (the samples the modal form would lose digits on).
    A model with a pole on the axis (a trial step to a singular A) has no response there: NaN, so that the
    trial's loss is not finite and the line search rejects it, rather than an exception."""
    A, B, C, E = (x.to(_COMPLEX) for x in matrices)
    n, K = A.shape[-1], jw.numel()
    pencil = jw[None, :, None, None] * torch.eye(n, dtype=_COMPLEX) - A[:, None]  # [b, K, n, n]
    if not derivatives:
        X, info = torch.linalg.solve_ex(pencil, B[:, None].expand(-1, K, -1, -1))  # [b, K, n, m]
        X = torch.where((info == 0)[..., None, None], X, torch.full_like(X, complex(math.nan, math.nan)))
        return C[:, None] @ X + E[:, None], None
    LU, pivots, info = torch.linalg.lu_factor_ex(pencil)  # one LU for both sides
    X = torch.linalg.lu_solve(LU, pivots, B[:, None].expand(-1, K, -1, -1))
    Y = torch.linalg.lu_solve(LU, pivots, C[:, None].expand(-1, K, -1, -1), left=False)  # [b, K, o, n]
    bad = (info != 0)[..., None, None]
    X = torch.where(bad, torch.full_like(X, complex(math.nan, math.nan)), X)
    Y = torch.where(bad, torch.full_like(Y, complex(math.nan, math.nan)), Y)
    return C[:, None] @ X + E[:, None], _derivative_products(model, params, Y, X)


def _derivative_products(model, params, Y, X):
    """dH [b, P, K, o, m] = Y dA X + Y dB + dC X + dE from Y [b, K, o, n] and X [b, K, n, m]."""
    dA, dB, dC, dE = (d.to(_COMPLEX) for d in model.matrix_derivatives(params.double()))  # [b, P, ...]
    return (
        torch.einsum("bkoi,bpil,bklm->bpkom", Y, dA, X)
        + torch.einsum("bkoi,bpim->bpkom", Y, dB)
        + torch.einsum("bpol,bklm->bpkom", dC, X)
        + dE[:, :, None]
    )


def _response_modal(model, params, lam, V, V_inv, matrices, jw, derivatives):
    """frequency_response from A = V diag(lam) V^-1 (frequency_response's docstring). Shapes as there; u = C V diag(g)
    [b, K, o, n] and w = diag(g) V^-1 B [b, K, n, m] are Y's and X's modal coordinates, and every product runs over
    (K, o, m) rows at once."""
    if matrices[0].shape[-1] * matrices[1].shape[-2] == 1 and _compiled_applies(lam):
        return _response_one_channel(model, params, lam, V, V_inv, matrices, jw, derivatives)
    B, C, E = (x.to(_COMPLEX) for x in matrices)
    # g = 1 / (j w - lam) = (re - j im) / (re² + im²) [b, K, n], by real arithmetic (torch's complex division: 2x)
    re = (-lam.real)[:, None, :].expand(-1, jw.numel(), -1)
    im = jw.imag[None, :, None] - lam.imag[:, None, :]
    inv = 1.0 / (re * re + im * im)
    CV, WB = C @ V, V_inv @ B  # [b, o, n], [b, n, m]
    o, m = CV.shape[1], WB.shape[2]
    g = torch.complex(re * inv, -im * inv) if derivatives or o * m > 1 else None
    if o * m == 1:  # H = E + Σ_i r_i g_i with the residues r = (C V)_i (V^-1 B)_i, elementwise in real arithmetic
        r = CV[:, 0] * WB[..., 0]  # [b, n]
        real = ((r.real[:, None] * re + r.imag[:, None] * im) * inv).sum(-1)
        imag = ((r.imag[:, None] * re - r.real[:, None] * im) * inv).sum(-1)
        H = (torch.complex(real, imag)[..., None, None] + E[:, None]).contiguous()
    else:  # the residues [b, n, (o, m)] times g
        residues = (CV.transpose(1, 2)[..., :, None] * WB[:, :, None, :]).reshape(CV.shape[0], -1, o * m)
        H = (g @ residues).view(*g.shape[:2], o, m) + E[:, None]
    # an eigenvalue on the axis (a trial step to a singular A): no response there, NaN as the LU path gives
    H = torch.where(torch.isfinite(H), H, torch.full_like(H, complex(math.nan, math.nan)))
    if not derivatives:
        return H, None
    u = CV[:, None] * g[:, :, None, :]  # [b, K, o, n]
    dA, dB, dC, dE = (d.to(_COMPLEX) for d in model.matrix_derivatives(params.double()))  # [b, P, ...]
    b, K, o, n = u.shape
    m, P = B.shape[-1], dA.shape[1]
    w = (g[..., None] * WB[:, None]).transpose(-1, -2)  # [b, K, m, n] (w transposed)
    modal_dA = (V_inv[:, None] @ dA @ V[:, None]).reshape(b, P, n * n)  # V^-1 dA_j V, (i, l) flattened
    outer = (u[:, :, :, None, :, None] * w[:, :, None, :, None, :]).reshape(b, K * o * m, n * n)  # u_oi w_ml
    dH = (outer @ modal_dA.transpose(1, 2)).view(b, K, o, m, P)
    modal_dB = (V_inv[:, None] @ dB).permute(0, 2, 1, 3).reshape(b, n, P * m)  # V^-1 dB_j, [b, n, (P, m)]
    dH = dH + (u.reshape(b, K * o, n) @ modal_dB).view(b, K, o, P, m).transpose(-1, -2)
    modal_dC = (dC @ V[:, None]).permute(0, 3, 1, 2).reshape(b, n, P * o)  # dC_j V, [b, n, (P, o)]
    dH = dH + (w.reshape(b, K * m, n) @ modal_dC).view(b, K, m, P, o).permute(0, 1, 4, 2, 3)
    return H, dH.permute(0, 4, 1, 2, 3) + dE[:, :, None]


def _response_one_channel(model, params, lam, V, V_inv, matrices, jw, derivatives):
    """_response_modal for one output and one input (the road-free seat) by a compiled loop per sample and frequency
    (_kernels.one_channel_response: H by the same sums; dH_j as a sum over the symmetric products g_i g_l, n (n + 1) / 2
    a frequency instead of n^2; the derivatives' modal terms formed here), instead of [b, K, n^2] tensors and their
    batched products."""
    B, C, E = matrices
    CV = (C.to(_COMPLEX) @ V)[:, 0]  # [b, n]
    WB = (V_inv @ B.to(_COMPLEX))[..., 0]  # [b, n]
    modal = None
    if derivatives:
        dA, dB, dC, dE = (d.to(_COMPLEX) for d in model.matrix_derivatives(params.double()))  # [b, P, ...]
        modal = ((V_inv[:, None] @ dA @ V[:, None]), (V_inv[:, None] @ dB)[..., 0], (dC @ V[:, None])[:, :, 0],
                 dE[:, :, 0, 0].real)  # fmt: skip
    H, dH = _compiled_response(lam, CV, WB, E[:, 0, 0], jw.imag, modal)
    H = H[:, :, None, None]
    # an eigenvalue on the axis (a trial step to a singular A): no response there, NaN as the LU path gives
    H = torch.where(torch.isfinite(H), H, torch.full_like(H, complex(math.nan, math.nan)))
    return H, (None if dH is None else dH[..., None, None])


def spectral_matrix(H: Tensor | None, v_out: Tensor, v_in: Tensor | None) -> Tensor:
    """S [b, K, o, o] = diag(v_out) + H diag(v_in) H^H; v_out [b, o], v_in [b, m] or None (no input noise)."""
    o = v_out.shape[1]
    K = 1 if H is None else H.shape[1]
    S = torch.diag_embed(v_out.to(_COMPLEX))[:, None].expand(-1, K, o, o)
    if H is not None and v_in is not None:
        S = S + (H * v_in.to(_COMPLEX)[:, None, None, :]) @ H.conj().transpose(-1, -2)
    return S


def _cholesky(S: Tensor) -> Tensor:
    """L [b, K, o, o] with S = L L^H per frequency; NaN for a sample whose S is not positive definite at some
    frequency (a trial step run off to a response that overflows): its loss is then not finite, which the line
    search counts as a failed trial, as the one-output path's square root does, instead of stopping the run."""
    L, info = torch.linalg.cholesky_ex(S)
    bad = (info != 0).flatten(1).any(1)
    if bool(bad.any()):
        L = torch.where(bad.view(-1, *([1] * (L.ndim - 1))), torch.full_like(L, math.nan), L)
    return L


def _solve_psd(A: Tensor, y: Tensor, rcond: float = 1e-12) -> Tensor:
    """x [b, J] with A x = y for symmetric positive semi-definite A [b, J, J] (small J), by Gaussian
    elimination unrolled over J and vectorised over b (a batched LAPACK call costs ~10 us per
    sample here, longer than the arithmetic). A pivot below rcond x max diag(A) means the direction
    is not identified: its component of x is 0 (as the minimum-norm solution would leave it)."""
    J = A.shape[-1]
    U, rhs = A.clone(), y.clone()
    tol = rcond * A.diagonal(dim1=-2, dim2=-1).amax(-1)
    inverse = []
    for k in range(J):
        pivot = U[:, k, k]
        ok = pivot > tol
        inv = torch.where(ok, 1.0 / torch.where(ok, pivot, torch.ones_like(pivot)), torch.zeros_like(pivot))
        inverse.append(inv)
        for i in range(k + 1, J):
            factor = U[:, i, k] * inv
            U[:, i, k:] -= factor[:, None] * U[:, k, k:]
            rhs[:, i] -= factor * rhs[:, k]
    x = torch.zeros_like(rhs)
    for k in reversed(range(J)):
        x[:, k] = (rhs[:, k] - (U[:, k, k + 1 :] * x[:, k + 1 :]).sum(-1)) * inverse[k]
    return x


def estimate_variances(
    residual: Tensor,
    H: Tensor | None,
    n_inputs: int = 0,
    reference: Tensor | None = None,
    iterations: int = 30,
    floor: float = 1e-12,
    leverage: Tensor | None = None,
) -> tuple[Tensor, Tensor | None]:
    """Whittle fit of (v_out [b, o], v_in [b, m] or None) to the periodogram of ``residual`` [b, T, o].

    ``H`` [b, K, o, m] (K = T // 2 + 1) is the model's frequency response at the same p; with
    ``n_inputs`` = 0 or H None only the output variances are fitted (then v_out is each channel's
    mean square without its DC, the white-noise maximum likelihood). Variances are floored at
    ``floor`` x ``reference`` [b, o] (e.g. the measured channels' mean squares; default the
    residual's) so that an exact fit cannot give infinite weight.

    ``leverage`` [b, K]: the fit's leverage per frequency (:func:`spectral_leverage`). A residual at a
    fitted p is shorter than the noise where the model is flexible — E P_k = S_k (1 - h_k) — and the
    model is most flexible exactly where the input's noise shows (the resonance, |H| large): without
    the correction the input noise comes out 20 % low and the errors-in-variables fit drifts back
    towards the output-error bias. With it, each frequency's likelihood term weighs (1 - h_k) and reads
    P_k / (1 - h_k) (restricted likelihood; for white noise Σ c_k P_k / Σ c_k (1 - h_k)).
    """
    r = residual.to(torch.float64)
    b, T, o = r.shape
    c = parseval_weights(T)
    R = torch.fft.rfft(r, dim=1)  # [b, K, o]
    P = R[..., :, None] * R[..., None, :].conj() / T  # [b, K, o, o]
    # Per-sample frequency weights: Parseval's c_k, times (1 - h_k) for the restricted fit, whose periodogram
    # is then P_k / (1 - h_k) (a bin the fit takes whole, h_k -> 1, weighs nothing).
    cw = c[None, :].expand(b, -1)
    if leverage is not None:
        free = (1.0 - leverage.to(torch.float64)).clamp(1e-6, 1.0)
        cw = cw * free
        P = P / free[:, :, None, None]
    power = (cw[:, :, None] * P.diagonal(dim1=-2, dim2=-1).real).sum(1) / cw.sum(1, keepdim=True)  # [b, o], no DC
    scale = (power if reference is None else reference.to(torch.float64)).clamp_min(1e-300)
    lower_out = floor * scale
    if H is None or n_inputs == 0:
        return power.maximum(lower_out), None
    m = n_inputs
    gain = (c[None, :, None, None] * H.abs().square()).sum(1) / c.sum()  # [b, o, m] mean |H|^2
    # Basis of S: one unit diagonal per output, H_i H_i^H per input; S = sum_j v_j B_j.
    basis = [
        torch.diag_embed(torch.nn.functional.one_hot(torch.tensor(i), o).to(_COMPLEX))[None, None] for i in range(o)
    ]
    basis = [bj.expand(b, H.shape[1], o, o) for bj in basis]
    basis += [H[..., i, None] @ H[..., i, None].conj().transpose(-1, -2) for i in range(m)]
    Bstack = torch.stack(basis, 1)  # [b, o + m, K, o, o]
    # Start: half of each output's power to its own noise, the rest to the inputs through |H|^2.
    v = torch.cat([0.5 * power, 0.5 * power.mean(1, keepdim=True) / gain.mean(1).clamp_min(1e-300)], 1)
    lower = torch.cat([lower_out, floor * (scale.mean(1, keepdim=True) / gain.mean(1).clamp_min(1e-300))], 1)
    v = v.maximum(lower)
    weight = cw[:, None, :].to(torch.float64)
    if o == 1:  # S_k = v_1 + sum_i v_i |H_ki|^2 is real: the same scoring without complex matrices
        G = torch.cat([torch.ones_like(H[..., 0, :1].real), H[..., 0, :].abs().square()], -1)  # [b, K, J]
        G = G.transpose(1, 2).contiguous()  # [b, J, K]: the sums over frequencies run along rows
        Pk = P[..., 0, 0].real  # [b, K]
        active = torch.arange(b)
        for _ in range(iterations):  # each sample until its own step is below 1e-8 relative
            Ga, va = G[active], v[active]
            S = (Ga * va[:, :, None]).sum(1)  # [n, K]
            w = cw[active] / S.square()
            score = (Ga * (w * (Pk[active] - S))[:, None, :]).sum(-1)  # [n, J]
            info = torch.bmm(Ga * w[:, None, :], Ga.transpose(1, 2))  # [n, J, J]
            new = (va + _solve_psd(info, score)).maximum(lower[active])
            v[active] = new
            active = active[~((new - va).abs() <= 1e-8 * va).all(1)]
            if active.numel() == 0:
                break
        return v[:, :o], v[:, o:]
    for _ in range(iterations):
        S = (v.to(_COMPLEX)[:, :, None, None, None] * Bstack).sum(1)  # [b, K, o, o]
        Sinv = torch.linalg.inv(S)
        W = Sinv[:, None] @ Bstack  # S^-1 B_j, [b, J, K, o, o]
        score = (W @ (Sinv @ P - torch.eye(o, dtype=_COMPLEX))[:, None]).diagonal(dim1=-2, dim2=-1).sum(-1).real
        score = (weight * score).sum(-1)  # [b, J]
        info = torch.einsum("bjkxy,blkyx->bjlk", W, W).real
        info = (weight[:, None] * info).sum(-1)  # [b, J, J]
        step = _solve_psd(info, score)
        new = (v + step).maximum(lower)
        if bool(((new - v).abs() <= 1e-8 * v).all()):
            v = new
            break
        v = new
    return v[:, :o], v[:, o:]


def input_noise_log_std(H: Tensor, v_out: Tensor, v_in: Tensor, n_steps: int, leverage: Tensor | None = None) -> Tensor:
    """[b, m] the standard deviation of log v_in, each input noise variance as :func:`estimate_variances` fits it
    from one window: the inverse of the Whittle likelihood's Fisher information Σ_k w_k G_jk G_lk / S_k² (one
    output: S_k = v_out + Σ_i v_in,i |H_ki|², G = (1, |H_k1|², ...), w_k = c_k (1 − h_k)). The seat's
    transmissibility separates input from output noise only through the contrast of |H|², so one window
    leaves v_in uncertain by tens of per cent; a fit that treats it as known is overconfident (the
    occupant model's intervals carry it, estimation/occupant.py). Several outputs: their first is used."""
    c = parseval_weights(n_steps)[None, :]
    if leverage is not None:
        c = c * (1.0 - leverage.to(torch.float64)).clamp(1e-6, 1.0)
    gain = H[:, :, 0, :].abs().square()  # [b, K, m]
    G = torch.cat([torch.ones_like(gain[..., :1]), gain], -1)  # [b, K, 1 + m]
    S = v_out[:, :1, None].transpose(1, 2) + (gain * v_in[:, None, :]).sum(-1, keepdim=True)  # [b, K, 1]
    info = torch.einsum("bk,bkj,bkl->bjl", c.expand(G.shape[0], -1), G / S, G / S)
    cov = torch.linalg.pinv(info, hermitian=True)
    variance = cov.diagonal(dim1=1, dim2=2)[:, 1:].clamp_min(0.0)
    return variance.sqrt() / v_in.clamp_min(1e-300)


def spectral_leverage(
    jacobian: Tensor, noise: SpectralNoise | None, params: Tensor, precision: Tensor | None = None
) -> Tensor:
    """[b, K] the fit's leverage per frequency: the diagonal of the hat matrix X (XᵀX + Λ)⁻¹ Xᵀ of the
    whitened real stack X of the Jacobian ``jacobian`` [b, T, o, Q] (time domain, the free columns) at
    ``params`` [b, n_theta] under ``noise`` (None: white, equal variances), averaged over each frequency's
    real and imaginary rows and its outputs; Λ = diag(``precision`` [b, Q]) a prior's (None: none).
    Σ_k of it is the number of effectively fitted unknowns (estimate_variances' correction)."""
    b, T, o, Q = jacobian.shape
    index = torch.arange(b)
    if noise is None:
        w = (parseval_weights(T) / T).sqrt().to(_COMPLEX)
        X = torch.fft.rfft(jacobian.to(torch.float64), dim=1) * w.view(1, -1, 1, 1)
    else:
        X = noise._solve(noise._factor(index, params, T, False)[0], noise._spectrum(jacobian))
    K = X.shape[1]
    stack = torch.cat([X.real, X.imag], 1).reshape(b, 2 * K * o, Q)  # rows: (Re | Im) x frequency x output
    F = stack.transpose(1, 2) @ stack
    if precision is not None:
        F = F + torch.diag_embed(precision.to(torch.float64))
    scale = F.diagonal(dim1=1, dim2=2).clamp_min(1e-300).sqrt()
    inverse = torch.linalg.pinv(F / (scale[:, :, None] * scale[:, None, :]), hermitian=True, rtol=1e-10)
    inverse = inverse / (scale[:, :, None] * scale[:, None, :])
    h = ((stack @ inverse) * stack).sum(-1).view(b, 2, K, o).mean(-1).sum(1)  # [b, K]
    components = torch.full((K,), 2.0, dtype=torch.float64)  # real rows per frequency: Re and Im,
    if T % 2 == 0:
        components[-1] = 1.0  # Re only at Nyquist (DC has none: its rows are zero)
    return h / components


class SpectralNoise:
    """Per-solve noise model of a fit: variances of each sample's output (and input) noise.

    ``whiten_residual`` / ``whiten`` map the time-domain residual [b, T, o] (and its Jacobian columns
    [b, T, o, Q]) to the real least-squares stack [b, T', o] / [b, T', o, 1 + Q] of the module
    docstring (T' = 2 K, zero rows for DC and the imaginary parts of DC and Nyquist);
    ``white_time_residual`` gives the whitened residual back in the time domain, for the tests of
    whiteness. ``linear_model`` and ``h`` are needed only when ``v_in`` is given (input noise).
    """

    def __init__(
        self,
        v_out: Tensor,
        v_in: Tensor | None = None,
        linear_model: LinearModel | None = None,
        h: float | None = None,
        frozen_at: Tensor | None = None,
    ) -> None:
        self.v_out = v_out.to(torch.float64)
        self.v_in = None if v_in is None else v_in.to(torch.float64)
        if self.v_in is not None and (linear_model is None or h is None):
            raise ValueError("input noise (v_in) needs the linear model and the sampling interval h")
        if not (torch.isfinite(self.v_out).all() and (self.v_out > 0).all()):
            raise ValueError("output noise variances must be finite and > 0")
        if self.v_in is not None and not (torch.isfinite(self.v_in).all() and (self.v_in >= 0).all()):
            raise ValueError("input noise variances must be finite and >= 0")
        self.model = linear_model
        self.h = None if h is None else float(h)
        # S evaluated at these θ [batch, Q] and held fixed (iteratively reweighted, no dS term): its
        # factor for the whole batch is computed once per window length, not at every line-search trial.
        self.frozen_at = None if frozen_at is None else frozen_at.to(torch.float64)
        # [b, m] std of log v_in where the variances were fitted to the data (input_noise_log_std), else None
        self.v_in_log_std: Tensor | None = None
        self._frozen_factor: dict[int, Tensor] = {}

    def subset(self, rows: Tensor) -> SpectralNoise:
        """The noise model of the samples ``rows`` only (a sub-problem's)."""
        noise = SpectralNoise(
            self.v_out[rows],
            None if self.v_in is None else self.v_in[rows],
            self.model,
            self.h,
            None if self.frozen_at is None else self.frozen_at[rows],
        )
        noise.v_in_log_std = None if self.v_in_log_std is None else self.v_in_log_std[rows]
        return noise

    @property
    def has_input_noise(self) -> bool:
        return self.v_in is not None

    def omega(self, n_steps: int) -> Tensor:
        return 2 * math.pi * torch.fft.rfftfreq(n_steps, d=self.h, dtype=torch.float64)

    def _factor(self, index: Tensor, params: Tensor | None, n_steps: int, derivatives: bool):
        """Cholesky factor L [b, K, o, o] of S and, with derivatives, dS [b, P, K, o, o]."""
        v_out = self.v_out[index]
        if not self.has_input_noise:
            L = torch.diag_embed(v_out.sqrt().to(_COMPLEX))[:, None]
            return L, None
        if self.frozen_at is not None:
            if n_steps not in self._frozen_factor:
                H, _ = frequency_response(self.model, self.frozen_at[:, : self.model.n_params], self.omega(n_steps))
                self._frozen_factor[n_steps] = _cholesky(spectral_matrix(H, self.v_out, self.v_in))
            return self._frozen_factor[n_steps][index], None
        H, dH = frequency_response(self.model, params[:, : self.model.n_params], self.omega(n_steps), derivatives)
        v_in = self.v_in[index]
        if H.shape[-2] == 1:  # one output: S = v_out + sum_i v_in,i |H_i|^2 and its derivative, elementwise
            S = v_out[:, None, :] + (H.abs().square() * v_in[:, None, None, :]).sum(-1)  # [b, K, 1]
            L = S.sqrt().to(_COMPLEX)[..., None]
            if not derivatives:
                return L, None
            dS = 2 * (H.conj()[:, None] * dH * v_in[:, None, None, None, :]).real.sum(-1)  # [b, P, K, 1]
            return L, dS.to(_COMPLEX)[..., None]
        L = _cholesky(spectral_matrix(H, v_out, v_in))
        if not derivatives:
            return L, None
        HV = H * v_in.to(_COMPLEX)[:, None, None, :]  # [b, K, o, m]
        dHV = dH @ HV.conj().transpose(-1, -2)[:, None]  # dH V H^H, [b, P, K, o, o]
        return L, dHV + dHV.conj().transpose(-1, -2)

    def _spectrum(self, x: Tensor) -> Tensor:
        """rfft over time with the sqrt(c_k / T) weights: [b, T, ...] -> [b, K, ...] complex."""
        T = x.shape[1]
        w = (parseval_weights(T) / T).sqrt().to(_COMPLEX)
        X = torch.fft.rfft(x.to(torch.float64), dim=1)
        return X * w.view(1, -1, *([1] * (x.ndim - 2)))

    @staticmethod
    def _solve(L: Tensor, X: Tensor) -> Tensor:
        """L^-1 X per frequency: L [b, 1 or K, o, o] (lower), X [b, K, o, c] -> [b, K, o, c]."""
        if L.shape[-1] == 1:  # one output: a division (the batched triangular solve costs 30x more)
            return X / L
        return torch.linalg.solve_triangular(L.expand(-1, X.shape[1], -1, -1), X, upper=False)

    @staticmethod
    def _real_stack(E: Tensor) -> Tensor:
        """[b, K, ...] complex -> [b, 2K, ...] real (real parts, then imaginary parts): one copy of the interleaved
        view, twice as fast as joining the two strided halves."""
        return torch.view_as_real(E).movedim(-1, 1).reshape(E.shape[0], 2 * E.shape[1], *E.shape[2:]).contiguous()

    def _centered(self, x: Tensor, index: Tensor) -> Tensor:
        """x [b, T, o, ...] less its time mean, over sqrt(v_out) per channel: without input noise the real stack's
        sums of squares and products in the time domain (Parseval with c_0 = 0: sum_k c_k X_k conj(Y_k) / T =
        sum_t (x_t - mean x)(y_t - mean y)), without the DFT. Its rows are time steps, not frequencies."""
        scale = self.v_out[index].rsqrt().view(x.shape[0], 1, x.shape[2], *([1] * (x.ndim - 3)))
        return (x - x.mean(1, keepdim=True)) * scale

    def whiten_residual(
        self, residual: Tensor, params: Tensor | None, index: Tensor, frequency_rows: bool = True
    ) -> Tensor:
        """residual [b, T, o] at θ ``params`` [b, Q] of the samples ``index`` -> [b, 2K, o]; with ``frequency_rows``
        False and no input noise the time-domain rows of the same sums of squares, [b, T, o] (_centered)."""
        if not frequency_rows and not self.has_input_noise:
            return self._centered(residual.to(torch.float64), index)
        L, _ = self._factor(index, params, residual.shape[1], False)
        return self._real_stack(self._solve(L, self._spectrum(residual)[..., None])[..., 0])

    def whiten(self, augmented: Tensor, params: Tensor, index: Tensor, frequency_rows: bool = True) -> Tensor:
        """(R | J) [b, T, o, 1 + Q] -> the whitened (e | de/dθ) [b, 2K, o, 1 + Q]; S depends on the
        first ``n_params`` entries of θ (input noise), which adds -Phi(M) e to their columns. With
        ``frequency_rows`` False and no input noise: the time-domain rows of the same Gram, [b, T, o, 1 + Q]
        (_centered; what the normal equations need, not the spectral score groups)."""
        if not frequency_rows and not self.has_input_noise:
            return self._centered(augmented.to(torch.float64), index)
        n_steps = augmented.shape[1]
        L, dS = self._factor(index, params, n_steps, self.has_input_noise)
        E = self._solve(L, self._spectrum(augmented))  # L^-1 (R | J), [b, K, o, 1 + Q]
        if dS is not None and L.shape[-1] == 1:  # one output: S, dS real scalars per frequency, Phi(M) = dS / 2S
            ratio = (dS[..., 0, 0].real / L[..., 0, 0].real.square()[:, None]).to(E.dtype)  # [b, P, K]
            P = dS.shape[1]
            E[..., 0, 1 : 1 + P] -= 0.5 * ratio.transpose(1, 2) * E[..., 0, :1]
        elif dS is not None:
            e = E[..., 0]  # [b, K, o]
            P = dS.shape[1]
            Linv = self._solve(L, torch.eye(L.shape[-1], dtype=_COMPLEX).expand(*E.shape[:2], -1, -1))
            M = Linv[:, None] @ dS @ Linv.conj().transpose(-1, -2)[:, None]  # [b, P, K, o, o]
            phi = M.tril()
            phi = phi - 0.5 * torch.diag_embed(M.diagonal(dim1=-2, dim2=-1))
            correction = (phi @ e[:, None, :, :, None])[..., 0]  # [b, P, K, o]
            E[..., 1 : 1 + P] = E[..., 1 : 1 + P] - correction.permute(0, 2, 3, 1)
        return self._real_stack(E)

    def white_time_residual(self, residual: Tensor, params: Tensor | None, index: Tensor) -> Tensor:
        """The whitened residual back in the time domain [b, T, o] (DC removed), for the whiteness tests."""
        T = residual.shape[1]
        L, _ = self._factor(index, params, T, False)
        Rk = torch.fft.rfft(residual.to(torch.float64), dim=1)
        Rk[:, 0] = 0
        return torch.fft.irfft(self._solve(L, Rk[..., None])[..., 0], n=T, dim=1)
