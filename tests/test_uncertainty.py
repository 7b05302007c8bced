"""Robust covariances of the solver (SolverConfig.covariance) against Monte-Carlo on linear models.

For y = X θ + ε the least-squares estimate is exactly θ̂ = θ + (XᵀX)⁻¹ Xᵀ ε, so its covariance over
many noise draws is the independent fact: (XᵀX)⁻¹ Xᵀ Cov(ε) X (XᵀX)⁻¹. The model-based σ̂² (XᵀX)⁻¹ is
that only for white ε; the sandwich estimates it from the residuals whatever Cov(ε) is, as long as the
groups it sums over are uncorrelated (time steps for heteroscedastic ε, DFT frequencies for
stationary coloured ε).
"""

import math

import pytest
import torch

from hybridqcm.estimation.noise import SpectralNoise
from hybridqcm.estimation.problems import LeastSquaresProblem
from hybridqcm.estimation.response import ResponseModel
from hybridqcm.estimation.solver import GaussNewton, SolverConfig

T, N_MC = 256, 3000


class Linear(ResponseModel):
    """y = X θ with a fixed design X [T, 1, n] (no physical parameters: θ are free of sign)."""

    output_names = ("y",)
    n_params = 0

    def __init__(self, design):
        self.design = design
        self.theta_names = tuple(f"t{j}" for j in range(design.shape[-1]))

    def outputs(self, theta, inputs, start=0, n_steps=None):
        return torch.einsum("ton,bn->bto", self.design, theta)

    def sensitivities(self, theta, inputs, start=0, n_steps=None):
        jac = self.design.expand(theta.shape[0], *self.design.shape)
        return torch.cat([self.outputs(theta, inputs).unsqueeze(-1), jac], -1)


def _design():
    """Broadband regressors (information spread over many frequencies, so no group has high leverage):
    a low-passed (moving average over 16 steps) and a white fixed random sequence."""
    g = torch.Generator().manual_seed(0)
    raw = torch.randn(2, T + 15, generator=g, dtype=torch.float64)
    slow = raw[0].unfold(0, 16, 1).mean(1)[:T]
    fast = raw[1, :T]
    return torch.stack([slow / slow.std(), fast], -1)[:, None]


def _fit(noise_t, covariance, band=1, spectral=None, dof=False):
    """Estimates and std of N_MC fits of y = X·(1, -2) + noise_t [N_MC, T]."""
    design = _design()
    truth = torch.tensor([1.0, -2.0], dtype=torch.float64)
    y = torch.einsum("ton,n->to", design, truth)[None] + noise_t[..., None]
    problem = LeastSquaresProblem(
        y,
        torch.zeros(N_MC, T, dtype=torch.float64),
        observed=(True,),
        model=Linear(design),
        noise=spectral,
    )
    config = SolverConfig(
        max_iterations=3, misfit_lags=0, covariance=covariance, covariance_band=band, covariance_dof=dof
    )
    result = GaussNewton(config).solve(problem, torch.zeros(N_MC, 2, dtype=torch.float64))
    return result.params - truth, result.std


def _mc_var(errors):
    return errors.var(0)


def test_white_noise_sandwich_and_jackknife_equal_the_model_based_covariance():
    g = torch.Generator().manual_seed(1)
    noise = 0.3 * torch.randn(N_MC, T, generator=g, dtype=torch.float64)
    err, model = _fit(noise, "model")
    _, sandwich = _fit(noise, "sandwich")
    _, jackknife = _fit(noise, "jackknife")
    mc = _mc_var(err)
    # sampling error of a variance from 3000 draws: ~ sqrt(2/3000) = 2.6 %
    for std in (model, sandwich, jackknife):
        assert torch.allclose(std.square().mean(0), mc, rtol=0.08)
    # with low leverage (T = 256, 2 unknowns) the jackknife is the sandwich to O(1/T)
    assert torch.allclose(jackknife.square().mean(0), sandwich.square().mean(0), rtol=0.03)


def test_heteroscedastic_noise_sandwich_matches_monte_carlo_where_model_based_does_not():
    """Noise std growing with the slow regressor's magnitude: model-based is wrong by a known factor."""
    g = torch.Generator().manual_seed(2)
    scale = 0.05 + 1.0 * _design()[:, 0, 0].abs() ** 2  # [T], large where regressor 1 is large
    noise = scale * torch.randn(N_MC, T, generator=g, dtype=torch.float64)
    err, model = _fit(noise, "model")
    _, sandwich = _fit(noise, "sandwich")
    mc = _mc_var(err)
    assert torch.allclose(sandwich.square().mean(0), mc, rtol=0.08)
    assert model.square().mean(0)[0] < 0.8 * mc[0]  # the white-noise formula underestimates


