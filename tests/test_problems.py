"""ProblemEvaluation's passes (estimation/problems.py): the normal equations against the Gram of the
explicitly formed (R | J), with the chunks on several threads, the modal path's fallback samples
gathered over the chunks of a pass, and the residual subtracted inside the models."""

from __future__ import annotations

import math

import pytest
import torch

import hybridqcm.estimation.problems as problems_module
from hybridqcm.estimation._kernels import compiled_loops
from hybridqcm.estimation.delay import DelayedResponse
from hybridqcm.estimation.exact import exact_outputs, exact_sensitivities, fallback_sensitivities
from hybridqcm.estimation.hold import held_input
from hybridqcm.estimation.problems import LeastSquaresProblem, ProblemEvaluation
from hybridqcm.estimation.response import EulerResponse, ExactResponse
from hybridqcm.estimation.sensitivity import euler_sensitivities
from hybridqcm.physics import reference_params
from hybridqcm.physics.linear_models import QuarterCarRoad, SeatBaseExcitation
from hybridqcm.testing import synthetic_samples

F64 = torch.float64


def _seat_problem(batch: int = 24, observed=(True,)):
    """Seat models damped near critically every fourth sample (double eigenvalue: the modal path hands
    them to the recursion), the others well apart; x0 unknown, a margin of 8 samples."""
    g = torch.Generator().manual_seed(5)
    p2 = 100.0 + 400.0 * torch.rand(batch, generator=g, dtype=F64)
    zeta = torch.where(torch.arange(batch) % 4 == 0, 1.0, 0.2 + 0.3 * torch.rand(batch, generator=g, dtype=F64))
    theta = torch.cat([torch.stack([2 * zeta * p2.sqrt(), p2], 1), 0.01 * torch.randn(batch, 2, generator=g)], 1)
    inputs = torch.randn(batch, 116, 1, generator=g, dtype=F64)
    targets = torch.randn(batch, 100, 1, generator=g, dtype=F64)
    model = ExactResponse(SeatBaseExcitation(), 0.01, "spline", 4, initial_state="unknown")
    return LeastSquaresProblem(targets, inputs, 0.01, model=model, input_offset=8, observed=observed), theta


def _explicit_normal_equations(problem: LeastSquaresProblem, theta):
    """F, JᵀR, L from (R | J) formed with the step recursion (an independent code path)."""
    model = problem.model
    out = exact_sensitivities(
        model.model, theta[:, : model.n_params], theta[:, model.n_params :], problem.inputs, 0.01, "spline", 4,
        start=8, n_steps=100, method="recursion",
    )  # fmt: skip
    obs = problem.observed_index
    out = out[:, :, obs]
    out[..., 0] -= problem.targets[:, :, obs]
    a = out.reshape(out.shape[0], -1, out.shape[-1])
    gram = a.transpose(1, 2) @ a
    return gram[:, 1:, 1:], gram[:, 1:, 0], 0.5 * gram[:, 0, 0]


@pytest.mark.parametrize("workers", [1, 2])
def test_normal_equations_with_fallback_samples_match_the_explicit_gram(workers):
    problem, theta = _seat_problem()
    evaluation = ProblemEvaluation(problem, chunk_size=5, workers=workers)  # chunks of 5: fallback rows in several
    index = torch.arange(theta.shape[0])
    _, redo = problem.model.sensitivities_deferred(theta, evaluation.road[index], *problem.window)
    assert redo.numel() >= 4  # the critically damped samples are left to the fallback
    fisher, gradient, loss = evaluation.normal_equations(theta, index)
    expected = _explicit_normal_equations(problem, theta)
    for got, want in zip((fisher, gradient, loss), expected):
        scale = want.abs().reshape(want.shape[0], -1).amax(1).clamp_min(1e-300)
        assert float(((got - want).abs().reshape(want.shape[0], -1).amax(1) / scale).max()) < 1e-9


