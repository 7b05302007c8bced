"""Parameter priors: acceptance rate, rejection of unstable draws, stability, determinism."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hybridqcm.physics.integrators import simulate
from hybridqcm.physics.parameters import REFERENCE_VEHICLE as V
from hybridqcm.physics.parameters import is_stable, occupant_mass, reference_params
from hybridqcm.physics.prior import PhysicalPrior, ThesisPrior, build_prior, reference_draw


def independent_stable(p: np.ndarray, h: float) -> np.ndarray:
    """Stability by numpy eigenvalues of matrices built from SPEC §1 (independent of the package)."""
    out = []
    I, Z = np.eye(3), np.zeros((3, 3))
    for row in p:
        p1, p2, p3, p4, p5, p6, p7, p8, p9, p10 = row
        D = np.array([[-p1, p1, 0], [p3, -(p3 + p4), p4], [0, p7, -p8]])
        S = np.array([[-p2, p2, 0], [p5, -(p5 + p6), p6], [0, p9, -p10]])
        cont = np.linalg.eigvals(np.block([[D, S], [I, Z]])).real.max() < 0
        disc = np.abs(np.linalg.eigvals(np.block([[I + h * D, h * S], [h * (I + h * D), I + h * h * S]]))).max() < 1
        out.append(cont and disc and (row > 0).all())
    return np.array(out)


def test_thesis_acceptance_rate_is_about_64_percent():
    draw = ThesisPrior().sample(20000, torch.Generator().manual_seed(11))
    assert draw.params.shape == (20000, 10) and draw.params.dtype == torch.float64
    # SPEC §2: about 36 % of thesis draws are unstable. Binomial std at this size ~0.003.
    assert 0.62 < draw.acceptance_rate < 0.66, draw.acceptance_rate
    assert bool(is_stable(draw.params, 0.01).all())


def test_thesis_prior_keeps_exactly_the_stable_candidates_in_order():
    """Replay the candidate stream with the same generator state: the accepted set is the first n
    stable candidates (by an independent stability check), and n_drawn counts the stream up to
    the last accepted one."""
    prior, n = ThesisPrior(), 500
    draw = prior.sample(n, torch.Generator().manual_seed(5))
    batch = max(64, int(1.6 * n))  # the first round's candidate count
    candidates = prior._candidates(batch, torch.Generator().manual_seed(5)).numpy()
    stable = independent_stable(candidates, 0.01)
    assert stable.sum() >= n, "seed chosen so one round suffices"
    assert (~stable).sum() > 0.2 * batch, "the stream must contain unstable draws"
    np.testing.assert_array_equal(draw.params.numpy(), candidates[stable][:n])
    assert draw.n_drawn == int(np.flatnonzero(stable)[n - 1]) + 1
    assert draw.acceptance_rate == pytest.approx(n / draw.n_drawn)


def test_rejected_thesis_draws_really_blow_up():
    """The rejected candidates are the physically unstable ones: after one kick on the wheel and no
    road, every rejected system's displacement grows from [10 s, 20 s) to [20 s, 30 s) (some by
    orders of magnitude), while every accepted one decays."""
    candidates = ThesisPrior()._candidates(200, torch.Generator().manual_seed(9))
    ok = is_stable(candidates, 0.01)
    assert 40 < int((~ok).sum()) < 160
    road = torch.zeros(200, 3000, dtype=torch.float64)
    road[:, 0] = 1.0
    x = simulate(candidates, road, 0.01, scaled_road=True).disp.abs()
    growth = x[:, 2000:].amax((1, 2)) / x[:, 1000:2000].amax((1, 2))
    assert growth[ok].max() < 1
    assert growth[~ok].min() > 1
    assert growth[~ok].max() > 1e6


def test_thesis_prior_structure():
    p = ThesisPrior().sample(3000, torch.Generator().manual_seed(2)).params
    m3 = occupant_mass(p)
    assert (m3 >= 30).all() and (m3 <= 150).all()
    assert m3.min() < 35 and m3.max() > 145  # the whole mass range is used
    torch.testing.assert_close(p[:, 0] / p[:, 1], torch.full_like(m3, V.C3 / V.K3))  # C3, K3 at reference
    rel = p[:, 2:] / reference_params()[2:] - 1
    # accepted draws are skewed by the rejection (p7 > p8 is mostly unstable) but stay near 10 %
    assert (rel.std(0) > 0.06).all() and (rel.std(0) < 0.12).all()
    assert (p[:, 6] - p[:, 7]).mean() < 0  # rejection favours p7 < p8


@pytest.mark.parametrize("perturb_seat", [False, True])
def test_physical_prior_always_stable_and_consistent(perturb_seat):
    prior = PhysicalPrior(perturb_seat=perturb_seat, sigma=0.1)
    candidates = prior._candidates(5000, torch.Generator().manual_seed(4))
    assert bool(is_stable(candidates, 0.01).all())  # every candidate, not just the accepted ones
    draw = prior.sample(2000, torch.Generator().manual_seed(4))
    assert draw.acceptance_rate == 1.0
    p = draw.params
    torch.testing.assert_close(p[:, 6], p[:, 7], rtol=0, atol=0)  # C1 = 0: p7 = p8
    torch.testing.assert_close(p[:, 0] / p[:, 1], p[:, 2] / p[:, 4])  # C3/K3 from either mass
    torch.testing.assert_close(p[:, 3] / p[:, 5], p[:, 6] / p[:, 8])  # C2/K2 from either mass
    assert (p[:, 9] > p[:, 8]).all()  # p_u = K1/m1 > 0
    seat_ratio = p[:, 0] / p[:, 1]
    if perturb_seat:
        assert seat_ratio.std() > 0.01 * seat_ratio.mean()
    else:
        torch.testing.assert_close(seat_ratio, torch.full_like(seat_ratio, V.C3 / V.K3))


def test_prior_is_deterministic_and_seed_dependent():
    a = ThesisPrior().sample(300, torch.Generator().manual_seed(1))
    b = ThesisPrior().sample(300, torch.Generator().manual_seed(1))
    c = ThesisPrior().sample(300, torch.Generator().manual_seed(2))
    assert torch.equal(a.params, b.params) and a.n_drawn == b.n_drawn
    assert not torch.equal(a.params, c.params)


def test_prior_edge_cases_and_validation():
    assert ThesisPrior().sample(0).params.shape == (0, 10)
    assert isinstance(build_prior("thesis"), ThesisPrior)
    assert isinstance(build_prior("physical", perturb_seat=True), PhysicalPrior)
    with pytest.raises(ValueError, match="unknown prior 'nope'"):
        build_prior("nope")
    with pytest.raises(ValueError, match="sigma"):
        ThesisPrior(sigma=-0.1)
    with pytest.raises(ValueError, match="mass_range"):
        ThesisPrior(mass_range=(150.0, 30.0))
    with pytest.raises(ValueError, match="h"):
        ThesisPrior(h=0.0)
    with pytest.raises(ValueError, match=">= 0"):
        ThesisPrior().sample(-1)
    ref = reference_draw(4)
    assert ref.params.shape == (4, 10) and torch.equal(ref.params[3], reference_params())


def test_prior_raises_when_nothing_is_stable():
    prior = ThesisPrior(h=1.0)  # Euler at h = 1 s is unstable for every draw
    prior.max_rounds = 3
    with pytest.raises(RuntimeError, match="acceptance too low"):
        prior.sample(10, torch.Generator().manual_seed(0))