def test_coloured_noise_frequency_sandwich_matches_monte_carlo():
    """AR(1) noise (ρ = 0.9) under a white spectral noise model: the model-based covariance assumes one
    variance at every frequency and is far too narrow for the slow regressor (the noise is strong at
    low frequencies); the per-frequency sandwich sees each frequency's own power."""
    g = torch.Generator().manual_seed(3)
    white = torch.randn(N_MC, T + 200, generator=g, dtype=torch.float64)
    ar = torch.zeros_like(white)
    for k in range(1, white.shape[1]):
        ar[:, k] = 0.9 * ar[:, k - 1] + white[:, k]
    noise = 0.1 * ar[:, 200:]  # stationary part
    spectral = SpectralNoise(torch.full((N_MC, 1), float(noise.var()), dtype=torch.float64))
    err, model = _fit(noise, "model", spectral=spectral)
    _, sandwich = _fit(noise, "sandwich", spectral=spectral)
    _, jackknife = _fit(noise, "jackknife", spectral=spectral)
    mc = _mc_var(err)
    assert model.square().mean(0)[0] < 0.2 * mc[0]  # measured: 10x too small
    # The slow regressor's information sits in the ~16 lowest bins, where the AR(1) power is too:
    # leverage. The sandwich (from residuals shrunk by the fit) is then biased low and the jackknife
    # high (Efron & Stein 1981), so they bracket the truth; both within 30 % of it (measured -20/+20 %).
    var_s, var_j = sandwich.square().mean(0), jackknife.square().mean(0)
    assert (var_s[0] < mc[0] < var_j[0]) and torch.allclose(var_s, mc, rtol=0.3) and torch.allclose(var_j, mc, rtol=0.3)
    # the robust choice takes the larger per parameter: never narrower than either
    _, robust = _fit(noise, "robust_sandwich", spectral=spectral)
    assert (robust >= model * (1 - 1e-12)).all() and (robust >= sandwich * (1 - 1e-12)).all()


def test_student_t_widening_follows_the_effective_degrees_of_freedom():
    """With groups so wide that only G = 8 remain (256 time steps / 32), the jackknife std at the t
    quantile is the plain one times t_ν(0.975)/z(0.975) with Satterthwaite's ν ≤ G (Cauchy-Schwarz);
    with 256 groups it is a few per cent on average."""
    from scipy.stats import t as student_t

    g = torch.Generator().manual_seed(4)
    noise = 0.3 * torch.randn(200, T, generator=g, dtype=torch.float64)
    ratio_many = _fit_small(noise, band=1, dof=True) / _fit_small(noise, band=1, dof=False)
    assert (ratio_many >= 1.0).all() and ratio_many.mean() < 1.06  # measured mean 1.04
    ratio_few = _fit_small(noise, band=32, dof=True) / _fit_small(noise, band=32, dof=False)
    lower = student_t.ppf(0.975, 8) / student_t.ppf(0.975, math.inf)
    assert (ratio_few >= lower * (1 - 1e-9)).all()


def _concentrated_design(g):
    """[64, 2]: a fast decay and a narrow bump, the information in a few time steps (a large Efron-Stein excess)."""
    t = torch.arange(64, dtype=torch.float64)
    bump = torch.exp(-(((t - 20) / 3) ** 2)) + 0.05 * torch.randn(64, generator=g, dtype=torch.float64)
    return torch.stack([torch.exp(-t / 4), bump], 1)


def _jackknife_draws(X, data, band):
    """score_groups' (meat, groups, moments) and σ̂² of the least-squares fits of ``data`` [draws, T] on X."""
    from hybridqcm.estimation.uncertainty import score_groups

    fisher = X.T @ X
    residual = data - torch.linalg.solve(fisher, X.T @ data.T).T @ X.T
    stack = torch.cat([residual[..., None, None], X.expand(data.shape[0], *X.shape)[:, :, None, :]], -1)  # (e | J)
    meat, groups, moments = score_groups(stack, band, spectral=False, jackknife=True)
    sigma2 = residual.square().sum(1) / (X.shape[0] - X.shape[1])
    return fisher.expand(data.shape[0], 2, 2), meat, groups, moments, sigma2


def test_jackknife_moments_match_monte_carlo():
    """White noise on the concentrated design: over 4 000 draws each parameter's jackknife variance V_k has
    the mean excess_k σ² (XᵀX)⁻¹_kk (+39 % / +18 % here: Efron-Stein) and the spread 2 E[V]² / Var V = ν that
    score_groups reports (Bell-McCaffrey, from X alone: the same in every draw)."""
    g = torch.Generator().manual_seed(5)
    X = _concentrated_design(g)
    eps = torch.randn(4000, 64, generator=g, dtype=torch.float64)
    for band in (1, 4):
        fisher, meat, groups, moments, _ = _jackknife_draws(X, eps, band)
        _, nu, excess = moments.unbind(-1)
        V = meat.diagonal(dim1=1, dim2=2)
        assert groups == 64 // band and torch.allclose(nu, nu[:1].expand_as(nu))
        assert torch.allclose(V.mean(0), excess[0] * torch.linalg.inv(fisher[0]).diagonal(), rtol=0.06)
        assert (excess[0] > 1.1).all()  # the excess the test divides out is real here
        assert torch.allclose(nu[0], 2 * V.mean(0).square() / V.var(0), rtol=0.1)  # measured 2.73 / 4.25, 1.06 / 1.17


