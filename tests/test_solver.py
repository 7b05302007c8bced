"""Batched Gauss-Newton / Levenberg-Marquardt: recovery, masks, singular cases, statuses."""

import math

import pytest
import torch

import hybridqcm.estimation.solver as solver_module
from hybridqcm.estimation.problems import LeastSquaresProblem
from hybridqcm.estimation.solver import GaussNewton, LevenbergMarquardt, SolverConfig, SolverStatus, build_solver
from hybridqcm.testing import synthetic_samples

H = 0.01


@pytest.fixture(scope="module")
def data():
    return synthetic_samples(48, n_steps=100, seed=11)


def _near_truth(params, scale=0.05, seed=0):
    g = torch.Generator().manual_seed(seed)
    return params * (1 + scale * torch.randn(params.shape, generator=g, dtype=torch.float64))


@pytest.mark.parametrize("cls", [GaussNewton, LevenbergMarquardt])
def test_recovers_parameters_noise_free(data, cls):
    problem = LeastSquaresProblem(data["accel"], data["road"], H)
    result = cls(SolverConfig(max_iterations=15)).solve(problem, _near_truth(data["params"]))
    err = (result.params - data["params"]).abs() / data["params"]
    assert (err <= 1e-6).all(1).double().mean() >= 0.95
    assert (result.status == SolverStatus.CONVERGED).double().mean() >= 0.95
    assert result.iterations.double().mean() <= 10
    # loss history: one row per iteration (+ the start), non-increasing per sample, finite
    history = result.loss_history
    assert torch.isfinite(history).all()
    assert (history[1:] <= history[:-1] * (1 + 1e-12) + 1e-300).all()
    assert result.singular_values.shape == (48, 10)
    assert torch.isfinite(result.std).all() and (result.std >= 0).all()


def test_known_parameters_bit_identical_and_masked(data):
    known = torch.zeros(10, dtype=torch.bool)
    known[[2, 4]] = True
    init = _near_truth(data["params"])
    init[:, [2, 4]] = data["params"][:, [2, 4]] * 1.001  # deliberately slightly off: must stay exactly so
    problem = LeastSquaresProblem(data["accel"], data["road"], H, known=known)
    result = GaussNewton(SolverConfig(max_iterations=5)).solve(problem, init)
    assert torch.equal(result.params[:, [2, 4]], init[:, [2, 4]])
    assert (result.std[:, [2, 4]] == 0).all()
    assert (result.covariance[:, [2, 4]] == 0).all() and (result.covariance[:, :, [2, 4]] == 0).all()
    assert result.singular_values.shape == (48, 8)


def test_unobserved_channels_do_not_enter(data):
    p = data["params"]
    forcing = (p[:, 9] - p[:, 8])[:, None] * data["road"]
    known = torch.zeros(10, dtype=torch.bool)
    known[[2, 4]] = True
    init = _near_truth(p)
    init[:, [2, 4]] = p[:, [2, 4]]
    garbage = data["accel"].clone()
    garbage[..., 1:] = torch.randn(garbage[..., 1:].shape, dtype=torch.float64) * 1e3
    garbage[0, 0, 2] = float("nan")  # even NaN in an unobserved channel is never read
    results = []
    for targets in (data["accel"], garbage):
        problem = LeastSquaresProblem(targets, forcing, H, scaled_road=True, observed=(True, False, False), known=known)
        results.append(GaussNewton(SolverConfig(max_iterations=20)).solve(problem, init))
    assert torch.equal(results[0].params, results[1].params)
    assert torch.equal(results[0].loss_history, results[1].loss_history)
    err = (results[0].params - p).abs() / p
    assert (err <= 0.01).all(1).double().mean() >= 0.9


