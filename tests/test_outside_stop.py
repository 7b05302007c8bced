"""A noise-whitened Gauss-Newton path that converges outside the domain p > 0 is stopped there as `diverged`
(SolverConfig.outside_tol), with the status it would have ended with and nothing else changed."""

from __future__ import annotations

import math

import pytest
import torch

from hybridqcm.errors import ConfigError
from hybridqcm.estimation.problems import LeastSquaresProblem
from hybridqcm.estimation.response import ExactResponse
from hybridqcm.estimation.solver import GaussNewton, SolverConfig, SolverStatus
from hybridqcm.physics.linear_models import SeatOccupantBaseExcitation
from hybridqcm.physics.occupant import body_start
from test_boundary import K3, MASS, B, H, _recordings  # a seat's recordings: rigid occupants or persons, 5 % noise

SEED, SCALE = 3, 1.1  # rigid occupants whose body1 fits from 10 % off end `diverged` (one of them converging there)


def _body_start(scale: float) -> torch.Tensor:
    p = torch.stack([615.0 / MASS, K3 / MASS], 1) * scale
    return torch.cat([p, body_start(1).expand(B, -1), torch.zeros(B, 4, dtype=torch.float64)], 1)


def _solve(a2, y, noise, start, **config):
    body = ExactResponse(SeatOccupantBaseExcitation(1), H, initial_state="unknown")
    problem = LeastSquaresProblem(y, a2, H, observed=(True,), model=body, noise=noise)
    return GaussNewton(SolverConfig(backtrack="interpolate", **config)).solve(problem, start)


def test_a_path_converging_outside_the_domain_is_stopped_there_with_the_status_it_would_end_with():
    """body1 on rigid occupants (the occupant selection's candidates on ballast): without the stop, the fits that
    end `diverged` (r1 < 0) spend their last iterations converging there; with it the same fits end `diverged`
    sooner, still outside, and every other fit is the same (to round-off: the batch's active set differs)."""
    a2, y, noise = _recordings(body=False, seed=SEED)
    plain = _solve(a2, y, noise, _body_start(SCALE))
    stopped = _solve(a2, y, noise, _body_start(SCALE), outside_tol=1.0)
    out = plain.status == SolverStatus.DIVERGED
    sooner = stopped.iterations < plain.iterations
    assert bool(sooner.any()) and bool(out[sooner].all())  # (here 16 -> 8 iterations)
    assert (plain.params[sooner, 2] < 0).all() and (stopped.params[sooner, 2] < 0).all()  # r1 < 0 in both
    assert stopped.status.tolist() == plain.status.tolist()
    assert (stopped.iterations <= plain.iterations).all()
    same = ~sooner
    torch.testing.assert_close(stopped.params[same], plain.params[same], rtol=1e-8, atol=0)


@pytest.mark.parametrize("seed", [3, 4])
def test_a_persons_fit_inside_the_domain_is_untouched(seed):
    """A person's recordings fitted with body1 from the prior's centre: no path leaves the domain to stay, and
    every number is the one without the stop, bit for bit."""
    a2, y, noise = _recordings(body=True, seed=seed)
    plain = _solve(a2, y, noise, _body_start(1.05))
    stopped = _solve(a2, y, noise, _body_start(1.05), outside_tol=1.0)
    assert (plain.status == SolverStatus.CONVERGED).all()
    assert ((K3 / plain.params[:, 1] / MASS - 1).abs() < 0.1).all()  # real fits of the person
    torch.testing.assert_close(stopped.params, plain.params, rtol=0, atol=0)
    torch.testing.assert_close(stopped.std, plain.std, rtol=0, atol=0)
    assert stopped.iterations.tolist() == plain.iterations.tolist()


def test_without_a_noise_model_the_stop_does_not_apply():
    """The tolerance is in nats of a noise-whitened loss; a plain least-squares fit has no such unit and is not
    stopped (the same numbers with and without it)."""
    a2, y, _ = _recordings(body=False, seed=SEED)
    plain = _solve(a2, y, None, _body_start(SCALE))
    stopped = _solve(a2, y, None, _body_start(SCALE), outside_tol=1.0)
    torch.testing.assert_close(stopped.params, plain.params, rtol=0, atol=0)
    assert stopped.iterations.tolist() == plain.iterations.tolist()


@pytest.mark.parametrize("bad", [-1.0, math.inf, math.nan, "1", True])
def test_an_outside_tolerance_that_is_not_a_number_of_nats_is_refused(bad):
    with pytest.raises(ValueError, match="outside_tol"):
        GaussNewton(SolverConfig(outside_tol=bad))
    from omegaconf import OmegaConf

    from hybridqcm.estimation.plan_settings import solver_settings

    cfg = OmegaConf.create({"solver": {"method": "gauss_newton", "outside_tol": bad}})
    with pytest.raises(ConfigError, match=r"solver\.outside_tol"):
        solver_settings(cfg)