def test_jackknife_excess_is_divided_out_only_where_the_working_model_holds():
    """With white noise the test passes for about 1 − α of the draws and the corrected variance's mean is
    σ² (XᵀX)⁻¹ (the uncorrected +18-39 % gone); with a misfit the model does not hold (a coherent error on the
    bump's flank, the same in every draw) the jackknife stays as it was in (nearly) every draw."""
    from types import SimpleNamespace

    from hybridqcm.estimation.uncertainty import _unbiased_where_consistent

    cfg = SimpleNamespace(jackknife_test=0.05, rcond=1e-12)
    g = torch.Generator().manual_seed(7)
    X = _concentrated_design(g)
    t = torch.arange(64, dtype=torch.float64)
    eps = torch.randn(4000, 64, generator=g, dtype=torch.float64)
    fisher, meat, _, moments, sigma2 = _jackknife_draws(X, eps, 1)
    corrected, dof = _unbiased_where_consistent(cfg, fisher, meat, moments, sigma2)
    kept = corrected.diagonal(dim1=1, dim2=2) == meat.diagonal(dim1=1, dim2=2)
    assert 0.02 < kept.double().mean() < 0.10  # about α of the draws fail the test
    assert torch.equal(dof[kept], moments[..., 0][kept]) and torch.equal(dof[~kept], moments[..., 1][~kept])
    expected = torch.linalg.inv(fisher[0]).diagonal()
    assert torch.allclose(corrected.diagonal(dim1=1, dim2=2)[~kept].view(-1, 1).mean(), expected.mean(), rtol=0.5)
    for k in range(2):  # per parameter, the draws that passed: their variance has the working model's mean
        passed = ~kept[:, k]
        ratio = corrected[passed, k, k].mean() / expected[k]
        assert 0.8 < float(ratio) < 1.02  # measured below 1: the test removes the draws of the upper tail
    # heteroscedastic noise, 4x where the bump is: the working model's σ̂² (XᵀX)⁻¹ under-states the bump's
    # coefficient 6x; its jackknife sees it, fails the test in most draws and keeps its surplus
    data = eps * (1 + 3 * torch.exp(-(((t - 20) / 4) ** 2)))
    fisher, meat, _, moments, sigma2 = _jackknife_draws(X, data, 1)
    corrected, _ = _unbiased_where_consistent(cfg, fisher, meat, moments, sigma2)
    kept = corrected.diagonal(dim1=1, dim2=2) == meat.diagonal(dim1=1, dim2=2)
    assert kept[:, 1].double().mean() > 0.8  # measured 0.86; the decay's coefficient, not under-stated: 0.003
    monte_carlo = torch.linalg.solve(fisher[0], X.T @ data.T).T.var(0)
    mean = corrected.diagonal(dim1=1, dim2=2).mean(0)
    assert (mean >= 0.98 * monte_carlo).all() and (mean <= 1.3 * monte_carlo).all()  # measured 1.01, 1.23


def _fit_small(noise_t, band, dof):
    design = _design()
    b = noise_t.shape[0]
    y = torch.einsum("ton,n->to", design, torch.tensor([1.0, -2.0], dtype=torch.float64))[None] + noise_t[..., None]
    problem = LeastSquaresProblem(y, torch.zeros(b, T, dtype=torch.float64), observed=(True,), model=Linear(design))
    config = SolverConfig(
        max_iterations=3, misfit_lags=0, covariance="jackknife", covariance_band=band, covariance_dof=dof
    )
    return GaussNewton(config).solve(problem, torch.zeros(b, 2, dtype=torch.float64)).std


def test_bad_covariance_settings_are_one_line_errors():
    with pytest.raises(ValueError, match="covariance='hc3'"):
        GaussNewton(SolverConfig(covariance="hc3"))
    with pytest.raises(ValueError, match="jackknife_test=0"):
        GaussNewton(SolverConfig(covariance="jackknife", jackknife_test=0))
    with pytest.raises(ValueError, match="covariance_band=0"):
        GaussNewton(SolverConfig(covariance="sandwich", covariance_band=0))