def test_zero_road_is_singular_not_nan(data):
    problem = LeastSquaresProblem(
        torch.zeros(4, 50, 3, dtype=torch.float64), torch.zeros(4, 50, dtype=torch.float64), H
    )
    init = data["params"][:4].clone()
    result = GaussNewton().solve(problem, init)
    assert (result.status == SolverStatus.SINGULAR).all()
    for tensor in (
        result.params,
        result.loss,
        result.loss_history,
        result.std,
        result.covariance,
        result.singular_values,
    ):
        assert not torch.isnan(tensor).any()
    assert torch.equal(result.params, init)
    assert torch.isinf(result.std).all()  # nothing is identifiable without input


def test_rank_deficient_pseudo_inverse():
    """Duplicate information (only a1 observed, p1..p6 cannot all be identified) gives a status, not NaN."""
    data = synthetic_samples(4, n_steps=40, seed=5)
    problem = LeastSquaresProblem(data["accel"], data["road"], H, observed=(False, False, True))
    result = GaussNewton(SolverConfig(max_iterations=3)).solve(problem, data["params"] * 1.01)
    assert not torch.isnan(result.params).any() and not torch.isnan(result.std).any()
    assert set(result.status.tolist()) <= {s.value for s in SolverStatus}


def test_linear_parametrization_keeps_parameters_positive(data):
    g = torch.Generator().manual_seed(1)
    from hybridqcm.physics import reference_params

    init = reference_params().expand(16, 10) * (1 + 0.1 * torch.randn(16, 10, generator=g, dtype=torch.float64))
    problem = LeastSquaresProblem(data["accel"][:16], data["road"][:16], H)
    result = build_solver("gauss_newton", parametrization="linear", max_iterations=10).solve(problem, init)
    assert (result.params > 0).all()


def test_literal_armijo_rejects_full_steps(data):
    """SPEC §8 read literally (c = 1) can never accept a Gauss-Newton step on a near-quadratic model."""
    problem = LeastSquaresProblem(data["accel"][:8], data["road"][:8], H)
    init = _near_truth(data["params"][:8], 0.01)
    strict = GaussNewton(SolverConfig(max_iterations=5, armijo_c=1.0)).solve(problem, init)
    default = GaussNewton(SolverConfig(max_iterations=5)).solve(problem, init)
    assert (default.loss < strict.loss).all()


def test_uncertainty_is_calibrated_under_noise():
    data = synthetic_samples(64, n_steps=100, seed=21)
    g = torch.Generator().manual_seed(2)
    noise = (
        1e-3
        * data["accel"].abs().mean((1,), keepdim=True)
        * torch.randn(data["accel"].shape, generator=g, dtype=torch.float64)
    )
    problem = LeastSquaresProblem(data["accel"] + noise, data["road"], H)
    result = GaussNewton(SolverConfig(max_iterations=20)).solve(problem, _near_truth(data["params"], 0.02))
    inside = ((result.params - data["params"]).abs() <= 1.96 * result.std).double().mean()
    assert 0.85 <= inside <= 1.0
    assert (result.residual_variance > 0).all()


def test_bad_inputs():
    data = synthetic_samples(2, n_steps=20, seed=1)
    with pytest.raises(ValueError, match="targets"):
        LeastSquaresProblem(data["accel"][..., :2], data["road"], H)
    with pytest.raises(ValueError, match="all 10"):
        LeastSquaresProblem(data["accel"], data["road"], H, known=torch.ones(10, dtype=torch.bool))
    bad = data["accel"].clone()
    bad[0, 3, 0] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        LeastSquaresProblem(bad, data["road"], H)
    with pytest.raises(ValueError, match="unknown solver method"):
        build_solver("newton")
    with pytest.raises(TypeError, match="unknown solver setting"):
        GaussNewton(tolerance=1)


