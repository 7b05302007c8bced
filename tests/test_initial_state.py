"""The variable-projection start of the initial state (estimation/initial_state.py): x0 by linear
least squares at a fixed p, checked against the continuous-time simulator's own state and against
an explicit normal-equations solve built from output evaluations (another code path than the
sensitivities the projection uses)."""

import pytest
import torch

from hybridqcm.estimation.initial_state import project_initial_state
from hybridqcm.estimation.refinement import GaussNewtonRefinement, GaussNewtonStage, RefinementSettings
from hybridqcm.estimation.response import ExactResponse
from hybridqcm.estimation.restarts import Restarts
from hybridqcm.estimation.solver import GaussNewton
from hybridqcm.physics.continuous import simulate_continuous
from hybridqcm.physics.linear_models import QuarterCarRoad
from hybridqcm.physics.prior import build_prior

F64 = torch.float64
H = 0.01
BEFORE, T, AFTER = 4, 100, 8


@pytest.fixture(scope="module")
def drive():
    """Mid-drive windows (8-11 s after a start from rest) of the exact continuous-time response to a
    slow two-sine road: p, road [b, T_in, 1], accel [b, T, 3] and the simulated state at the window."""
    g = torch.Generator().manual_seed(7)
    params = build_prior("thesis", h=None).sample(4, g).params.to(F64)
    omega = torch.tensor([2 * torch.pi * 0.4, 2 * torch.pi * 1.1], dtype=F64)
    amplitude = 0.02 * (1 + torch.rand(4, 2, generator=g, dtype=F64))
    phase = 2 * torch.pi * torch.rand(4, 2, generator=g, dtype=F64)
    warmup = 8.0 + 3.0 * torch.rand(4, generator=g, dtype=F64)
    out = simulate_continuous(params, amplitude, phase, omega, BEFORE + T + AFTER, H, warmup)
    state = torch.cat([out.vel[:, BEFORE], out.disp[:, BEFORE]], -1)  # (v3 v2 v1 q3 q2 q1) at the window start
    return params, out.road[..., None], out.accel[:, BEFORE : BEFORE + T], state


def _response():
    return ExactResponse(QuarterCarRoad(), H, "spline", 16, "unknown")


def test_projection_at_the_true_p_is_the_state_the_data_came_from(drive):
    """Outputs of the exact model itself (its primal recursion) from a mid-drive state x0 ≠ 0: the
    projection (built from the sensitivities) returns that x0 to round-off, with all channels and
    with a3 alone (exp 8)."""
    params, road, _, state = drive
    assert float(state.abs().amin(1).min()) > 0  # a mid-drive state, off rest in every entry
    response = _response()
    theta = torch.cat([params, state], 1)
    exact = response.outputs(theta, road, BEFORE, T)
    start = torch.cat([params, torch.zeros_like(state)], 1)
    for observed in ((True, True, True), (True, False, False)):
        x0 = project_initial_state(response, start, road, exact, observed, start=BEFORE)
        assert torch.equal(x0[:, :10], params)
        error = ((x0[:, 10:] - state).abs() / state.abs().amax(1, keepdim=True)).max()
        assert float(error) < 1e-8, (observed, float(error))


def test_projection_on_continuous_time_data_is_the_simulated_state(drive):
    """Recordings of the continuous-time simulator (not the model): the state it reports at the
    window's first sample, to within the hold's model error (~1e-5 of the outputs at 16 sub-steps)."""
    params, road, accel, state = drive
    start = torch.cat([params, torch.zeros_like(state)], 1)
    x0 = project_initial_state(_response(), start, road, accel, (True, True, True), start=BEFORE)[:, 10:]
    error = ((x0 - state).abs() / state.abs().amax(1, keepdim=True)).max()
    assert float(error) < 1e-4, float(error)


def test_projection_off_the_true_p_is_the_weighted_least_squares_argmin(drive):
    """p 3 % off: x0 solves the weighted normal equations HᵀW²H x0 = HᵀW²(y - F), with F = y(p, 0)
    and the columns of H = y(p, e_j) - y(p, 0) taken from output evaluations."""
    params, road, accel, _ = drive
    g = torch.Generator().manual_seed(1)
    p = params * (1 + 0.03 * torch.randn(params.shape, generator=g, dtype=F64))
    weights = torch.tensor([[2.0, 1.0, 0.5]], dtype=F64).expand(4, 3)
    observed = (True, False, True)
    response = _response()
    theta = torch.cat([p, torch.ones(4, 6, dtype=F64)], 1)  # the start x0 must not matter
    x0 = project_initial_state(response, theta, road, accel, observed, weights, start=BEFORE)[:, 10:]

    def y(x):
        return response.outputs(torch.cat([p, x], 1), road, BEFORE, T)[:, :, [0, 2]] * weights[:, None, [0, 2]]

    free = y(torch.zeros(4, 6, dtype=F64))
    columns = torch.stack([y(torch.eye(6, dtype=F64)[j].expand(4, 6)) - free for j in range(6)], -1)
    design, rhs = columns.reshape(4, -1, 6), (accel[:, :, [0, 2]] * weights[:, None, [0, 2]] - free).reshape(4, -1)
    normal = torch.linalg.solve(design.mT @ design, (design.mT @ rhs[..., None]))[..., 0]
    assert torch.allclose(x0, normal, rtol=1e-7, atol=1e-9 * float(normal.abs().max()))
    loss = ((design @ x0[..., None])[..., 0] - rhs).square().sum(1)
    for step in (1e-3, -1e-3):  # and nothing nearby fits better
        nudged = ((design @ (x0 * (1 + step))[..., None])[..., 0] - rhs).square().sum(1)
        assert bool((nudged > loss).all())


