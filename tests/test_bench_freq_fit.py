"""bench/freq_fit.py: the frequency-domain fit of the road-free seat, against independent facts — the seat's
equations of motion (physics/occupant.py's docstring) integrated by scipy's solve_ivp with the input known in
continuous time, and central finite differences of the residual."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import scipy.integrate
import torch

from conftest import REPO_ROOT

H = 0.01
N = 500  # one period of the multisine: 5 s
BODY1 = np.array([6.0, 1100.0, 1.8, 1000.0, 25.0])  # p1, p2, r, k (5 Hz), c
RIGID = np.array([7.0, 1150.0])
BODY2 = np.array([6.0, 1100.0, 1.8, 1000.0, 25.0, 0.5, 4000.0, 40.0])  # the second mode at 10 Hz


@pytest.fixture(scope="module")
def ff():
    spec = importlib.util.spec_from_file_location("freq_fit", REPO_ROOT / "bench" / "freq_fit.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _multisine(seed: int = 0):
    """a2(t) and its derivative-free closed form: sines on the window's bins 1 .. 75 (0.2 - 15 Hz), band-limited
    and periodic with the window."""
    rng = np.random.default_rng(seed)
    f = np.arange(1, 76) / (N * H)
    amp, phase = rng.uniform(0.5, 1.5, f.size) / np.sqrt(f.size), rng.uniform(0, 2 * np.pi, f.size)
    return lambda t: np.sum(amp[:, None] * np.sin(2 * np.pi * f[:, None] * np.atleast_1d(t)[None] + phase[:, None]), 0)


def _simulate(theta: np.ndarray, a2, t_end: float) -> tuple[np.ndarray, np.ndarray]:
    """a3, a2 sampled at H on [0, t_end) from rest: the seat with parallel body modes of physics/occupant.py's
    docstring, a_pan = R (-p1 ż - p2 z) + Σ r_i (c_i ẏ_i + k_i y_i), z̈ = a_pan - a2, ÿ_i = -(c_i ẏ_i + k_i y_i) - a_pan,
    R = 1 + Σ r_i (rigid: no modes)."""
    p1, p2 = theta[:2]
    modes = np.asarray(theta[2:]).reshape(-1, 3)
    R = 1 + modes[:, 0].sum()

    def pan(x):
        y, dy = x[2::2], x[3::2]
        return R * (-p1 * x[1] - p2 * x[0]) + np.sum(modes[:, 0] * (modes[:, 2] * dy + modes[:, 1] * y))

    def rhs(t, x):
        a = pan(x)
        out = [x[1], a - a2(t)[0]]
        for i, (_, k, c) in enumerate(modes):
            out += [x[3 + 2 * i], -(c * x[3 + 2 * i] + k * x[2 + 2 * i]) - a]
        return out

    t = np.arange(int(round(t_end / H))) * H
    x0 = [0.0] * (2 + 2 * len(modes))
    sol = scipy.integrate.solve_ivp(rhs, (0, t[-1]), x0, t_eval=t, rtol=1e-11, atol=1e-13, method="DOP853")
    return np.array([pan(x) for x in sol.y.T]), a2(t)


def _fit(ff, model, a3, a2, start, extra=2):
    A3, A2, s = ff.spectra(a3[None], a2[None], H)
    sig = torch.tensor([0.05 * np.sqrt(np.mean(a3**2))]), torch.tensor([0.05 * np.sqrt(np.mean(a2**2))])
    problem = ff.FreqProblem(model, A3, A2, s, N, *sig, None, extra)
    x, iters, _ = ff.levenberg_marquardt(problem, torch.log(torch.tensor(start))[None], 100)
    return torch.exp(x[0]).numpy(), problem, x


@pytest.mark.parametrize("model, theta", [("rigid", RIGID), ("body1", BODY1), ("body2", BODY2)])
def test_steady_state_fit_recovers_theta(ff, model, theta):
    """Noise-free, periodic and band-limited: A3 = H A2 holds exactly on every bin, the fit from 10 % off
    recovers θ to 1e-6 and the transient term vanishes."""
    a2 = _multisine()
    a3, a2s = _simulate(theta, a2, 40.0 + N * H)  # 40 s settle (the slowest mode decays as e^{-2.5 t})
    a3, a2s = a3[-N:], a2s[-N:]
    fit, problem, x = _fit(ff, model, a3, a2s, theta * 1.1)
    np.testing.assert_allclose(fit, theta, rtol=1e-6)
    _, transient = problem.residual(x, with_transient=True)
    A3 = problem.A3
    assert float(transient.abs().max()) < 1e-6 * float(A3.abs().max())


def test_transient_term_takes_a_start_from_rest(ff):
    """The first period from rest: y = steady state + the decaying transient. The textbook continuous-time leakage
    term (degree n - 1) leaves the error of the DFT's rectangle rule at the window's sampled ends (percent); each
    pair of edge degrees added takes an order of the Euler-Maclaurin expansion of that error off."""
    a2 = _multisine(1)
    a3, a2s = _simulate(BODY1, a2, N * H)
    errors = [np.max(np.abs(_fit(ff, "body1", a3, a2s, BODY1 * 1.1, extra=e)[0] / BODY1 - 1)) for e in (0, 2, 6)]
    assert errors[0] > 1e-2
    assert errors[1] < 1e-3
    assert errors[2] < 1e-5


@pytest.mark.parametrize("model, theta", [("body1", BODY1), ("body2", BODY2)])
def test_jacobian_matches_finite_differences(ff, model, theta):
    """The closed-form Jacobian of the projected residual (γ re-solved inside) against central differences and
    forward-mode AD."""
    rng = np.random.default_rng(3)
    a3, a2 = rng.standard_normal((2, 3, N))
    A3, A2, s = ff.spectra(a3, a2, H)
    sig = torch.full((3,), 0.1, dtype=torch.float64)
    P = len(theta)
    mean, std = torch.ones(P, dtype=torch.float64), torch.tensor([np.inf, np.inf] + [1.0, 300.0, 10.0] * (P // 3))
    problem = ff.FreqProblem(model, A3, A2, s, N, sig, sig, (mean, std), 2)
    x = torch.log(torch.tensor(theta)).repeat(3, 1) + 0.05 * torch.tensor(rng.standard_normal((3, P)))
    _, J = problem.jacobian(x)
    np.testing.assert_allclose(
        J.numpy(), problem.jacobian_ad(x)[1].numpy(), rtol=1e-9, atol=1e-12 * float(J.abs().max())
    )
    step = 1e-6
    for j in range(P):
        dx = torch.zeros_like(x)
        dx[:, j] = step
        fd = (problem.residual(x + dx) - problem.residual(x - dx)) / (2 * step)
        np.testing.assert_allclose(J[..., j].numpy(), fd.numpy(), rtol=1e-5, atol=1e-6 * float(fd.abs().max()))


def test_fit_variances_recovers_white_noise(ff):
    """White noise of known variance on both channels of a periodic steady state: Whittle's fit at the true θ
    returns it: the mean over 200 recordings within 6 % (standard errors 0.5 % on a3's, 1.8 % on a2's, fewer
    bins carry it). Without the leverage correction a2's came out 9 % low (the transient's degrees of freedom)."""
    a2 = _multisine(2)
    a3, a2s = _simulate(BODY1, a2, 40.0 + N * H)
    a3, a2s = a3[-N:], a2s[-N:]
    rng = np.random.default_rng(4)
    sd3, sd2 = 0.05 * np.sqrt(np.mean(a3**2)), 0.05 * np.sqrt(np.mean(a2s**2))
    b = 200
    A3, A2, s = ff.spectra(a3 + sd3 * rng.standard_normal((b, N)), a2s + sd2 * rng.standard_normal((b, N)), H)
    ones = torch.ones(b, dtype=torch.float64)
    problem = ff.FreqProblem("body1", A3, A2, s, N, ones * sd3 * 3, ones * sd2 / 3, None, 2)  # wrong weights
    v3, v2 = problem.fit_variances(torch.log(torch.tensor(BODY1)).repeat(b, 1))
    assert abs(float(v3.mean()) / sd3**2 - 1) < 0.06
    assert abs(float(v2.mean()) / sd2**2 - 1) < 0.06