def test_channel_weights(data):
    """Unit weights change nothing; weights enter R and J alike (the noise-free optimum is unchanged)."""
    init = _near_truth(data["params"][:8])
    accel, road = data["accel"][:8], data["road"][:8]
    base = GaussNewton(SolverConfig(max_iterations=4)).solve(LeastSquaresProblem(accel, road, H), init)
    ones = GaussNewton(SolverConfig(max_iterations=4)).solve(
        LeastSquaresProblem(accel, road, H, weights=torch.ones(8, 3, dtype=torch.float64)), init
    )
    assert torch.equal(base.params, ones.params)
    weights = torch.tensor([[10.0, 1.0, 0.1]], dtype=torch.float64).expand(8, 3)
    weighted = GaussNewton(SolverConfig(max_iterations=15)).solve(
        LeastSquaresProblem(accel, road, H, weights=weights), init
    )
    err = (weighted.params - data["params"][:8]).abs() / data["params"][:8]
    assert (err <= 1e-6).all()
    with pytest.raises(ValueError, match="weights"):
        LeastSquaresProblem(accel, road, H, weights=torch.zeros(8, 3))


def test_wrong_model_is_misfit_not_converged():
    """The Euler model fitted to the continuous-time response of the same vehicles (an RK4 integration
    at h/20, sampled every h) cannot fit it: every such sample must end `misfit`, never `converged`;
    the same vehicles' Euler data with white noise of 1 % of the channel RMS must not be called misfit."""
    from hybridqcm.physics import simulate

    data = synthetic_samples(24, n_steps=100, seed=31)
    fine = 20
    road_fine = torch.nn.functional.interpolate(
        data["road"][:, None], scale_factor=fine, mode="linear", align_corners=False
    )[:, 0]
    continuous = simulate(data["params"], road_fine, H / fine, method="rk4").accel[:, ::fine]
    road = road_fine[:, ::fine]
    solver = GaussNewton(SolverConfig(max_iterations=20))
    wrong = solver.solve(LeastSquaresProblem(continuous, road, H), _near_truth(data["params"], 0.01))
    misfit = wrong.status == SolverStatus.MISFIT
    assert (misfit | (wrong.status == SolverStatus.DIVERGED)).all() and misfit.sum() >= 6
    assert (wrong.relative_residual[misfit] > 0.005).all() and (wrong.whiteness[misfit] > 1).all()

    g = torch.Generator().manual_seed(3)
    rms = data["accel"].square().mean(1, keepdim=True).sqrt()
    noisy = data["accel"] + 0.01 * rms * torch.randn(data["accel"].shape, generator=g, dtype=torch.float64)
    right = solver.solve(LeastSquaresProblem(noisy, data["road"], H), _near_truth(data["params"], 0.01))
    assert (right.status != SolverStatus.MISFIT).all()
    evaluated = right.status != SolverStatus.DIVERGED  # p3/p5 may leave the domain under noise
    assert evaluated.sum() >= 20 and (right.whiteness[evaluated] < 1).all()


def _linear_model(design):
    """y = J θ with J fixed [T, 1, n]: a known-solution test problem (no input, no initial state)."""
    from hybridqcm.estimation.response import ResponseModel

    class Linear(ResponseModel):
        theta_names, output_names, n_params = ("a", "b", "c"), ("y",), 0

        def outputs(self, theta, inputs, start=0, n_steps=None):
            return torch.einsum("ton,bn->bto", design, theta)

        def sensitivities(self, theta, inputs, start=0, n_steps=None):
            jac = design.expand(theta.shape[0], *design.shape)
            return torch.cat([self.outputs(theta, inputs).unsqueeze(-1), jac], -1)

    return Linear()


