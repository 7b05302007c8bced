"""The Fisher information of the static mass from one finite window of a3 and a2, in the time domain.

The frequency-domain bound of bench/occupant_crb.py (``--domain dft``) treats the window as periodic: per DFT bin
A3_k = H_k A2_k exactly. A recording is a cut out of a drive, so |A2_k|² of the window holds the leakage of its
edges (a 1-2 Hz chassis motion cut at both ends spreads power over every bin, to the seat's 4-6 Hz as well), and the
transient the window starts with (the seat's unknown state) costs information that no bin accounts for. Both make
that bound too small: on 100 rigid recordings of 5 s (noise on a3) the finite window's bound below is 1.08-1.11x
the periodic one at the median and 1.19x on average (`occupant_crb.py FILE --domain time` against `--domain dft`;
bench/bound_check.py puts the estimator beside both). This module is the bound of the
model the estimator fits, on the samples it sees:

    y = T(θ) u + O(θ) x0 + (noise),    u the a2 samples [N], y the a3 samples [N],

T(θ) [N, N] lower-triangular Toeplitz, the map from a2 samples to a3 samples of the seat's transfer function
H(θ, s) with a first-order hold between samples (scipy's ``cont2discrete(..., 'foh')``: exact for a piecewise-linear
input; the estimator's quintic spline differs from it by < 1 % in amplitude below 10 Hz), O(θ) [N, n] the
free responses of H's n states (everything before the window, the hold of the sample before it too, leaves a state),
x0 unknown. With white noise of standard deviation s3 on a3 and s2 on a2 (errors in variables; the true input is
a nuisance parameter per sample and is profiled out: Woodbury turns the joint information into that of θ under the
residual's covariance)

    Σ = s3² I + s2² T Tᵀ,    J = Gᵀ Σ⁻¹ G,    G = [∂y/∂log θ_j (P columns), ∂y/∂τ (delay unknown), O]

and the relative variance of M = K3 / p2 is (J⁻¹)_{p2 p2}. ∂y/∂log θ_j by central differences of T and O; the
delay's column is -T u̇ (u̇ by central differences of the samples: the model's input delayed by τ). ``floor2``: a
measured a2 that holds white noise of that standard deviation puts E[nᵀ D_iᵀ Σ⁻¹ D_j n] = floor2² tr(D_iᵀ Σ⁻¹ D_j)
into J (D_j = ∂T/∂log θ_j, the delay's -T ∂), which is taken off so that the noise floor adds no information.

Transfer functions as polynomial ratios (``polynomials``), the same closed forms as occupant_crb.transfer:
rigid (p1 s + p2) / (s² + p1 s + p2); body1 with T_b = (c s + k)/(s² + c s + k) and the apparent mass
(1 + r T_b)/(1 + r); body2 the series chain of occupant_crb.transfer.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.signal

_P = np.polynomial.polynomial  # coefficient arrays lowest power first here; scipy wants highest first


def polynomials(model: str, theta) -> tuple[np.ndarray, np.ndarray]:
    """(numerator, denominator) of H(θ, s), highest power first (scipy's order)."""
    theta = np.asarray(theta, dtype=float)
    p1, p2 = theta[0], theta[1]
    seat = np.array([p2, p1])  # p1 s + p2
    s2 = np.array([0.0, 0.0, 1.0])
    if model == "rigid":
        num, den = seat, _P.polyadd(s2, seat)
    elif model == "body1":
        r, k, c = theta[2:5]
        nt, dt = np.array([k, c]), np.array([k, c, 1.0])
        num = (1 + r) * _P.polymul(seat, dt)
        den = _P.polyadd(_P.polymul(s2, _P.polyadd(dt, r * nt)), num)
    elif model == "body2":
        r_a, r_b, k_a, c_a, k_b, c_b = theta[2:8]
        nb, db = np.array([k_b, c_b]), np.array([k_b, c_b, 1.0])
        upper = _P.polyadd(r_a * db, r_b * nb)  # (r_a + r_b T_b) D_b
        za = r_a * np.array([k_a, c_a])
        inner = _P.polyadd(_P.polymul(s2, upper), _P.polymul(za, db))  # (s² upper + z_a) D_b
        na = _P.polyadd(inner, _P.polymul(upper, za))
        da = (1 + r_a + r_b) * inner
        num = _P.polymul(seat, da)
        den = _P.polyadd(_P.polymul(s2, na), num)
    else:
        raise ValueError(f"window_fisher: model {model!r}: rigid, body1 or body2")
    return np.trim_zeros(num, "b")[::-1], np.trim_zeros(den, "b")[::-1]


def _matrices(model: str, theta, n: int, h: float) -> tuple[np.ndarray, np.ndarray]:
    """T [n, n] (first-order hold, Toeplitz) and O [n, order] (the free responses: what the samples before the window
    leave in the seat, the first sample's hold into the window's first interval as well)."""
    num, den = polynomials(model, theta)
    num_d, den_d, _ = scipy.signal.cont2discrete((num, den), h, method="foh")
    impulse = np.zeros(n)
    impulse[0] = 1.0
    g = scipy.signal.lfilter(np.ravel(num_d), den_d, impulse)  # response to one sample: [n]
    T = scipy.linalg.toeplitz(g, np.zeros(n))
    A, _, C, _ = scipy.signal.tf2ss(num, den)
    lam, V = np.linalg.eig(A)  # distinct poles (damped modes): C e^{A t} = C V e^{Λ t} V⁻¹
    modes = np.exp(np.outer(np.arange(n) * h, lam)) * (C @ V)
    return T, np.real(modes @ np.linalg.inv(V))


def relative_sds(
    model: str,
    theta,
    a2: np.ndarray,
    a3: np.ndarray,
    s3: float,
    s2: float,
    h: float,
    floor2: float = 0.0,
    eps: float = 1e-6,
    prior_sd=None,
) -> tuple[float, float]:
    """(σ_M/M with the delay known, with it unknown) from one window: a2, a3 [N] the samples (a3 only sets the
    transient's x0, by least squares), s3, s2 the white noise's standard deviations on a3 and a2 (errors in
    variables; 0 for a noise-free channel), floor2 the noise already in the given a2 (module docstring). inf where
    θ is not identifiable from this window. prior_sd [P]: a Gaussian prior's standard deviation on each θ_j (NaN: none),
    whose information (θ_j / sd_j)² on log θ_j is added (the bound of an estimator that knows that prior)."""
    a2 = np.asarray(a2, dtype=float)
    n = len(a2)
    theta = np.asarray(theta, dtype=float)
    P = len(theta)
    T, O = _matrices(model, theta, n, h)
    x0 = np.linalg.lstsq(O, np.asarray(a3, dtype=float) - T @ a2, rcond=None)[0]
    cols, D = [], []
    for j in range(P):
        up, down = theta.copy(), theta.copy()
        up[j] *= np.exp(eps)
        down[j] *= np.exp(-eps)
        (Tu, Ou), (Td, Od) = _matrices(model, up, n, h), _matrices(model, down, n, h)
        D.append((Tu - Td) / (2 * eps))
        cols.append(D[-1] @ a2 + (Ou - Od) @ x0 / (2 * eps))
    D.append(-1e-3 * T @ _gradient_matrix(n, h))  # the delay τ in ms: the input delayed, -T u̇
    cols.append(D[-1] @ a2)
    G = np.column_stack([*cols, O])
    factor = scipy.linalg.cho_factor(s3**2 * np.eye(n) + s2**2 * (T @ T.T))
    J = G.T @ scipy.linalg.cho_solve(factor, G)
    if floor2 > 0:
        for j, dj in enumerate(D):
            solved = scipy.linalg.cho_solve(factor, dj)
            for i in range(j + 1):
                J[i, j] -= floor2**2 * np.sum(D[i] * solved)
                J[j, i] = J[i, j]
    if prior_sd is not None:
        with np.errstate(invalid="ignore"):
            info = np.nan_to_num((theta / np.asarray(prior_sd, dtype=float)) ** 2)
        J[np.arange(P), np.arange(P)] += info
    known = np.delete(np.delete(J, P, axis=0), P, axis=1)
    return _sd_p2(known), _sd_p2(J)


def relative_sd(
    model: str, theta, a2, a3, s3: float, s2: float, h: float, delay_unknown: bool, floor2=0.0, prior_sd=None
) -> float:
    """One of :func:`relative_sds`' two bounds."""
    return relative_sds(model, theta, a2, a3, s3, s2, h, floor2, prior_sd=prior_sd)[int(delay_unknown)]


def _sd_p2(J: np.ndarray) -> float:
    """sqrt((J⁻¹)_11), inverted at unit diagonal: the columns differ by orders of magnitude (a free response
    against ∂y/∂log θ); inf where J is not positive definite (θ not identifiable, or the floor took all)."""
    scale = 1.0 / np.sqrt(np.clip(np.diag(J), 1e-300, None))
    Js = J * np.outer(scale, scale)
    if np.linalg.eigvalsh(0.5 * (Js + Js.T)).min() <= 1e-12:
        return float("inf")
    return float(np.sqrt(np.linalg.inv(Js)[1, 1]) * scale[1])


def _gradient_matrix(n: int, h: float) -> np.ndarray:
    """[n, n] central differences (one-sided at the ends): the samples' time derivative, np.gradient's rule."""
    d = np.zeros((n, n))
    i = np.arange(1, n - 1)
    d[i, i + 1], d[i, i - 1] = 0.5 / h, -0.5 / h
    d[0, :2] = (-1 / h, 1 / h)
    d[-1, -2:] = (-1 / h, 1 / h)
    return d
