"""Prototype (issue 28): the road-free seat fitted directly in the frequency domain, no time-domain simulation.

    PYTHONPATH=src .venv/bin/python bench/freq_fit.py data/persons/body1_n5.h5 --model body1 [--n 100]
        [--tile 4] [--noise 0.05] [--start ref|truth] [--prior | --no-prior] [--extra 2] [--threads 1]
        [--max-iter 100] [--decrement 1e-6] [--sigma known|fit] [--sigma-start 0.02]
    ... data/persons/rigid_n5.h5 --model rigid          ... data/persons/body1_n0.h5 --noise 0 --no-prior

Per recording, the window's samples 6..505 of a3 and a2 (the 500 the library fits), their DFTs A3_k, A2_k at
ω_k = 2π k / (N h), k = 1 .. N/2 - 1 (DC and Nyquist dropped), and the residual

    R_k = A3_k - H(θ, s_k) A2_k - T_k(γ),     s_k = j ω_k,
    T_k = Σ_{i<n+e} γ_i s̃_k^i / D(s_k)          (s̃ = s / ω_s, ω_s = 2π 10 Hz: only the basis's scale)

with T the window's transient / leakage term of a continuous-time system (Pintelon & Schoukens, System
Identification, 2nd ed., § 6.3.2), D the denominator of H and n its order, γ real. The textbook term (e = 0)
is exact for the Fourier integral over the window, not for the DFT of its samples: the rectangle rule errs at the
window's ends by the Euler-Maclaurin terms (h/2)(x(T) - x(0)), (h²/12)(x'(T) - x'(0)), ... of both channels, real
polynomials in s which over D are more degrees of the same term. ``--extra`` e = 2 (the default) takes the
first two orders: on 100 noise-free body1 windows the static mass's mean error falls from 8 % (e = 0) to 0.03 %
(started at the truth). Models, in log θ (the closed
forms of bench/occupant_crb.py ``transfer``):

* rigid, θ = (p1, p2):  H = (p1 s + p2) / (s² + p1 s + p2), n = 2;
* body1, θ = (p1, p2, r, k, c):  q = s² + c s + k,  H = (p1 s + p2) q / D,
  D = s² (s² + (1 + r)(c s + k)) / (1 + r) + (p1 s + p2) q, n = 4 (= (p1 s + p2)/(s² (1 + r T)/(1 + r) + p1 s + p2),
  T = (c s + k)/q);
* body2, θ = (p1, p2, r1, k1, c1, r2, k2, c2), two parallel modes (physics/occupant.py): g_i = c_i s + k_i,
  q_i = s² + g_i, H = (p1 s + p2) q1 q2 / D, D = s² (q1 q2 + r1 g1 q2 + r2 g2 q1) / (1 + r1 + r2) + (p1 s + p2) q1 q2,
  n = 6 (no truth in these files: cost only).

Static mass M = K3 / p2, K3 = 98 935 N/m. The errors-in-variables cost (estimation/noise.py)

    L(θ) = ½ Σ_k |e_k|²,   e_k = sqrt(2 / (N S_k)) R_k (real and imaginary parts stacked),   S_k = σ3² + |H_k|² σ2²,

whose terms at the truth have unit variance. Here σ3, σ2 are *known*: ``--noise`` times each channel's clean RMS
(measured RMS / sqrt(1 + noise²)); the library fits them. ``--sigma fit`` fits them here too: a first fit with
σ = ``--sigma-start`` x each channel's RMS, then (``FreqProblem.fit_variances``) Whittle's likelihood of the
residual's periodogram, S linear in (σ3², σ2²), then the fit again from the first's θ. γ is eliminated at every evaluation by weighted linear
least squares (variable projection: e is the projected residual), so only θ is iterated. ``--prior`` adds the
library's literature prior on the body parameters (physics/occupant.body_prior: residuals (θ_j - μ_j)/σ_j in
linear θ, as estimation/plan_occupant.py does). Levenberg-Marquardt per recording; the Jacobian of the projected
residual in closed form (the full Golub-Pereyra derivative; ``jacobian_ad``: forward-mode AD, the check,
~5x slower); recordings that have converged (``levenberg_marquardt``: a Gauss-Newton decrement < 1e-6, or a
relative cost decrease < 1e-10 on an accepted step, or a step < 1e-8 in log θ) leave the batch. One start, no
restarts, no bounds (a few fits run off along p1 -> 0: the tail of the iteration counts).

Prints M's mean |error|, the share within 5 / 10 %, the seconds per iteration at the full batch and to
convergence, at ``--threads`` threads; ``--tile`` repeats the n recordings (a batch of 400 from 100).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

K3 = 98935.0
REF_C3, REF_M3 = 615.0, 80.0  # the reference vehicle's seat (bench/foreign_sim.py REF, physics/parameters.py)
WINDOW = slice(6, 506)  # the 500 samples the library fits of the 512 stored
OMEGA_SCALE = 2 * math.pi * 10.0
N_PARAMS = {"rigid": 2, "body1": 5, "body2": 8}
ORDER = {"rigid": 2, "body1": 4, "body2": 6}
N_MODES = {"rigid": 0, "body1": 1, "body2": 2}


def polynomials(model: str, theta: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Numerator and denominator of H [b, K] for theta [b, P] (linear) at s [K] (complex)."""
    p1, p2 = theta[:, 0:1], theta[:, 1:2]
    s = s[None]
    if model == "rigid":
        return p1 * s + p2, s * s + p1 * s + p2
    if model == "body2":
        r1, k1, c1, r2, k2, c2 = (theta[:, j : j + 1] for j in range(2, 8))
        g1, g2 = c1 * s + k1, c2 * s + k2
        q1, q2 = s * s + g1, s * s + g2
        num = (p1 * s + p2) * q1 * q2
        B = q1 * q2 + r1 * g1 * q2 + r2 * g2 * q1
        return num, s * s * B / (1 + r1 + r2) + num
    r, k, c = theta[:, 2:3], theta[:, 3:4], theta[:, 4:5]
    q = s * s + c * s + k
    num = (p1 * s + p2) * q
    return num, s * s * (s * s + (1 + r) * (c * s + k)) / (1 + r) + num