def test_a_fit_worse_than_zero_is_misfit_even_when_its_residual_is_white():
    """A residual larger than the data (white here: the model's columns are white noise) explains less
    than predicting zero: misfit, not converged. The least-squares fit of the same data is converged."""
    g = torch.Generator().manual_seed(1)
    design = torch.randn(200, 1, 3, generator=g, dtype=torch.float64)
    truth = torch.randn(4, 3, generator=g, dtype=torch.float64)
    data = torch.einsum("ton,bn->bto", design, truth) + 0.1 * torch.randn(4, 200, 1, generator=g, dtype=torch.float64)
    problem = LeastSquaresProblem(
        data, torch.zeros(4, 200, dtype=torch.float64), H, observed=(True,), model=_linear_model(design)
    )
    far = GaussNewton(SolverConfig(max_iterations=0)).solve(problem, truth + 10.0)
    assert (far.relative_residual > 1).all() and (far.whiteness < 1).all()
    assert (far.status == SolverStatus.MISFIT).all()
    fit = GaussNewton(SolverConfig(max_iterations=5)).solve(problem, truth + 10.0)
    assert (fit.status == SolverStatus.CONVERGED).all() and (fit.relative_residual < 0.2).all()


@pytest.mark.parametrize(("size", "status"), [(3e-3, SolverStatus.MISFIT), (2e-4, SolverStatus.CONVERGED)])
def test_a_structured_residual_is_judged_without_peers(size, status):
    """One recording, no batch to compare with: a structured residual the size a wrong basin leaves on
    noise-free data (3e-3 of the channel's RMS) is misfit; one the size of the exact model's hold error
    (2e-4) is not. The data are J θ plus a slow sine no column of J can represent."""
    g = torch.Generator().manual_seed(2)
    design = torch.randn(300, 1, 3, generator=g, dtype=torch.float64)
    truth = torch.randn(1, 3, generator=g, dtype=torch.float64)
    clean = torch.einsum("ton,bn->bto", design, truth)
    sine = torch.sin(torch.arange(300, dtype=torch.float64) / 7.0)[None, :, None]
    data = clean + size * clean.square().mean().sqrt() / sine.square().mean().sqrt() * sine
    problem = LeastSquaresProblem(
        data, torch.zeros(1, 300, dtype=torch.float64), H, observed=(True,), model=_linear_model(design)
    )
    fit = GaussNewton(SolverConfig(max_iterations=5)).solve(problem, truth + 1.0)
    assert fit.relative_residual.item() == pytest.approx(size, rel=0.2) and fit.whiteness.item() > 1
    assert fit.status.item() == status


def test_gaussian_prior_is_the_closed_form_map_on_a_linear_problem():
    """x0 enters the outputs linearly: with p known, the MAP estimate of x0 under a Gaussian prior and
    its Laplace covariance are the closed-form ridge solution (JᵀJ/σ² + Λ)⁻¹(JᵀY/σ² + Λμ)."""
    g = torch.Generator().manual_seed(0)
    design = torch.randn(40, 1, 3, generator=g, dtype=torch.float64)
    truth = torch.randn(5, 3, generator=g, dtype=torch.float64)
    data = torch.einsum("ton,bn->bto", design, truth) + 0.1 * torch.randn(5, 40, 1, generator=g, dtype=torch.float64)
    mean = torch.zeros(5, 3, dtype=torch.float64)
    precision = torch.tensor([[4.0, 0.0, 100.0]], dtype=torch.float64).expand(5, 3)
    weights = torch.full((5, 1), 10.0, dtype=torch.float64)  # 1/σ
    problem = LeastSquaresProblem(
        data,
        torch.zeros(5, 40, dtype=torch.float64),
        H,
        observed=(True,),
        weights=weights,
        model=_linear_model(design),
        prior_mean=mean,
        prior_precision=precision,
    )
    result = GaussNewton(SolverConfig(max_iterations=5, misfit_lags=0)).solve(
        problem, torch.ones(5, 3, dtype=torch.float64)
    )
    J = design[:, 0, :] * 10.0
    for b in range(5):
        information = J.T @ J + torch.diag(precision[b])
        expected = torch.linalg.solve(information, J.T @ (data[b, :, 0] * 10.0) + precision[b] * mean[b])
        assert torch.allclose(result.params[b], expected, rtol=1e-9, atol=1e-12)
        ridge_free = torch.linalg.solve(J.T @ J, J.T @ (data[b, :, 0] * 10.0))
        assert abs(result.params[b, 2]) < abs(ridge_free[2])  # the strong prior shrinks c towards 0
        posterior = torch.linalg.inv(J.T @ J / result.residual_variance[b] + torch.diag(precision[b]))
        assert torch.allclose(result.std[b], posterior.diagonal().sqrt(), rtol=1e-9)
    with pytest.raises(ValueError, match="prior"):
        LeastSquaresProblem(
            data,
            torch.zeros(5, 40, dtype=torch.float64),
            H,
            observed=(True,),
            model=_linear_model(design),
            prior_mean=mean,
        )