def test_app_interval_settings_map_to_the_solver_and_reject_bad_values():
    from omegaconf import OmegaConf

    from hybridqcm.errors import ConfigError
    from hybridqcm.estimation.plan_settings import interval_settings

    cfg = OmegaConf.create({"intervals": {"covariance": "jackknife", "band": 4, "student_t": False}})
    assert interval_settings(cfg) == {
        "covariance": "jackknife", "covariance_band": 4, "covariance_dof": False, "jackknife_test": 0.05,
    }  # fmt: skip
    assert interval_settings(OmegaConf.create({})) == {}
    for key, value, message in (
        ("covariance", "hc3", "intervals.covariance='hc3'"),
        ("band", 0, "intervals.band=0"),
        ("student_t", "yes", "intervals.student_t='yes'"),
        ("jackknife_test", 1.5, "intervals.jackknife_test=1.5"),
        ("jackknife_test", "often", "intervals.jackknife_test='often'"),
    ):
        bad = OmegaConf.create({"intervals": {"covariance": "model", key: value}})
        with pytest.raises(ConfigError, match=message.replace("(", r"\(")) as error:
            interval_settings(bad)
        assert "\n" not in str(error.value)


@pytest.mark.parametrize(
    "overrides, expected",
    [
        (["experiment=exp5_random_init", "dynamics=exact"], "model"),  # road known, residual whitened
        (["experiment=exp5_random_init", "dynamics=exact", "residual_weighting=false"], "robust_jackknife"),
        (["experiment=exp5_random_init", "dynamics=euler"], "robust_jackknife"),  # the source protocol
        (["experiment=occupant_roadfree"], "robust_jackknife"),  # a measured input: errors in variables
        (["experiment=sprung_roadfree"], "robust_jackknife"),
        (["experiment=exp5_random_init", "dynamics=exact", "intervals.covariance=jackknife"], "jackknife"),
    ],
)
def test_auto_covariance_is_the_model_one_only_where_the_whitened_residual_is_white(tiny_dataset, overrides, expected):
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.estimation.plan import validate

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("estimate", overrides=[*overrides, f"data.path={tiny_dataset}", "n_samples=2"])
    stages = validate(cfg)["stages"]
    assert stages[-1]["settings"]["covariance"] == expected
    assert all("covariance" not in s["settings"] for s in stages[:-1])


def test_robust_covariance_with_a_prior_is_the_gaussian_product():
    """MAP: the robust data covariance C combines with the prior precision Λ as (C⁻¹ + Λ)⁻¹ — a strong
    prior pins its parameter's std at 1/√λ and leaves the other one no wider than without it."""
    design = _design()
    g = torch.Generator().manual_seed(5)
    b = 50
    y = torch.einsum("ton,n->to", design, torch.tensor([1.0, -2.0], dtype=torch.float64))[None]
    y = y + 0.3 * torch.randn(b, T, 1, generator=g, dtype=torch.float64)
    config = SolverConfig(max_iterations=3, misfit_lags=0, covariance="robust_jackknife")
    stds = []
    for precision in (0.0, 1e8):
        problem = LeastSquaresProblem(
            y,
            torch.zeros(b, T, dtype=torch.float64),
            observed=(True,),
            model=Linear(design),
            prior_mean=torch.tensor([[1.0, -2.0]], dtype=torch.float64).expand(b, 2),  # a correct prior
            prior_precision=torch.tensor([[precision, 0.0]], dtype=torch.float64).expand(b, 2),
        )
        stds.append(GaussNewton(config).solve(problem, torch.zeros(b, 2, dtype=torch.float64)).std)
    free, pinned = stds
    assert torch.allclose(pinned[:, 0], torch.full((b,), 1e-4, dtype=torch.float64), rtol=1e-3)
    # θ2 given θ1 has variance 1/F22 ≤ (F⁻¹)22 (equal here: nearly orthogonal regressors); per sample the
    # jackknife is re-estimated at a different fit, so compare on average
    assert pinned[:, 1].square().mean() <= 1.05 * free[:, 1].square().mean()


def test_fewer_groups_than_unknowns_fall_back_to_the_model_based_covariance():
    g = torch.Generator().manual_seed(6)
    noise = 0.3 * torch.randn(20, T, generator=g, dtype=torch.float64)
    wide = _fit_small(noise, band=T, dof=True)  # one group, two unknowns
    design = _design()
    y = torch.einsum("ton,n->to", design, torch.tensor([1.0, -2.0], dtype=torch.float64))[None] + noise[..., None]
    problem = LeastSquaresProblem(y, torch.zeros(20, T, dtype=torch.float64), observed=(True,), model=Linear(design))
    model = GaussNewton(SolverConfig(max_iterations=3, misfit_lags=0)).solve(problem, torch.zeros(20, 2)).std
    assert torch.equal(wide, model) and torch.isfinite(wide).all()
