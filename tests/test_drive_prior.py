"""The prior counted once in a drive's combination (estimation/drive_prior.py) against the joint posterior it claims
to equal: linear-Gaussian windows, each fitted with the prior, whose joint posterior (every window's likelihood, the
prior once) is known in closed form; and windows Gaussian in log θ with a Gaussian prior in θ, where the combination
must be the stationary point of the joint log posterior (its gradient by autograd)."""

import pytest
import torch

from hybridqcm.estimation.drive import InformationCombiner, wald
from hybridqcm.estimation.drive_prior import PriorOnceCombiner


def _posterior_windows(n: int, seed: int):
    """Windows y_w = A_w θ + e (σ = 1), a few rows each (the prior matters), each fitted with the prior N(μ, 1/λ) on
    θ's last two entries. Returns (θ_w [n, 3], Σ_w [n, 3, 3], μ [3], λ [3], the joint posterior's mean and
    covariance, the windows' least-squares estimates [n, 3] and their information A_wᵀA_w [n, 3, 3])."""
    g = torch.Generator().manual_seed(seed)
    truth = torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
    mu = torch.tensor([0.0, 1.5, 0.0], dtype=torch.float64)
    lam = torch.tensor([0.0, 4.0, 2.0], dtype=torch.float64)
    thetas, covs, infos, moments = [], [], [], []
    for _ in range(n):
        A = torch.randn(5, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.4, 0.3], dtype=torch.float64)
        y = A @ truth + torch.randn(5, generator=g, dtype=torch.float64)
        info, moment = A.T @ A, A.T @ y
        post = info + torch.diag(lam)
        thetas.append(torch.linalg.solve(post, moment + lam * mu))
        covs.append(torch.linalg.inv(post))
        infos.append(info)
        moments.append(moment)
    info, moment = torch.stack(infos), torch.stack(moments)
    joint_info = info.sum(0) + torch.diag(lam)
    joint_mean = torch.linalg.solve(joint_info, moment.sum(0) + lam * mu)
    own = torch.linalg.solve(info, moment)
    return torch.stack(thetas), torch.stack(covs), mu, lam, joint_mean, torch.linalg.inv(joint_info), own, info


@pytest.mark.parametrize("source", ["reported", "model"])
def test_prior_once_is_the_joint_posterior_of_linear_gaussian_windows(source):
    theta, cov, mu, lam, joint_mean, joint_cov, own, info = _posterior_windows(8, 0)
    n = theta.shape[0]
    combiner = PriorOnceCombiner(
        theta, cov, mu.expand(n, 3), lam.expand(n, 3), cov if source == "model" else None, focus=0
    )
    g = combiner.combine(range(n))
    assert torch.allclose(g.mean, joint_mean, rtol=0, atol=1e-11)
    assert torch.allclose(g.covariance, joint_cov, rtol=0, atol=1e-12)
    # consistency from the likelihoods alone: the windows' least-squares estimates about their flat combination
    flat = torch.linalg.solve(info.sum(0), (info @ own.unsqueeze(-1)).squeeze(-1).sum(0))
    chi2 = float(torch.einsum("wi,wij,wj->", own - flat, info, own - flat))
    assert g.chi2 == pytest.approx(chi2, rel=1e-9)
    assert g.dof == 3 * (n - 1)
    # one window is its own posterior again
    one = combiner.combine([3])
    assert torch.allclose(one.mean, theta[3], atol=1e-11) and torch.allclose(one.covariance, cov[3], atol=1e-12)
    # today's rule counts the prior n times: visibly not the joint posterior
    old = InformationCombiner(theta, cov).combine(range(n))
    assert float((old.mean - joint_mean).abs().max()) > 1e-3
    assert float(old.covariance[1, 1]) < 0.9 * float(joint_cov[1, 1])


def test_prior_once_leave_one_out_is_the_joint_posterior_without_that_window():
    """scale='marginal''s jackknife: each window left out, the prior kept (exact for a linear prior)."""
    theta, cov, mu, lam, *_ = _posterior_windows(6, 1)
    n = theta.shape[0]
    combiner = PriorOnceCombiner(theta, cov, mu.expand(n, 3), lam.expand(n, 3), focus=1)
    g = combiner.combine(range(n))
    loo = torch.stack([combiner.combine([v for v in range(n) if v != w]).mean[1] for w in range(n)])
    assert g.focus_scatter == pytest.approx(float((loo - loo.mean()).square().sum()) * (n - 1) / n, rel=1e-9)