def _armijo_search(phi, loss0, slope, last=30):
    """Drive _next_exponent on a 1-D loss φ(α) (α = 2^-e): the accepted e and the number of trials."""
    from hybridqcm.estimation.line_search import _next_exponent

    failed, passed, e, trials = -1, last + 1, 0, 0
    while 0 <= e <= last:
        alpha = 0.5**e
        value = phi(alpha)
        trials += 1
        if math.isfinite(value) and value <= loss0 - 1e-4 * alpha * slope:
            passed = e
        else:
            failed = e
        t = lambda x, dtype=torch.float64: torch.tensor([x], dtype=dtype)  # noqa: E731
        e = int(
            _next_exponent(t(failed, torch.long), t(passed, torch.long), t(alpha), t(value), t(loss0), t(slope), last)
        )
    return (passed if passed <= last else None), trials


@pytest.mark.parametrize("power", [2, 4, 8])
@pytest.mark.parametrize("overshoot", [1.0, 3.0, 50.0, 2000.0, 1e5])
def test_interpolated_line_search_ends_on_the_halving_step(power, overshoot):
    """φ(α) = L0 − gα + 1.5 g (sα)^p / (s p): a step that overshoots by ``overshoot`` a loss of growth ``power``.
    The halving search's answer (the first e = 0, 1, ... that passes Armijo, found by a scan) is found, in far
    fewer trials where halving needs many."""
    loss0, slope = 10.0, 2.0

    def phi(alpha):
        x = alpha * overshoot
        return loss0 - slope * alpha + slope / overshoot * x**power / power * 1.5 if x < 1e30 else math.inf

    halving = next((e for e in range(31) if phi(0.5**e) <= loss0 - 1e-4 * 0.5**e * slope), None)
    found, trials = _armijo_search(phi, loss0, slope)
    assert found == halving
    assert trials <= 7  # the parabola's guess, then a bisection of at most 30 exponents
    if halving >= 11:
        assert trials <= halving + 1 - 4


def test_interpolated_line_search_gives_the_halving_estimates(data):
    problem = LeastSquaresProblem(data["accel"][:16], data["road"][:16], H)
    init = _near_truth(data["params"][:16], 0.3, seed=3)
    halve = GaussNewton(SolverConfig(max_iterations=40)).solve(problem, init)
    interpolate = GaussNewton(SolverConfig(max_iterations=40, backtrack="interpolate")).solve(problem, init)
    assert torch.equal(interpolate.status, halve.status) and torch.equal(interpolate.iterations, halve.iterations)
    assert torch.allclose(interpolate.params, halve.params, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="backtrack"):
        GaussNewton(SolverConfig(backtrack="cubic"))


