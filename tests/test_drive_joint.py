"""The joint fit of a drive's windows (estimation/drive_joint.py) against the stacked problem solved directly."""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import least_squares

from hybridqcm.estimation.drive_joint import joint_gauss_newton, joint_normal_equations
from hybridqcm.estimation.problems import LeastSquaresProblem, ProblemEvaluation
from hybridqcm.estimation.response import ResponseModel
from hybridqcm.estimation.solver import SolverStatus

T = 80


class WindowModel(ResponseModel):
    """y_t = a u_t + b u_{t-1} + x1 e^{-t/8} + x2 e^{-t/8} sin(t/3) (+ nonlinear: e^{-c t/T} u_t with c): θ =
    (a, b[, c], x1, x2); the two states are the window's own, (a, b, c) shared. ``inputs`` [W, T + 1]."""

    output_names = ("y",)

    def __init__(self, nonlinear: bool = False):
        self.nonlinear = nonlinear
        self.theta_names = ("a", "b", "c", "x1", "x2") if nonlinear else ("a", "b", "x1", "x2")
        self.n_params = 3 if nonlinear else 2

    def _columns(self, theta, inputs):
        t = torch.arange(T, dtype=torch.float64)
        u, u1 = inputs[:, 1 : T + 1], inputs[:, :T]
        decay = torch.exp(-t / 8).expand_as(u)
        cols = [u, u1]
        if self.nonlinear:
            cols.append(torch.exp(-theta[:, 2:3] * t / T) * u)
        return cols + [decay, decay * torch.sin(t / 3)]

    def outputs(self, theta, inputs, start=0, n_steps=None):
        cols = self._columns(theta, inputs)
        if not self.nonlinear:
            return sum(theta[:, j : j + 1] * c for j, c in enumerate(cols)).unsqueeze(2)
        y = theta[:, 0:1] * cols[0] + theta[:, 1:2] * cols[1] + cols[2] + theta[:, 3:4] * cols[3]
        return (y + theta[:, 4:5] * cols[4]).unsqueeze(2)

    def sensitivities(self, theta, inputs, start=0, n_steps=None):
        cols = self._columns(theta, inputs)
        if self.nonlinear:
            t = torch.arange(T, dtype=torch.float64)
            cols[2] = -t / T * cols[2]  # d/dc of e^{-c t/T} u
        return torch.stack([self.outputs(theta, inputs)[:, :, 0], *cols], 2).unsqueeze(2)


def _windows(model, truth_shared, n_windows, group, seed=0, noise=0.05):
    g = torch.Generator().manual_seed(seed)
    inputs = torch.randn(n_windows, T + 1, generator=g, dtype=torch.float64)
    states = torch.randn(n_windows, 2, generator=g, dtype=torch.float64)
    theta = torch.cat([truth_shared[group], states], 1)
    y = model.outputs(theta, inputs) + noise * torch.randn(n_windows, T, 1, generator=g, dtype=torch.float64)
    return inputs, theta, y


def _stacked(model, inputs, y, rows, n_shared):
    """The segment's stacked residual r(θ_s, x_1..x_W) as scipy sees it."""

    def residual(z):
        shared, states = z[:n_shared], z[n_shared:].reshape(len(rows), 2)
        theta = torch.cat([torch.as_tensor(shared).expand(len(rows), -1), torch.as_tensor(states)], 1)
        return (model.outputs(theta, inputs[rows]) - y[rows]).flatten().numpy()

    return residual


def test_joint_fit_of_a_linear_model_is_the_stacked_least_squares_fit_and_its_covariance():
    """Two segments of 5 and 7 windows, θ_s shared within each: one GN step is the stacked problem's
    least-squares solution (to 1e-10), and S⁻¹ is the shared block of the stacked (JᵀJ)⁻¹."""
    model = WindowModel()
    group = torch.tensor([0] * 5 + [1] * 7)
    truth = torch.tensor([[1.5, 0.7], [2.0, 0.4]], dtype=torch.float64)
    inputs, theta, y = _windows(model, truth, group.numel(), group)
    problem = LeastSquaresProblem(y, inputs, observed=(True,), model=model)
    evaluation = ProblemEvaluation(problem, chunk_size=4)
    start = theta * 1.3 + 0.1
    fit = joint_gauss_newton(evaluation, start, group, torch.tensor([True, True, False, False]))
    assert (fit.status == SolverStatus.CONVERGED).all()
    for g in range(2):
        rows = (group == g).nonzero().squeeze(1)
        t = torch.arange(T, dtype=torch.float64)
        design = torch.zeros(rows.numel() * T, 2 + 2 * rows.numel(), dtype=torch.float64)
        for k, w in enumerate(rows):
            block = slice(k * T, (k + 1) * T)
            design[block, 0], design[block, 1] = inputs[w, 1:], inputs[w, :T]
            design[block, 2 + 2 * k] = torch.exp(-t / 8)
            design[block, 3 + 2 * k] = torch.exp(-t / 8) * torch.sin(t / 3)
        solution = torch.linalg.lstsq(design, y[rows].flatten()).solution
        assert torch.allclose(fit.shared[g], solution[:2], rtol=0, atol=1e-10)
        assert torch.allclose(fit.params[rows][:, 2:].flatten(), solution[2:], rtol=0, atol=1e-10)
        full_cov = torch.linalg.inv(design.T @ design)[:2, :2]
        assert torch.allclose(fit.covariance[g], full_cov, rtol=1e-10, atol=0)