def test_rank_deficient_window_still_fits(drive):
    """Two samples of a3 cannot determine six states (rank 2): the projection is finite, not the
    all-zero answer a rank-deficient least-squares driver can return, and fits both samples."""
    params, road, accel, state = drive
    response = _response()
    theta = torch.cat([params, torch.zeros_like(state)], 1)
    x0 = project_initial_state(response, theta, road, accel[:, :2], (True, False, False), start=BEFORE)
    assert torch.isfinite(x0).all() and bool((x0[:, 10:].abs().amax(1) > 0).all())
    fitted = response.outputs(x0, road, BEFORE, 2)[:, :, 0]
    assert torch.allclose(fitted, accel[:, :2, 0], rtol=0, atol=1e-8 * float(accel[:, :2, 0].abs().max()))


def test_refinement_validates_x0_start():
    with pytest.raises(ValueError, match="x0_start='zero'"):
        GaussNewtonRefinement([GaussNewtonStage("gn", GaussNewton())], RefinementSettings(x0_start="zero"))


def test_restarts_alternate_the_x0_start(drive):
    """x0_start="alternate": the first attempt starts x0 at the projection, restart 1 at rest,
    restart 2 at the projection again (at its own start p)."""
    params, road, accel, _ = drive
    starts = []

    class Recording(GaussNewton):
        def solve(self, problem, initial_params, callback=None):
            starts.append(initial_params.clone())
            return super().solve(problem, initial_params, callback)

    response = _response()
    refinement = GaussNewtonRefinement(
        [GaussNewtonStage("gn", Recording(max_iterations=1))],
        RefinementSettings(response=response, x0_start="alternate", peer_factor=None),
        restarts=Restarts(count=2, threshold=0.0),  # every sample is retried
    )
    init = params * 1.05
    outputs = {"targets": accel, "road": road, "pu": params[:, 9] - params[:, 8], "init": init}
    outputs.update(index=torch.arange(4), input_offset=BEFORE)
    refinement.refine(outputs)
    first, restarts = starts[0], starts[1]  # the two restarts run in one solver call
    assert len(starts) == 2 and restarts.shape[0] == 8
    expected = project_initial_state(
        response, torch.cat([init, torch.zeros(4, 6, dtype=F64)], 1), road, accel, (True,) * 3, start=BEFORE
    )
    assert torch.allclose(first, expected, rtol=1e-12, atol=0)
    assert bool((restarts[:4, 10:] == 0).all())  # restart 1: at rest
    again = project_initial_state(response, restarts[4:], road, accel, (True,) * 3, start=BEFORE)
    assert bool((restarts[4:, 10:].abs().amax(1) > 0).all()) and torch.allclose(restarts[4:], again, rtol=1e-12, atol=0)


def test_a_refinements_steps_between_solves_run_at_its_solves_torch_threads(drive, monkeypatch):
    """With the solves' chunks on two threads (each op on one), the x0 projection between solves runs at one torch
    thread too (op_threads), as a one-thread run's does: torch rounds a large reduction by its thread count, so at
    two it gave other numbers (exp 5, 2 048 recordings: up to 5e-5 relative). The estimates are one thread's."""
    import hybridqcm.estimation.refinement as refinement_module
    from hybridqcm.estimation.solver import SolverConfig

    params, road, accel, _ = drive
    seen = []
    original = refinement_module.project_initial_state
    monkeypatch.setattr(
        refinement_module,
        "project_initial_state",
        lambda *a, **k: seen.append(torch.get_num_threads()) or original(*a, **k),
    )
    outputs = {"targets": accel, "road": road, "pu": params[:, 9] - params[:, 8], "init": params * 1.05}
    outputs.update(index=torch.arange(4), input_offset=BEFORE)
    results = {}
    before = torch.get_num_threads()
    torch.set_num_threads(2)  # the process's own count, which the refinement must not inherit between solves
    try:
        for threads in (1, 2):
            seen.clear()
            stage = GaussNewtonStage("gn", GaussNewton(SolverConfig(max_iterations=4, num_threads=threads)))
            settings = RefinementSettings(response=_response(), x0_start="least_squares", peer_factor=None)
            refinement = GaussNewtonRefinement([stage], settings)
            results[threads] = refinement.refine(outputs)["final"]
            assert seen == [1], threads
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert torch.equal(results[1].params, results[2].params) and torch.equal(results[1].status, results[2].status)