def test_eigh_in_slices_equals_one_call_and_pseudo_inverse_is_exact():
    """The sliced eigen-decomposition (used off the CPU for large batches) gives the whole batch's
    eigenvalues and the same matrices back, and the pseudo-inverse of a full-rank batch is its inverse."""
    from hybridqcm.estimation._linalg import _eigh, pseudo_inverse

    gen = torch.Generator().manual_seed(3)
    a = torch.randn(50, 6, 6, dtype=torch.float64, generator=gen)
    m = a @ a.transpose(1, 2) + 0.1 * torch.eye(6, dtype=torch.float64)
    whole_values, _ = torch.linalg.eigh(m)
    values, vectors = _eigh(m, slice_rows=7)
    assert values.shape == (50, 6) and torch.allclose(values, whole_values, rtol=1e-12, atol=0)
    rebuilt = vectors @ torch.diag_embed(values) @ vectors.transpose(1, 2)
    assert torch.allclose(rebuilt, m, rtol=1e-10, atol=1e-10)
    pinv, unidentified, _, deficient = pseudo_inverse(m, rcond=1e-10)
    assert torch.allclose(pinv, torch.linalg.inv(m), rtol=1e-8, atol=1e-10)
    assert not unidentified.any() and not deficient.any()


def _overshooting_steps(data, config, seed, blow):
    """For the line-search tests: a solver, its run from near the truth of the first len(``blow``) samples, and their
    Gauss-Newton steps and predicted decreases blown up by ``blow`` [n] -> (solver, run, index, step, loss, predicted)."""
    n = blow.numel()
    problem = LeastSquaresProblem(data["accel"][:n], data["road"][:n], H)
    solver = GaussNewton(config)
    run = solver._start(problem, _near_truth(data["params"][:n], 0.2, seed=seed))
    index = torch.arange(n)
    fisher, gradient, loss = run.evaluation.normal_equations(run.params, index)
    step, predicted, _ = solver._step(run, index, fisher, gradient, loss)
    return solver, run, index, step * blow[:, None], loss, predicted * blow


def _counted_losses(run):
    """run.evaluation.loss_at wrapped to record each call's row count -> (evaluation, the real loss_at, the counts);
    the caller restores ``evaluation.loss_at = real``."""
    evaluation, calls = run.evaluation, []
    real = evaluation.loss_at

    def counted(trial, rows):
        calls.append(rows.numel())
        return real(trial, rows)

    evaluation.loss_at = counted
    return evaluation, real, calls


@pytest.mark.parametrize("parametrization", ["unconstrained", "linear"])
def test_the_halving_search_in_blocks_takes_each_samples_first_passing_step(data, parametrization):
    """line_search's "halve" tries the exponents in blocks, one model call per block: each sample's α must be the
    first α0 2^-e that passes the Armijo test, found by a scan of one sample at a time (the same loss_at), for
    Gauss-Newton steps blown up 1-10⁶× (0-25 halvings), in at most five calls for 31 exponents; and in one call
    where each sample's first block reaches its last accepted e (the same search again)."""
    from hybridqcm.estimation.line_search import line_search

    blow = 10.0 ** torch.linspace(0, 6, 24, dtype=torch.float64)  # steps that overshoot by up to 10⁶
    solver, run, index, step, loss, predicted = _overshooting_steps(
        data, SolverConfig(parametrization=parametrization), 5, blow
    )
    evaluation, real, calls = _counted_losses(run)
    alpha, new_loss = line_search(solver, run, index, step, loss, predicted)
    assert len(calls) <= 5
    calls.clear()
    again, _ = line_search(solver, run, index, step, loss, predicted)  # run.exponent now holds each sample's e
    evaluation.loss_at = real
    assert len(calls) == 1 and torch.equal(again, alpha)

    expected_alpha, expected_loss = torch.zeros(24, dtype=torch.float64), loss.clone()
    free = run.free
    for i in range(24):
        for e in range(31):
            a = 0.5**e
            trial = run.params[i : i + 1].clone()
            trial[:, free] = trial[:, free] - a * step[i : i + 1]
            if parametrization == "linear" and not bool((trial[:, free] > 0).all()):
                continue
            value = float(real(trial, index[i : i + 1]))
            if math.isfinite(value) and value <= float(loss[i]) - 1e-4 * a * float(predicted[i]):
                expected_alpha[i], expected_loss[i] = a, value
                break
    assert torch.equal(alpha, expected_alpha)
    assert (expected_alpha[blow > 1e3] < 1e-2).all() and (expected_alpha > 0).all()  # real backtracking, all found
    torch.testing.assert_close(new_loss, expected_loss, rtol=1e-12, atol=0)


