"""Profile-likelihood intervals and the noise fit's leverage correction (estimation/profile.py, noise.py)."""

from __future__ import annotations

import dataclasses
import math

import torch

from hybridqcm.estimation.noise import estimate_variances, parseval_weights, spectral_leverage
from hybridqcm.estimation.problems import LeastSquaresProblem
from hybridqcm.estimation.profile import profile_interval
from hybridqcm.estimation.response import ExactResponse
from hybridqcm.estimation.solver import build_solver
from hybridqcm.physics.linear_models import SeatBaseExcitation

H = 0.01
F64 = torch.float64


def _seat_problem(sigma: float, batch: int = 3, T: int = 300, seed: int = 0):
    """A seat (p1, p2 per recording) driven by a smooth random base acceleration, a3 with white noise of
    ``sigma`` m/s², weighted by 1/sigma so that the loss is in units of the noise."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T + 40, dtype=F64) * H
    freqs = torch.rand(batch, 12, generator=g, dtype=F64) * 9 + 0.5
    phase = torch.rand(batch, 12, generator=g, dtype=F64) * 2 * math.pi
    a2 = torch.sin(2 * math.pi * freqs[:, :, None] * t + phase[:, :, None]).sum(1)[..., None]
    p = torch.tensor([[7.7, 1236.7], [4.1, 660.0], [12.0, 2500.0]], dtype=F64)[:batch]
    response = ExactResponse(SeatBaseExcitation(), H, "spline", 16, "unknown")
    x0 = torch.zeros(batch, 2, dtype=F64)
    clean = response.outputs(torch.cat([p, x0], 1), a2, 20, T)
    noisy = clean + sigma * torch.randn(clean.shape, generator=g, dtype=F64)
    problem = LeastSquaresProblem(
        noisy,
        a2,
        H,
        observed=(True,),
        model=response,
        input_offset=20,
        weights=torch.full((batch, 1), 1.0 / sigma, dtype=F64),
    )
    return problem, torch.cat([p, x0], 1)


def _fit(problem, start):
    solver = build_solver("gauss_newton", max_iterations=50, covariance="model")
    result = solver.solve(problem, start)
    return result.params, result.covariance, result.residual_variance


def _deviance_at(problem, params, best_loss, value):
    """2 ΔL with θ_2 held at ``value`` [b]: an independent constrained solve (more iterations, its own start)."""
    known = problem.known.clone()
    known[1] = True
    fixed = dataclasses.replace(problem, known=known)
    start = params.clone()
    start[:, 1] = value
    solver = build_solver("gauss_newton", max_iterations=80, covariance="model")
    result = solver.solve(fixed, start)
    return 2.0 * (solver.objective(fixed, result.params) - best_loss)


def test_profile_ends_lie_where_the_deviance_is_the_chi2_quantile():
    """Noisy seats: at each end the deviance of an independent constrained fit is z² = 3.84, and 1 % of
    the way back inside it is smaller — the interval is the likelihood-ratio set, not θ̂ ± 1.96 σ."""
    problem, truth = _seat_problem(sigma=0.4)
    params, cov, _ = _fit(problem, truth)
    solver = build_solver("gauss_newton", max_iterations=8, covariance="model")
    low, high, reached = profile_interval(solver, problem, params, cov, 1)
    assert bool(reached.all())
    best = solver.objective(problem, params)
    for end in (low, high):
        deviance = _deviance_at(problem, params, best, end)
        torch.testing.assert_close(deviance, torch.full_like(deviance, 1.959963984540054**2), atol=0.08, rtol=0)
        inside = _deviance_at(problem, params, best, params[:, 1] + 0.99 * (end - params[:, 1]))
        assert bool((inside < 3.84).all())


def test_a_nearly_linear_problem_gives_the_laplace_interval():
    """High signal-to-noise: the posterior is Gaussian, and the profile interval (deviance in units of the
    residual variance σ̂², as the Laplace covariance) is θ̂ ± 1.96 σ to 1 %."""
    problem, truth = _seat_problem(sigma=0.002)
    params, cov, variance = _fit(problem, truth)
    solver = build_solver("gauss_newton", max_iterations=8, covariance="model")
    low, high, _ = profile_interval(solver, problem, params, cov, 1, scale=variance)
    sigma = cov[:, 1, 1].sqrt()
    torch.testing.assert_close((high - params[:, 1]) / sigma, torch.full_like(sigma, 1.96), rtol=0.01, atol=0)
    torch.testing.assert_close((params[:, 1] - low) / sigma, torch.full_like(sigma, 1.96), rtol=0.01, atol=0)


def test_leverage_sums_to_the_number_of_fitted_unknowns():
    """The hat matrix is a projection: its trace, Σ_k h_k over the real rows, is the rank of the Jacobian."""
    g = torch.Generator().manual_seed(3)
    T, Q = 128, 5
    jacobian = torch.randn(2, T, 1, Q, generator=g, dtype=F64)
    h = spectral_leverage(jacobian, None, torch.zeros(2, Q, dtype=F64))
    components = torch.full((T // 2 + 1,), 2.0, dtype=F64)
    components[-1] = 1.0
    components[0] = 0.0  # DC carries no rows
    rows_dc = jacobian.mean(1).abs().sum() > 0  # the DC part of J is dropped (the noise fit leaves it out)
    total = (h * components).sum(1)
    assert rows_dc
    torch.testing.assert_close(total, torch.full_like(total, float(Q)), rtol=1e-8, atol=1e-8)


def test_leverage_corrected_noise_variance_is_unbiased():
    """White noise of variance 1 fitted by 40 narrow-band columns out of 200 samples: the residual's power
    is (1 - 40/199) of the noise's, and P_k / (1 - h_k) gives it back (Monte Carlo over 400 fits)."""
    g = torch.Generator().manual_seed(5)
    b, T, Q = 400, 200, 40
    t = torch.arange(T, dtype=F64)
    k = torch.arange(10, 10 + Q // 2, dtype=F64)  # cosines and sines of 20 DFT frequencies
    basis = torch.cat([torch.cos(2 * math.pi * k[:, None] * t / T), torch.sin(2 * math.pi * k[:, None] * t / T)]).T
    noise = torch.randn(b, T, generator=g, dtype=F64)
    coef = torch.linalg.lstsq(basis, noise.T).solution
    residual = (noise - (basis @ coef).T)[..., None]  # [b, T, 1]
    plain, _ = estimate_variances(residual, None)
    jacobian = basis[None, :, None, :].expand(b, T, 1, Q)
    h = spectral_leverage(jacobian, None, torch.zeros(b, Q, dtype=F64))
    corrected, _ = estimate_variances(residual, None, leverage=h)
    expected_plain = 1.0 - Q / (T - 1)  # the Parseval weights of T samples without DC sum to T - 1
    assert abs(float(plain.mean()) - expected_plain) < 0.01
    assert abs(float(corrected.mean()) - 1.0) < 0.01
    assert float(parseval_weights(T).sum()) == T - 1


def test_a_sigma_many_times_the_value_gives_an_open_interval_not_an_error():
    """A Laplace σ thousands of times θ (a window standing still: next to no signal in p2) stepped the first
    profile point to θ e^(1.96 σ/θ) = inf and the solver refused it ("initial params contain NaN/inf"), which
    stopped a whole run of drives with a stop. Now the step in log θ is bounded: no error, the other rows'
    intervals unchanged, the wide row's ends numbers (not NaN)."""
    problem, truth = _seat_problem(sigma=0.4)
    params, cov, _ = _fit(problem, truth)
    solver = build_solver("gauss_newton", max_iterations=8, covariance="model")
    low, high, _ = profile_interval(solver, problem, params, cov, 1)
    wide = cov.clone()
    wide[0, 1, 1] = (5e3 * params[0, 1]) ** 2
    low_w, high_w, _ = profile_interval(solver, problem, params, wide, 1)
    torch.testing.assert_close(low_w[1:], low[1:])
    torch.testing.assert_close(high_w[1:], high[1:])
    assert not bool(torch.isnan(low_w[0])) and not bool(torch.isnan(high_w[0]))