def test_schur_reduced_normal_equations_equal_the_full_ones():
    """The reduced system's solution and back-substitution equal the solve of the full block-arrow matrix
    assembled from the windows' blocks, with a prior on θ_s counted once (1e-10)."""
    g = torch.Generator().manual_seed(3)
    W, s, ell = 6, 3, 4
    J = torch.randn(W, 30, s + ell, generator=g, dtype=torch.float64)
    R = torch.randn(W, 30, generator=g, dtype=torch.float64)
    fisher, gradient = J.transpose(1, 2) @ J, (J.transpose(1, 2) @ R.unsqueeze(2)).squeeze(2)
    shared = torch.tensor([True] * s + [False] * ell)
    lam, dev = torch.tensor([[2.0, 0.0, 0.5]], dtype=torch.float64), torch.tensor([[0.3, 1.0, -0.2]])
    S, r, back = joint_normal_equations(fisher, gradient, shared, torch.zeros(W, dtype=torch.long), 1, lam, dev)
    d_s = torch.linalg.solve(S[0], r[0])
    step = back(d_s.expand(W, -1))
    n = s + W * ell
    full, rhs = torch.zeros(n, n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    full[:s, :s] = fisher[:, :s, :s].sum(0) + torch.diag(lam[0])
    rhs[:s] = gradient[:, :s].sum(0) + lam[0] * dev[0]
    for w in range(W):
        loc = slice(s + w * ell, s + (w + 1) * ell)
        full[:s, loc], full[loc, :s], full[loc, loc] = fisher[w, :s, s:], fisher[w, s:, :s], fisher[w, s:, s:]
        rhs[loc] = gradient[w, s:]
    direct = torch.linalg.solve(full, rhs)
    assert torch.allclose(d_s, direct[:s], rtol=0, atol=1e-10)
    assert torch.allclose(step[:, s:].flatten(), direct[s:], rtol=0, atol=1e-10)
    assert torch.allclose(step[:, :s], d_s.expand(W, -1), rtol=0, atol=0)
    assert torch.allclose(torch.linalg.inv(S[0]), torch.linalg.inv(full)[:s, :s], rtol=1e-10, atol=1e-12)


def test_joint_fit_of_a_nonlinear_model_matches_scipy_on_the_stacked_problem():
    """A parameter inside an exponential, shared by 6 windows with their own states: the joint GN's minimum
    is scipy's least_squares on the stacked residual (the same minimum to 1e-7 relative)."""
    model = WindowModel(nonlinear=True)
    group = torch.zeros(6, dtype=torch.long)
    truth = torch.tensor([[1.2, 0.5, 2.0]], dtype=torch.float64)
    inputs, theta, y = _windows(model, truth, 6, group, seed=5)
    problem = LeastSquaresProblem(y, inputs, observed=(True,), model=model)
    start = theta.clone()
    start[:, :3] = torch.tensor([1.0, 0.6, 1.4])
    fit = joint_gauss_newton(
        ProblemEvaluation(problem, chunk_size=3),
        start,
        group,
        torch.tensor([True, True, True, False, False]),
        decrement_tol=1e-20,
        max_iterations=50,
    )
    assert fit.status[0] in (SolverStatus.CONVERGED, SolverStatus.STALLED)
    z0 = np.concatenate([start[0, :3].numpy(), start[:, 3:].flatten().numpy()])
    reference = least_squares(_stacked(model, inputs, y, torch.arange(6), 3), z0, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    assert np.allclose(fit.shared[0].numpy(), reference.x[:3], rtol=1e-7, atol=0)
    assert abs(float(fit.loss[0]) - 0.5 * float(np.sum(reference.fun**2))) < 1e-10 * float(fit.loss[0]) + 1e-14