def test_threads_give_the_numbers_of_one_thread_bit_for_bit():
    problem, theta = _seat_problem(40)
    index = torch.arange(40).flip(0)[::2]  # an unordered subset, as the solver's active samples
    one = ProblemEvaluation(problem, chunk_size=4).data_normal_equations(theta, index, band=3)
    two = ProblemEvaluation(problem, chunk_size=4, workers=2).data_normal_equations(theta, index, band=3)
    for a, b in zip(one[:4], two[:4]):
        assert torch.equal(a, b)
    assert one[4][0] == two[4][0]
    trial = theta * 1.01
    loss_one = ProblemEvaluation(problem, chunk_size=2).loss_at(trial[index], index)
    loss_two = ProblemEvaluation(problem, chunk_size=2, workers=2).loss_at(trial[index], index)
    assert torch.equal(loss_one, loss_two)


_COMPILED = pytest.mark.skipif(not compiled_loops(), reason="the pieces even out where the compiled loops run")


@_COMPILED
@pytest.mark.parametrize("workers", [2, 3])
def test_pieces_cover_every_row_once_in_order_and_even_out_the_workers(workers):
    evaluation = ProblemEvaluation(_seat_problem(4)[0], chunk_size=512, workers=workers)
    for n in (0, 1, 127, 255, 256, 300, 1000, 1500, 6928, 17000, 17001):
        for size in (5, 512, 1024):
            pieces = evaluation._pieces(n, size, problems_module._MIN_PIECE, True)
            assert [r for p in pieces for r in range(p.start, p.stop)] == list(range(n))
            lengths = [p.stop - p.start for p in pieces]
            assert all(0 < length <= size for length in lengths)
            assert len(pieces) <= -(-n // size) + workers - 1  # no more than one round of the workers more
            if n >= problems_module._MIN_PIECE * workers:
                assert max(lengths) - min(lengths) <= 1
                # a multiple of the workers wherever the pieces keep their least rows
                rounded = math.ceil(math.ceil(n / size) / workers) * workers
                assert len(pieces) % workers == 0 or n // rounded < problems_module._MIN_PIECE
    before = [(0, 512), (512, 1024), (1024, 1500)]
    one = ProblemEvaluation(_seat_problem(4)[0], chunk_size=512)._pieces(1500, 512, 64, True)
    assert [(p.start, p.stop) for p in one] == before  # one worker: as before
    assert [(p.start, p.stop) for p in evaluation._pieces(1500, 512, 64, False)] == before  # not apart: as before
    two = evaluation._pieces(1500, 512, 64, True)
    assert len(two) == (3 if workers == 3 else 4) and {p.stop - p.start for p in two} <= {375, 500}
    assert (
        len(evaluation._pieces(300, 1024, 256, True)) == 1 and len(evaluation._pieces(300, 1024, 64, True)) == workers
    )


def test_which_passes_a_model_lets_a_solve_cut_anywhere():
    problem, _ = _seat_problem(4)
    delayed = DelayedResponse(problem.model)
    assert EulerResponse(0.01).outputs_apart and EulerResponse(0.01).sensitivities_apart
    assert problem.model.outputs_apart and not problem.model.sensitivities_apart  # ExactResponse
    assert not delayed.outputs_apart and not delayed.sensitivities_apart


def test_the_exact_models_sensitivities_depend_on_their_batch_mates_modes():
    """Why ExactResponse.sensitivities_apart is False: an under-damped seat's sensitivities are other bits beside an
    over-damped one (the modal basis is as wide as the batch's largest number of propagated modes), its outputs
    are not (the step recursion: per sample). If this ever holds bit for bit, the Jacobian pass may be cut too."""
    model = SeatBaseExcitation()
    g = torch.Generator().manual_seed(5)
    zeta = torch.tensor([0.2, 0.3, 2.5, 0.25], dtype=F64)
    params = torch.stack([2 * zeta * 300.0**0.5, torch.full((4,), 300.0, dtype=F64)], 1)
    x0 = 0.01 * torch.randn(4, 2, generator=g, dtype=F64)
    inputs = torch.randn(4, 116, 1, generator=g, dtype=F64)
    window = dict(start=8, n_steps=100)
    with_mate = exact_sensitivities(model, params, x0, inputs, 0.01, "spline", 4, **window)[[0, 1, 3]]
    alone = exact_sensitivities(model, params[[0, 1, 3]], x0[[0, 1, 3]], inputs[[0, 1, 3]], 0.01, "spline", 4, **window)
    assert not torch.equal(with_mate, alone)
    torch.testing.assert_close(with_mate, alone, rtol=1e-12, atol=1e-15 * float(alone.abs().max()))
    # the outputs from the held input prepared once for the whole problem (as a solve holds it), batch first
    held = held_input(inputs, "spline", 4, 8, 100).permute(2, 1, 0).contiguous().permute(2, 1, 0)
    rows = torch.tensor([0, 1, 3])
    outputs = exact_outputs(model, params, x0, inputs, 0.01, "spline", 4, **window, held=held)[rows]
    alone = exact_outputs(
        model, params[rows], x0[rows], inputs[rows], 0.01, "spline", 4, **window, held=held[..., rows]
    )
    assert torch.equal(outputs, alone)


@_COMPILED
def test_pieces_of_several_workers_give_one_workers_numbers_bit_for_bit(monkeypatch):
    """Cut into other pieces than one worker's (the least rows lowered so that 20 samples are): the Euler model's
    normal equations, scores and trial losses, and the exact model's trial losses, are the same bits, each sample
    evaluated on its own."""
    monkeypatch.setattr(problems_module, "_MIN_PIECE", 3)
    monkeypatch.setattr(problems_module, "_MIN_TRIAL_PIECE", 3)
    data = synthetic_samples(40, n_steps=60, seed=4)
    euler = LeastSquaresProblem(data["accel"], data["road"], 0.01)
    theta = data["params"] * (1 + 0.05 * torch.randn(40, 10, generator=torch.Generator().manual_seed(2), dtype=F64))
    index = torch.arange(40).flip(0)[::2]  # 20 samples: pieces of 7, 7, 6 on one worker, 5 x 4 on two
    one = ProblemEvaluation(euler, chunk_size=7)
    two = ProblemEvaluation(euler, chunk_size=7, workers=2)
    assert [p.stop - p.start for p in one._pieces(20, 7, 3, True)] == [7, 7, 6]
    assert [p.stop - p.start for p in two._pieces(20, 7, 3, True)] == [5, 5, 5, 5]
    a, b = one.data_normal_equations(theta, index, band=3), two.data_normal_equations(theta, index, band=3)
    for x, y in zip(a[:4], b[:4]):
        assert torch.equal(x, y)
    assert torch.equal(one.loss_at(theta[index] * 1.01, index), two.loss_at(theta[index] * 1.01, index))
    seat, seat_theta = _seat_problem(40)  # damped near critically every fourth sample, the others apart
    trial = seat_theta[index] * 1.01
    one, two = ProblemEvaluation(seat, chunk_size=4), ProblemEvaluation(seat, chunk_size=4, workers=2)
    assert torch.equal(one.loss_at(trial, index), two.loss_at(trial, index))


def test_deferred_fallback_rows_are_those_fallback_sensitivities_gives():
    problem, theta = _seat_problem()
    model = problem.model
    args = (model.model, theta[:, :2], theta[:, 2:], problem.inputs, 0.01, "spline", 4)
    full = exact_sensitivities(*args, start=8, n_steps=100)
    deferred, rows = exact_sensitivities(*args, start=8, n_steps=100, defer_fallback=True)
    keep = torch.ones(theta.shape[0], dtype=torch.bool)
    keep[rows] = False
    assert torch.equal(deferred[keep], full[keep])
    fixed = fallback_sensitivities(
        model.model, theta[rows, :2], theta[rows, 2:], problem.inputs[rows], 0.01, "spline", 4, start=8, n_steps=100
    )
    # the same numbers up to round-off: the rows recomputed as a batch of their own (on some CPUs torch's
    # vectorised kernels round a batch's tail differently; measured here 2e-13 relative at most)
    torch.testing.assert_close(fixed, full[rows], rtol=1e-12, atol=1e-15)


def test_residual_is_subtracted_inside_the_models():
    """Exact (modal and recursion) and Euler: column 0 with ``targets`` is the prediction less them."""
    problem, theta = _seat_problem()
    args = (problem.model.model, theta[:, :2], theta[:, 2:], problem.inputs, 0.01, "spline", 4)
    for method in ("modal", "recursion"):
        plain = exact_sensitivities(*args, start=8, n_steps=100, method=method)
        residual = exact_sensitivities(*args, start=8, n_steps=100, method=method, targets=problem.targets)
        assert torch.equal(residual[..., 1:], plain[..., 1:])
        want = plain[..., 0] - problem.targets
        assert float((residual[..., 0] - want).abs().max()) <= 1e-12 * float(want.abs().max())
    data = synthetic_samples(6, n_steps=50, seed=2)
    params, road, accel = data["params"].to(F64), data["road"].to(F64), data["accel"].to(F64)
    plain = euler_sensitivities(params, road, 0.01)
    residual = euler_sensitivities(params, road, 0.01, targets=accel)
    assert torch.equal(residual[..., 1:], plain[..., 1:]) and torch.equal(residual[..., 0], plain[..., 0] - accel)


def test_unobserved_channels_take_no_part_in_the_residual():
    """Quarter car with a2 unobserved: the normal equations equal those of the problem built from the two
    observed channels' explicit residual (the full-width targets carry zeros on a2)."""
    data = synthetic_samples(5, n_steps=60, seed=4)
    theta = torch.cat([reference_params().expand(5, 10).to(F64), torch.zeros(5, 6, dtype=F64)], 1)
    model = ExactResponse(QuarterCarRoad(), 0.01, "spline", 4, initial_state="unknown")
    problem = LeastSquaresProblem(
        data["accel"][:, 5:55].to(F64), data["road"].to(F64), 0.01, model=model, input_offset=5,
        observed=(True, False, True),
    )  # fmt: skip
    fisher, gradient, loss = ProblemEvaluation(problem, chunk_size=2).normal_equations(theta, torch.arange(5))
    out = model.sensitivities(theta, data["road"].to(F64)[..., None], 5, 50)[:, :, [0, 2]]
    out[..., 0] -= problem.targets[:, :, [0, 2]]
    a = out.reshape(5, -1, 17)
    gram = a.transpose(1, 2) @ a
    assert torch.allclose(fisher, gram[:, 1:, 1:], rtol=1e-12, atol=0)
    assert torch.allclose(gradient, gram[:, 1:, 0], rtol=1e-10, atol=1e-12 * float(gradient.abs().max()))
    assert torch.allclose(loss, 0.5 * gram[:, 0, 0], rtol=1e-12, atol=0)


def test_a_subset_is_the_problem_of_those_samples():
    """LeastSquaresProblem.subset: its loss at the rows' θ is the whole problem's loss of those rows, with the
    errors-in-variables noise model and a prior (both per sample) indexed along, in any order of the rows."""
    from hybridqcm.estimation.noise import SpectralNoise
    from hybridqcm.estimation.solver import GaussNewton, SolverConfig

    problem, theta = _seat_problem()
    b = theta.shape[0]
    g = torch.Generator().manual_seed(7)
    noise = SpectralNoise(
        0.5 + torch.rand(b, 1, generator=g, dtype=F64),
        0.1 + torch.rand(b, 1, generator=g, dtype=F64),
        SeatBaseExcitation(),
        0.01,
    )
    problem = LeastSquaresProblem(
        problem.targets, problem.inputs, 0.01, model=problem.model, input_offset=8, observed=(True,), noise=noise,
        prior_mean=theta * (1 + 0.1 * torch.rand(theta.shape, generator=g, dtype=F64)),
        prior_precision=torch.rand(theta.shape, generator=g, dtype=F64),
    )  # fmt: skip
    solver = GaussNewton(SolverConfig())
    rows = torch.tensor([17, 3, 4, 22])
    whole = solver.objective(problem, theta)
    part = solver.objective(problem.subset(rows), theta[rows])
    torch.testing.assert_close(part, whole[rows], rtol=1e-12, atol=0)
    assert not torch.allclose(part, whole[torch.tensor([3, 17, 4, 22])])  # the rows' own, in their order