@pytest.mark.parametrize("overshoot", [1.0, 1e3])
def test_the_interpolated_search_with_speculative_trials_is_the_same_search_in_fewer_calls(
    data, overshoot, monkeypatch
):
    """line_search's "interpolate" evaluates, for a few samples, the two exponents it may go to next beside the one it
    needs (_with_speculation): the accepted α and losses must be those of the search without them, bit for bit
    (the Euler model's loss of a sample does not depend on the rows beside it), in fewer model calls, each with at most
    three trials a sample; and with more samples than _SPECULATE the calls are those of the plain search."""
    from hybridqcm.estimation import line_search as line_search_module

    blow = overshoot * 10.0 ** torch.linspace(0, 3, 12, dtype=torch.float64)  # 0 to ~20 halvings
    solver, run, index, step, loss, predicted = _overshooting_steps(
        data, SolverConfig(backtrack="interpolate"), 9, blow
    )
    evaluation, real, calls = _counted_losses(run)
    results = {}
    for speculate in (0, 16):
        monkeypatch.setattr(line_search_module, "_SPECULATE", speculate)
        run.exponent[index] = 0
        calls.clear()
        results[speculate] = (*line_search_module.line_search(solver, run, index, step, loss, predicted), list(calls))
    evaluation.loss_at = real
    (alpha, new_loss, plain), (alpha_s, new_loss_s, speculative) = results[0], results[16]
    assert torch.equal(alpha_s, alpha) and torch.equal(new_loss_s, new_loss)
    assert len(speculative) < len(plain) and max(speculative) <= 3 * 12 and max(plain) <= 12
    # and it is halving's answer (the Armijo test is monotone in e here): each sample's first passing α = 2^-e, by a
    # scan of one sample at a time
    for i in range(12):
        for e in range(31):
            trial = run.params[i : i + 1].clone()
            trial[:, run.free] = trial[:, run.free] - 0.5**e * step[i : i + 1]
            value = float(real(trial, index[i : i + 1]))
            if value <= float(loss[i]) - 1e-4 * 0.5**e * float(predicted[i]):
                assert float(alpha[i]) == 0.5**e and float(new_loss[i]) == pytest.approx(value, rel=1e-12, abs=0)
                break
        else:
            raise AssertionError(f"sample {i}: no step passes")
    assert (alpha < 1).any()  # some after backtracking


def test_the_step_on_the_chunk_threads_is_the_step_on_one_bit_for_bit(monkeypatch):
    """With num_threads 2 the per-sample solves of the step run in two parts on threads (here from 2 x 4 samples
    on): every estimate, status and iteration count is one thread's, for both methods."""
    monkeypatch.setattr(solver_module, "_STEP_PART", 4)
    calls = []
    original = solver_module.parallel_map
    monkeypatch.setattr(solver_module, "parallel_map", lambda *a: calls.append(1) or original(*a))
    data = synthetic_samples(24, n_steps=60, seed=7)
    problem = LeastSquaresProblem(data["accel"], data["road"], 0.01)
    start = data["params"] * (
        1 + 0.2 * torch.randn(24, 10, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    )
    for method in (GaussNewton, LevenbergMarquardt):
        one = method(SolverConfig(max_iterations=8, num_threads=1, chunk_size=5)).solve(problem, start)
        calls.clear()
        two = method(SolverConfig(max_iterations=8, num_threads=2, chunk_size=5)).solve(problem, start)
        assert calls, "the step did not go to the threads"
        assert torch.equal(one.params, two.params) and torch.equal(one.status, two.status)
        assert torch.equal(one.iterations, two.iterations)