def test_prior_once_in_logarithms_is_the_stationary_point_of_the_joint_log_posterior():
    """Windows Gaussian in x = log θ (precision L_w about x̃_w), a Gaussian prior in θ: each window's posterior is
    its MAP with the Gauss-Newton curvature L_w + diag(λ θ²) as covariance (as the refinement reports it, mapped to
    θ by the delta method). The combination in logarithms must zero the gradient of Σ_w ℓ_w(x) + log π(e^x)."""
    g = torch.Generator().manual_seed(2)
    d, n = 3, 7
    mu = torch.tensor([0.0, 2.0, 1000.0], dtype=torch.float64)
    lam = torch.tensor([0.0, 1.0 / 1.5**2, 1.0 / 400.0**2], dtype=torch.float64)
    centre = torch.log(torch.tensor([5e4, 3.0, 900.0], dtype=torch.float64))
    Ls, xs, thetas, covs = [], [], [], []
    for _ in range(n):
        B = torch.randn(d, d, generator=g, dtype=torch.float64)
        L = B @ B.T * 20.0 + torch.eye(d, dtype=torch.float64) * 2.0
        xt = centre + 0.1 * torch.randn(d, generator=g, dtype=torch.float64)
        x = xt.clone()
        for _ in range(100):  # the window's MAP: Newton with the prior's Gauss-Newton curvature
            t = x.exp()
            x = torch.linalg.solve(L + torch.diag(lam * t * t), L @ xt + lam * t * t * x - lam * (t - mu) * t)
        t = x.exp()
        cov_x = torch.linalg.inv(L + torch.diag(lam * t * t))
        Ls.append(L), xs.append(xt), thetas.append(t), covs.append(cov_x * t[:, None] * t[None, :])
    theta, cov = torch.stack(thetas), torch.stack(covs)
    log = torch.ones(d, dtype=torch.bool)
    combined = PriorOnceCombiner(theta, cov, mu.expand(n, d), lam.expand(n, d), log=log).combine(range(n))

    def gradient(value: torch.Tensor) -> torch.Tensor:
        x = value.log().clone().requires_grad_(True)
        total = sum(-0.5 * (x - xt) @ L @ (x - xt) for L, xt in zip(Ls, xs))
        total = total - 0.5 * (lam * (x.exp() - mu).square()).sum()
        return torch.autograd.grad(total, x)[0]

    scale = float(torch.stack(Ls).sum(0).diagonal().max())
    assert float(gradient(combined.mean).abs().max()) < 1e-9 * scale
    old = InformationCombiner(theta, cov, log=log).combine(range(n))
    assert float(gradient(old.mean).abs().max()) > 1e-3


def test_prior_once_without_any_prior_is_todays_combination():
    theta, cov, *_ = _posterior_windows(5, 3)
    zero = torch.zeros_like(theta)
    new = PriorOnceCombiner(theta, cov, zero, zero, scale="marginal", focus=1).combine(range(5))
    old = InformationCombiner(theta, cov, scale="marginal", focus=1).combine(range(5))
    assert torch.allclose(new.mean, old.mean, atol=1e-12) and torch.allclose(new.covariance, old.covariance, atol=1e-12)
    assert new.chi2 == pytest.approx(old.chi2, rel=1e-9) and new.focus_scatter == pytest.approx(old.focus_scatter)


def test_prior_once_tests_compare_the_likelihoods_not_the_posteriors_that_share_the_prior():
    """Two halves of a drive: wald() between their prior-once combinations is the Wald statistic of the halves'
    least-squares estimates (computed here from the windows' own data), not of their posteriors."""
    theta, cov, mu, lam, _, _, own, info = _posterior_windows(8, 4)
    combiner = PriorOnceCombiner(theta, cov, mu.expand(8, 3), lam.expand(8, 3))
    halves = [list(range(4)), list(range(4, 8))]
    fits = []
    for half in halves:
        total = info[half].sum(0)
        fits.append((torch.linalg.solve(total, (info[half] @ own[half].unsqueeze(-1)).squeeze(-1).sum(0)), total))
    diff = fits[0][0] - fits[1][0]
    expected = float(diff @ torch.linalg.solve(torch.linalg.inv(fits[0][1]) + torch.linalg.inv(fits[1][1]), diff))
    a, b = (combiner.combine(h) for h in halves)
    assert wald(a, b) == pytest.approx(expected, rel=1e-9)
    posterior = a.mean - b.mean
    assert float(posterior @ torch.linalg.solve(a.covariance + b.covariance, posterior)) != pytest.approx(
        expected, rel=1e-3
    )