def polynomial_derivatives(model: str, theta: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """d num / d log θ_j and d den / d log θ_j [b, P, K] (the closed forms of ``polynomials``)."""
    p1, p2 = theta[:, 0:1], theta[:, 1:2]
    s = s[None]
    one = torch.ones_like(s)
    if model == "rigid":
        dnum = torch.stack([p1 * s, p2 * one], 1)
        return dnum, dnum
    if model == "body2":
        return _body2_derivatives(theta, s)
    r, k, c = theta[:, 2:3], theta[:, 3:4], theta[:, 4:5]
    q = s * s + c * s + k
    lin = p1 * s + p2
    zero = torch.zeros_like(lin)
    dnum = torch.stack([p1 * s * q, p2 * q, zero, k * lin, c * lin * s], 1)
    s2 = s * s
    extra = torch.stack([zero, zero, -r * s2 * s2 / (1 + r) ** 2, k * s2 * one, c * s2 * s], 1)
    return dnum, dnum + extra


def _body2_derivatives(theta: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """body2 (two parallel modes, physics/occupant.py): num = L q1 q2, den = s² B / R + num with L = p1 s + p2,
    g_i = c_i s + k_i, q_i = s² + g_i, B = q1 q2 + r1 g1 q2 + r2 g2 q1, R = 1 + r1 + r2; d / d log θ_j."""
    p1, p2 = theta[:, 0:1], theta[:, 1:2]
    r1, k1, c1, r2, k2, c2 = (theta[:, j : j + 1] for j in range(2, 8))
    g1, g2 = c1 * s + k1, c2 * s + k2
    q1, q2 = s * s + g1, s * s + g2
    lin, R = p1 * s + p2, 1 + r1 + r2
    B = q1 * q2 + r1 * g1 * q2 + r2 * g2 * q1
    s2 = s * s
    zero = torch.zeros_like(lin)
    # a mode's k or c moves g_i and q_i alike by dg: dQ = dg q_other, dB = dg (q_other (1 + r_i) + r_other g_other)
    dg = [k1 * torch.ones_like(s), c1 * s, k2 * torch.ones_like(s), c2 * s]
    other_q, dB_per = [q2, q2, q1, q1], [q2 * (1 + r1) + r2 * g2] * 2 + [q1 * (1 + r2) + r1 * g1] * 2
    dnum = [p1 * s * q1 * q2, p2 * q1 * q2, zero, lin * dg[0] * other_q[0], lin * dg[1] * other_q[1], zero]
    dnum += [lin * dg[2] * other_q[2], lin * dg[3] * other_q[3]]
    dden_extra = [zero, zero, s2 * r1 * (g1 * q2 - B / R) / R, s2 * dg[0] * dB_per[0] / R, s2 * dg[1] * dB_per[1] / R]
    dden_extra += [s2 * r2 * (g2 * q1 - B / R) / R, s2 * dg[2] * dB_per[2] / R, s2 * dg[3] * dB_per[3] / R]
    dnum = torch.stack(dnum, 1)  # p1, p2, r1, k1, c1, r2, k2, c2
    return dnum, dnum + torch.stack(dden_extra, 1)


def spectra(a3: np.ndarray, a2: np.ndarray, h: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A3, A2 [b, K] and s [K] of windows a3, a2 [b, N]: bins 1 .. N/2 - 1 (no DC, no Nyquist)."""
    n = a3.shape[-1]
    k = np.arange(1, (n - 1) // 2 + 1) if n % 2 else np.arange(1, n // 2)
    A3 = torch.from_numpy(np.fft.rfft(a3, axis=-1)[:, k])
    A2 = torch.from_numpy(np.fft.rfft(a2, axis=-1)[:, k])
    s = torch.from_numpy(1j * 2 * np.pi * k / (n * h))
    return A3, A2, s


class FreqProblem:
    """The projected, whitened residual e(log θ) [b, 2K (+ prior)] of one batch (module docstring)."""

    def __init__(self, model, A3, A2, s, n_samples, sigma3, sigma2, prior=None, extra: int = 0):
        self.model, self.A3, self.A2, self.s, self.n = model, A3, A2, s, n_samples
        self.v3, self.v2 = sigma3[:, None] ** 2, sigma2[:, None] ** 2  # [b, 1]
        self.prior = prior  # (mean [P], std [P]) in linear θ, inf std: no prior on that parameter
        order = ORDER[model] + extra
        self.basis = torch.stack([(s / OMEGA_SCALE) ** i for i in range(order)], -1)  # [K, n]

    def subset(self, idx: torch.Tensor) -> FreqProblem:
        sub = FreqProblem.__new__(FreqProblem)
        sub.__dict__ = dict(self.__dict__)
        sub.A3, sub.A2, sub.v3, sub.v2 = self.A3[idx], self.A2[idx], self.v3[idx], self.v2[idx]
        return sub

    def with_variances(self, v3: torch.Tensor, v2: torch.Tensor) -> FreqProblem:
        """The same problem with per-sample noise variances v3, v2 [b]."""
        new = FreqProblem.__new__(FreqProblem)
        new.__dict__ = dict(self.__dict__)
        new.v3, new.v2 = v3[:, None], v2[:, None]
        return new

    def fit_variances(self, log_theta: torch.Tensor, iterations: int = 20) -> tuple[torch.Tensor, torch.Tensor]:
        """v3, v2 [b] by Whittle's likelihood Σ_k log S_k + P_k / S_k of the residual's periodogram
        P_k = |R_k|² / N at log θ (R with the fitted transient taken off, divided by 1 - its leverage), S_k = v3 + |H_k|² v2 linear in v:
        Fisher scoring (estimation/noise.py estimate_variances, here for one output and one input)."""
        _, _, _, H, w, Xs, _, _, L, _, e = self._solve(log_theta)
        K = self.s.shape[0]
        # the transient takes n + e degrees of freedom, most of them from the few low bins that carry v2's
        # information (1/D is large there): E P_k = S_k (1 - leverage_k), so P_k is divided by that (about 9 % on
        # v2 on 500-sample windows otherwise)
        lev = (Xs * torch.cholesky_solve(Xs.transpose(1, 2), L).transpose(1, 2)).sum(2)  # [b, 2K]
        keep = (1 - 0.5 * (lev[:, :K] + lev[:, K:])).clamp_min(1e-3)
        P = (e[:, :K].square() + e[:, K:].square()) / w.square() / self.n / keep  # [b, K]
        a = torch.stack([torch.ones_like(P), H.real.square() + H.imag.square()], -1)  # dS/dv [b, K, 2]
        v = torch.stack([P[:, -K // 4 :].mean(1), P[:, : K // 4].mean(1) / a[:, : K // 4, 1].mean(1)], -1) * 0.5
        for _ in range(iterations):
            S = (a @ v[..., None])[..., 0]
            grad = (a * ((P - S) / S.square())[..., None]).sum(1)
            F = (a[..., :, None] * a[..., None, :] / S.square()[..., None, None]).sum(1)
            v = (v + torch.linalg.solve(F, grad)).clamp_min(1e-12 * v.amax(1, keepdim=True))
        return v[:, 0], v[:, 1]

    def _solve(self, log_theta: torch.Tensor):
        """The pieces of e at log θ [b, P]: θ, num, den, H, w [b, K], X (column-scaled) [b, 2K, n], y [b, 2K], the
        scaled γ [b, n, 1], its Cholesky factor, the column scales [b, 1, n], and the data part of e [b, 2K]."""
        theta = torch.exp(log_theta)
        num, den = polynomials(self.model, theta, self.s)
        H = num / den
        S = self.v3 + (H.real**2 + H.imag**2) * self.v2
        w = torch.sqrt(2.0 / (self.n * S))  # [b, K]
        b = w * (self.A3 - H * self.A2)
        Phi = (w / den)[..., None] * self.basis[None]  # [b, K, n]
        X = torch.cat([Phi.real, Phi.imag], 1)  # [b, 2K, n]
        y = torch.cat([b.real, b.imag], 1)  # [b, 2K]
        # column scaling keeps the normal equations conditioned; e does not depend on it
        scale = X.square().sum(1, keepdim=True).sqrt()
        Xs = X / scale
        G = Xs.transpose(1, 2) @ Xs
        L, info = torch.linalg.cholesky_ex(G)
        if bool((info != 0).any()):  # a trial step into overflow: its cost is inf, LM rejects it
            bad = info != 0
            L = torch.where(bad[:, None, None], torch.eye(G.shape[-1], dtype=G.dtype), L)
            y = torch.where(bad[:, None], torch.full_like(y, math.inf), y)
        g = torch.cholesky_solve((Xs.transpose(1, 2) @ y[..., None]), L)  # [b, n, 1]
        e = y - (Xs @ g)[..., 0]
        return theta, num, den, H, w, Xs, y, g, L, scale, e

    def _with_prior(self, theta: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
        if self.prior is None:
            return e
        mean, std = self.prior
        finite = torch.isfinite(std)
        return torch.cat([e, (theta[:, finite] - mean[finite]) / std[finite]], 1)

    def residual(self, log_theta: torch.Tensor, with_transient: bool = False):
        """e [b, M]; with_transient: also the fitted transient term T_k [b, K] (complex, the units of A3)."""
        theta, _, den, *_, g, _, scale, e = self._solve(log_theta)
        e = self._with_prior(theta, e)
        if with_transient:
            return e, ((self.basis[None] / den[..., None]) @ (g / scale.transpose(1, 2)).to(den.dtype))[..., 0]
        return e

    def jacobian(self, log_theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """e [b, M] and de/dlog θ [b, M, P], in closed form: the variable-projection derivative (Golub & Pereyra)
        de = r' - X G⁻¹ (Xᵀ r' + dXᵀ e), r' = dy - dX γ, with dH = (dnum - H dden)/den,
        dw = -w Re(conj(H) dH) v2 / S, dy = dw (A3 - H A2) - w dH A2, dΦ = (dw/den - w dden/den²) basis."""
        theta, num, den, H, w, Xs, y, g, L, scale, e = self._solve(log_theta)
        dnum, dden = polynomial_derivatives(self.model, theta, self.s)  # [b, P, K], per d log θ_j
        den_, H_, w_ = den[:, None], H[:, None], w[:, None]
        dH = (dnum - H_ * dden) / den_
        S = self.v3 + (H.real**2 + H.imag**2) * self.v2
        dw = -w_ * (H_.conj() * dH).real * (self.v2 / S)[:, None]
        dy = dw * (self.A3 - H * self.A2)[:, None] - w_ * dH * self.A2[:, None]
        coef = dw / den_ - w_ * dden / den_**2  # dΦ = coef basis, never formed: [b, P, K, n] is what costs
        gamma = (g / scale.transpose(1, 2))[..., 0].to(coef.dtype)  # [b, n], the unscaled columns'
        dXg = coef * (self.basis @ gamma.T).T[:, None]  # dΦ γ [b, P, K]
        rp = torch.cat([(dy - dXg).real, (dy - dXg).imag], 2)  # [b, P, 2K]
        K = self.s.shape[0]
        E = torch.complex(e[:, :K], e[:, K:])  # [b, K]
        dXe = ((coef * E.conj()[:, None]) @ self.basis).real / scale  # dXᵀ e [b, P, n], the scaled columns'
        rhs = rp @ Xs + dXe  # Xᵀ r' + dXᵀ e [b, P, n]
        dg = torch.cholesky_solve(rhs.transpose(1, 2), L)  # [b, n, P]
        de = rp - (Xs @ dg).transpose(1, 2)  # [b, P, 2K]
        if self.prior is not None:
            _, std = self.prior
            finite = torch.isfinite(std)
            dprior = torch.diag_embed(theta / torch.where(finite, std, 1.0))[:, finite]  # [b, n_prior, P]
            return self._with_prior(theta, e), torch.cat([de.transpose(1, 2), dprior], 1)
        return e, de.transpose(1, 2)

    def jacobian_ad(self, log_theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The same by forward-mode AD (one jvp per parameter over the whole batch): a check, ~5x slower."""
        cols = []
        e = None
        for j in range(log_theta.shape[1]):
            t = torch.zeros_like(log_theta)
            t[:, j] = 1.0
            e, d = torch.func.jvp(self.residual, (log_theta,), (t,))
            cols.append(d)
        return e, torch.stack(cols, -1)


def cost(e: torch.Tensor) -> torch.Tensor:
    return 0.5 * e.square().sum(-1)


def levenberg_marquardt(
    problem: FreqProblem, x0: torch.Tensor, max_iter: int = 100, tol: float = 1e-10, step_tol=1e-8, decrement=1e-6
):
    """Per-recording LM from log θ x0 [b, P]. Returns log θ [b, P], iterations to convergence [b] (max_iter + 1:
    not converged), and the timings {'iter_s': the median over the iterations at the full batch, 'total_s'}.
    A recording has converged after an accepted step with a relative cost decrease < tol or a step < step_tol,
    or when the Gauss-Newton decrement ½ gᵀ (JᵀJ)⁻¹ g at its point is < decrement (the cost has unit noise
    variance per term, so that is the likelihood still to gain: 1e-6 leaves θ ~1e-3 standard deviations from
    the minimum); decrement=0 turns that test off."""
    x = x0.clone()
    b = x.shape[0]
    lam = torch.full((b,), 1e-3, dtype=x.dtype)
    f = cost(problem.residual(x))
    iters = torch.full((b,), max_iter + 1, dtype=torch.long)
    active = torch.arange(b)
    problem.subset(active[:2]).jacobian(x[:2])  # warm-up: torch.func's first call is slow, not the method's cost
    t0 = time.perf_counter()
    full = []  # seconds of the iterations at the full batch
    for it in range(1, max_iter + 1):
        ti = time.perf_counter()
        n_active = len(active)
        sub = problem.subset(active)
        xa, la, fa = x[active], lam[active], f[active]
        e, J = sub.jacobian(xa)
        A = J.transpose(1, 2) @ J
        grad = (J.transpose(1, 2) @ e[..., None])[..., 0]
        diag = torch.diagonal(A, dim1=1, dim2=2).clamp_min(1e-30)
        step = -torch.linalg.solve(A + torch.diag_embed(la[:, None] * diag), grad)
        newton = torch.linalg.solve(A + torch.diag_embed(1e-12 * diag), grad[..., None])[..., 0]
        near = 0.5 * (grad * newton).sum(1) < decrement
        trial = xa + step
        ft = cost(sub.residual(trial))
        ok = torch.isfinite(ft) & (ft < fa)
        x[active] = torch.where(ok[:, None], trial, xa)
        decrease = (fa - torch.where(ok, ft, fa)) / fa.clamp_min(1e-300)
        f[active] = torch.where(ok, ft, fa)
        lam[active] = torch.where(ok, (la / 10).clamp_min(1e-12), la * 8)
        done = near | (ok & ((decrease < tol) | (step.abs().amax(1) < step_tol)))
        iters[active[done]] = it
        active = active[~done]
        if n_active == b:
            full.append(time.perf_counter() - ti)
        if len(active) == 0:
            break
    return x, iters, {"iter_s": float(np.median(full)), "total_s": time.perf_counter() - t0}


def read(path: Path, n: int):
    """a3, a2 windows [n, 500], h, truth m3 [n] and (for body1 persons) the true body1 θ [n, 5] (else None)."""
    import h5py

    with h5py.File(path, "r") as f:
        g = f["test"]
        accel = g["accel"][:n]
        h = float(f.attrs["h"])
        m3 = g["truth_m3"][:n]
        theta = None
        if "truth_body" in g:
            cols = g["truth_body"].attrs["columns"]
            cols = (cols.decode() if isinstance(cols, bytes) else cols).split(",")
            body = {c: g["truth_body"][:n, j] for j, c in enumerate(cols)}
            C3 = g["params"][:n, 0] * m3
            m_s = g["truth_pan"][:n] + body["m_r"]
            theta = np.stack(
                [C3 / m3, K3 / m3, body["m_b"] / m_s, body["k_b"] / body["m_b"], body["c_b"] / body["m_b"]]
            )
            theta = theta.T
    return accel[:, WINDOW, 0], accel[:, WINDOW, 1], h, m3, theta


def body_prior_tensors(model: str = "body1"):
    """(mean, std) [3 n_modes] of the library's literature prior on the body parameters."""
    from hybridqcm.physics.occupant import body_prior

    return body_prior(N_MODES[model])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("path", type=Path)
    ap.add_argument("--model", choices=tuple(N_PARAMS), default="body1")
    ap.add_argument("--n", type=int, default=100, help="recordings read from the file's test split")
    ap.add_argument("--tile", type=int, default=1, help="repeat the n recordings (a batch of tile * n)")
    ap.add_argument("--noise", type=float, default=0.05, help="σ as a fraction of each channel's clean RMS")
    ap.add_argument("--start", choices=("ref", "truth"), default="ref", help="reference vehicle or truth x 1.1")
    ap.add_argument("--prior", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--extra", type=int, default=2, help="degrees added to the transient's polynomial (edge terms)")
    ap.add_argument(
        "--sigma", choices=("known", "fit"), default="known", help="σ3, σ2 given (--noise) or fitted (Whittle)"
    )
    ap.add_argument("--sigma-start", type=float, default=0.02, help="--sigma fit: the first fit's σ / channel RMS")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--max-iter", type=int, default=100)
    ap.add_argument("--decrement", type=float, default=1e-6, help="stop at this Gauss-Newton decrement; 0: off")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    a3, a2, h, m3, theta_true = read(args.path, args.n)
    a3, a2, m3 = (np.tile(a, (args.tile,) + (1,) * (a.ndim - 1)) for a in (a3, a2, m3))
    clean = math.sqrt(1 + args.noise**2)
    level = args.noise if args.noise > 0 else 0.05  # noise-free data: the 5 % weighting, only a weighting
    if args.sigma == "fit":
        level, clean = args.sigma_start, 1.0
    sig3 = torch.from_numpy(level * np.sqrt(np.mean(a3**2, 1)) / clean)
    sig2 = torch.from_numpy(level * np.sqrt(np.mean(a2**2, 1)) / clean)
    A3, A2, s = spectra(a3, a2, h)
    prior = None
    if args.model != "rigid" and args.prior:
        mean, std = body_prior_tensors(args.model)
        prior = (torch.cat([torch.ones(2, dtype=torch.float64), mean]), torch.cat([torch.full((2,), math.inf), std]))
    problem = FreqProblem(args.model, A3, A2, s, a3.shape[1], sig3, sig2, prior, args.extra)

    b = len(m3)
    if args.start == "truth":
        if args.model != "rigid":
            if theta_true is None or args.model != "body1":
                raise SystemExit(f"freq_fit: {args.path}: --start truth: no body1 truth for --model {args.model}")
            start = np.tile(theta_true, (args.tile, 1)) * 1.1
        else:
            start = np.stack([np.full(b, REF_C3 / REF_M3), K3 / m3], 1) * 1.1  # C3 unknown per file: REF's
    else:
        start = np.tile([REF_C3 / REF_M3, K3 / REF_M3], (b, 1))
        if args.model != "rigid":
            start = np.concatenate([start, np.tile(body_prior_tensors(args.model)[0].numpy(), (b, 1))], 1)
    x, iters, timing = levenberg_marquardt(
        problem, torch.log(torch.from_numpy(start)), args.max_iter, decrement=args.decrement
    )
    if args.sigma == "fit":  # the variances at the first fit, then the fit again from there
        t0 = time.perf_counter()
        v3, v2 = problem.fit_variances(x)
        problem = problem.with_variances(v3, v2)
        t_var = time.perf_counter() - t0
        x, iters2, timing2 = levenberg_marquardt(problem, x, args.max_iter, decrement=args.decrement)
        ratio = torch.sqrt(torch.stack([v3, v2], 1)).numpy() / np.stack([sig3.numpy(), sig2.numpy()], 1)
        ratio *= args.sigma_start * math.sqrt(1 + args.noise**2) / args.noise if args.noise > 0 else 1.0
        print(f"fitted σ over the true (--noise) σ, a3 and a2: median {np.median(ratio, 0).round(3)}")
        timing = {"iter_s": timing["iter_s"], "total_s": timing["total_s"] + t_var + timing2["total_s"]}
        iters = torch.where((iters <= args.max_iter) & (iters2 <= args.max_iter), iters + iters2, args.max_iter + 1)
    M = K3 / torch.exp(x[:, 1]).numpy()
    err = np.abs(M / m3 - 1)
    conv = iters <= args.max_iter
    print(
        f"{args.path.name} model={args.model} batch={b} threads={args.threads} start={args.start} prior={prior is not None}"
        f" noise={args.noise} sigma={args.sigma} extra={args.extra}: M mean |error| {100 * err.mean():.2f} % (median {100 * np.median(err):.2f} %,"
        f" signed {100 * np.mean(M / m3 - 1):+.3f} %),"
        f" within 5 % {100 * (err <= 0.05).mean():.0f} %, within 10 % {100 * (err <= 0.10).mean():.0f} %;"
        f" converged {int(conv.sum())}/{b}, iterations mean {iters[conv].float().mean():.1f} max {int(iters.max())};"
        f" s/iteration at the full batch {timing['iter_s']:.3f}, to convergence {timing['total_s']:.2f} s"
    )


if __name__ == "__main__":
    main()
