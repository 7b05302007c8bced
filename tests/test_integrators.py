"""Parameters <-> matrices, stability, and the integrators against independent solutions.

The reference solutions here do not use the code under test: the single-DOF case has a
closed form, the coupled case is solved exactly with scipy's matrix exponential (the
input is piecewise constant, so the zero-order-hold solution is the exact continuous one),
and D, S are rebuilt from SPEC §1 by hand in numpy.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch

from hybridqcm.data.hdf5 import read_split
from hybridqcm.physics.integrators import METHODS, SemiExplicitEuler, simulate
from hybridqcm.physics.parameters import (
    REFERENCE_VEHICLE,
    PhysicalConstants,
    euler_step_matrix,
    is_stable,
    matrices_to_params,
    occupant_mass,
    params_to_matrices,
    reference_params,
    road_gain,
    system_matrix,
)

V = REFERENCE_VEHICLE


def spec_matrices(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """D, S of SPEC §1 written out independently of the package (numpy, one sample)."""
    p1, p2, p3, p4, p5, p6, p7, p8, p9, p10 = p
    D = np.array([[-p1, p1, 0], [p3, -(p3 + p4), p4], [0, p7, -p8]], dtype=float)
    S = np.array([[-p2, p2, 0], [p5, -(p5 + p6), p6], [0, p9, -p10]], dtype=float)
    return D, S


def spec_system(p: np.ndarray) -> np.ndarray:
    D, S = spec_matrices(p)
    return np.block([[D, S], [np.eye(3), np.zeros((3, 3))]])


# --------------------------------------------------------------------------- parameters


def test_reference_params_match_spec_constants():
    p = reference_params().numpy()
    expected = [
        615 / 80,
        98935 / 80,
        615 / 2160,
        4761 / 2160,
        98935 / 2160,
        149171 / 2160,
        4761 / 145,
        4761 / 145,
        149171 / 145,
        (149171 + 40000) / 145,
    ]
    np.testing.assert_allclose(p, expected, rtol=1e-15)
    assert road_gain(reference_params()).item() == pytest.approx(40000 / 145, rel=1e-14)  # K1/m1
    assert occupant_mass(reference_params()).item() == pytest.approx(80.0, rel=1e-14)


def test_params_matrices_round_trip_and_layout():
    g = torch.Generator().manual_seed(0)
    p = reference_params() * (1 + 0.3 * torch.rand(4, 7, 10, generator=g, dtype=torch.float64))
    D, S = params_to_matrices(p)
    assert D.shape == S.shape == (4, 7, 3, 3)
    D_np, S_np = spec_matrices(p[2, 3].numpy())
    np.testing.assert_array_equal(D[2, 3].numpy(), D_np)
    np.testing.assert_array_equal(S[2, 3].numpy(), S_np)
    assert torch.equal(matrices_to_params(D, S), p)
    np.testing.assert_array_equal(system_matrix(p)[1, 2].numpy(), spec_system(p[1, 2].numpy()))


def test_matrices_to_params_rejects_wrong_structure():
    D, S = params_to_matrices(reference_params())
    for which, (i, j) in [("D", (0, 2)), ("S", (2, 0)), ("D", (0, 0)), ("S", (1, 1))]:
        D2, S2 = D.clone(), S.clone()
        (D2 if which == "D" else S2)[i, j] += 1.0  # breaks a zero or a row sum
        with pytest.raises(ValueError, match="structure"):
            matrices_to_params(D2, S2)
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 3\]"):
        matrices_to_params(D[:2], S[:2])
    with pytest.raises(ValueError):
        matrices_to_params(D, S[None].expand(2, 3, 3))


def test_matrices_to_params_rejects_non_positive_parameters():
    for index in (0, 4, 9):
        p = reference_params().clone()
        p[index] = -abs(p[index])
        with pytest.raises(ValueError, match=f"p{index + 1}"):
            matrices_to_params(*params_to_matrices(p))
    p = reference_params().clone()
    p[6] = 0.0
    with pytest.raises(ValueError, match="p7"):
        matrices_to_params(*params_to_matrices(p))


def test_param_shape_validated():
    with pytest.raises(ValueError, match="10"):
        params_to_matrices(torch.ones(9))
    with pytest.raises(ValueError, match="10"):
        road_gain(torch.ones(3, 11))
    with pytest.raises(ValueError):
        PhysicalConstants(m1=0.0)
    with pytest.raises(ValueError):
        PhysicalConstants(C1=-1.0)
    PhysicalConstants(C1=0.0)  # C1 = 0 is the default and allowed


def test_road_gain_and_occupant_mass_from_physical_constants():
    c = PhysicalConstants(C1=100.0, K1=50000.0, m1=120.0, m3=95.0, K3=90000.0)
    p = c.to_params()
    assert road_gain(p).item() == pytest.approx(50000.0 / 120.0, rel=1e-13)
    assert occupant_mass(p, K3=90000.0).item() == pytest.approx(95.0, rel=1e-13)
    assert p[7].item() - p[6].item() == pytest.approx(100.0 / 120.0, rel=1e-12)  # C1 / m1
    batch = torch.stack([p, 2 * p])
    assert road_gain(batch).shape == (2,) and occupant_mass(batch).shape == (2,)


def test_euler_step_matrix_is_the_semi_explicit_euler_map():
    p = reference_params()[None].repeat(3, 1)
    p[1, 0] *= 2.5
    road = torch.zeros(3, 6, dtype=torch.float64)
    road[:, 0] = 1.0  # one kick, then free motion
    traj = simulate(p, road, 0.01, scaled_road=True)
    M = euler_step_matrix(p, 0.01)
    x1 = torch.cat([traj.vel[:, 1], traj.disp[:, 1]], -1)
    for k in range(1, 5):
        x_next = (M @ x1[..., None]).squeeze(-1)
        torch.testing.assert_close(
            x_next, torch.cat([traj.vel[:, k + 1], traj.disp[:, k + 1]], -1), rtol=1e-13, atol=1e-16
        )
        x1 = x_next


def test_is_stable_matches_independent_eigenvalues():
    g = torch.Generator().manual_seed(3)
    p = reference_params() * (1 + 0.25 * torch.randn(400, 10, generator=g, dtype=torch.float64))
    p[:, 6] = reference_params()[6] * (1 + 0.5 * torch.randn(400, generator=g, dtype=torch.float64))
    h = 0.01
    continuous = np.array([np.linalg.eigvals(spec_system(row)).real.max() < 0 for row in p.numpy()])
    discrete = []
    for row in p.numpy():
        D, S = spec_matrices(row)
        I = np.eye(3)
        step = np.block([[I + h * D, h * S], [h * (I + h * D), I + h * h * S]])
        discrete.append(np.abs(np.linalg.eigvals(step)).max() < 1)
    discrete = np.array(discrete)
    assert 0 < continuous.sum() < len(p), "the test needs both stable and unstable cases"
    np.testing.assert_array_equal(is_stable(p).numpy(), continuous)
    np.testing.assert_array_equal(is_stable(p, h).numpy(), continuous & discrete)
    assert bool(is_stable(reference_params(), h))


def test_stable_continuous_system_can_be_unstable_under_euler():
    # A very stiff seat (K3 / m3 huge) is a stable ODE, but h = 0.01 is then beyond Euler's limit.
    p = PhysicalConstants(K3=98935.0 * 100).to_params()
    assert bool(is_stable(p)) and not bool(is_stable(p, 0.01)) and bool(is_stable(p, 0.001))


# --------------------------------------------------------------------------- integrators


def single_dof_params(zeta: float, omega: float) -> torch.Tensor:
    """p with p4 = p6 = 0: chassis and occupant stay at rest, the wheel is a damped oscillator
    q1'' = -p8 q1' - p10 q1 + f (structurally a single mass-spring-damper)."""
    p = reference_params().clone()
    p[3] = p[5] = 0.0
    p[7], p[9] = 2 * zeta * omega, omega**2
    return p[None]


def single_dof_exact(t: np.ndarray, zeta: float, omega: float, force: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form step response from rest: (q(t), v(t))."""
    wd = omega * math.sqrt(1 - zeta**2)
    decay = np.exp(-zeta * omega * t)
    q = force / omega**2 * (1 - decay * (np.cos(wd * t) + zeta * omega / wd * np.sin(wd * t)))
    v = force / wd * decay * np.sin(wd * t)
    return q, v


def test_single_dof_step_response_against_closed_form():
    zeta, omega, force, h = 0.1, 20.0, 3.0, 5e-4
    n = int(round(1.0 / h)) + 1
    traj = simulate(
        single_dof_params(zeta, omega), torch.full((1, n), force, dtype=torch.float64), h, "rk4", scaled_road=True
    )
    t = h * np.arange(n)
    q, v = single_dof_exact(t, zeta, omega, force)
    # RK4 at h * omega = 0.01: global error ~ 1e-9 of the response (q ~ 1e-2, v ~ 0.2)
    np.testing.assert_allclose(traj.disp[0, :, 2].numpy(), q, rtol=0, atol=1e-10)
    np.testing.assert_allclose(traj.vel[0, :, 2].numpy(), v, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        traj.accel[0, :, 2].numpy(), force - 2 * zeta * omega * v - omega**2 * q, rtol=0, atol=1e-7
    )
    assert traj.accel[0, :, :2].abs().max() == 0 and traj.disp[0, :, :2].abs().max() == 0


@pytest.mark.parametrize(
    "method,order", [("semi_explicit_euler", 1), ("forward_euler", 1), ("implicit_midpoint", 2), ("rk4", 4)]
)
def test_single_dof_convergence_order(method, order):
    zeta, omega, force, T = 0.1, 20.0, 3.0, 1.0
    errors = []
    hs = [0.01, 0.005, 0.0025, 0.00125]
    for h in hs:
        n = int(round(T / h)) + 1
        traj = simulate(
            single_dof_params(zeta, omega), torch.full((1, n), force, dtype=torch.float64), h, method, scaled_road=True
        )
        q, v = single_dof_exact(np.array([T]), zeta, omega, force)
        errors.append(math.hypot(traj.disp[0, -1, 2].item() - q[0], (traj.vel[0, -1, 2].item() - v[0]) / omega))
    rates = [math.log2(a / b) for a, b in zip(errors, errors[1:])]
    assert errors[-1] < errors[0]
    assert abs(rates[-1] - order) < 0.2, (errors, rates)


def zoh_exact(p: np.ndarray, force_coarse: np.ndarray, H: float) -> np.ndarray:
    """Exact state (v, q) [len+1, 6] of the 6x6 system at t = jH for wheel forcing held constant on [jH, (j+1)H)."""
    A = spec_system(p)
    Phi = scipy.linalg.expm(A * H)
    Gamma = np.linalg.solve(A, (Phi - np.eye(6)))[:, 2]  # A^-1 (e^{AH} - I) e_{v1}
    x = np.zeros(6)
    out = [x]
    for f in force_coarse:
        x = Phi @ x + Gamma * f
        out.append(x)
    return np.array(out)


@pytest.mark.parametrize(
    "method,order", [("semi_explicit_euler", 1), ("forward_euler", 1), ("implicit_midpoint", 2), ("rk4", 4)]
)
def test_coupled_system_converges_to_exact_zoh_solution(method, order):
    """Reference vehicle with a piecewise-constant road (steps every H = 0.02 s): the exact solution
    at t = 1 s by matrix exponentials; each method's error falls as h^order."""
    H, T = 0.02, 1.0
    rng = np.random.default_rng(0)
    u_coarse = rng.normal(0, 0.01, int(round(T / H)))
    p = reference_params()
    exact = zoh_exact(p.numpy(), road_gain(p).item() * u_coarse, H)[-1]
    errors = []
    for m in (2, 4, 8, 16):
        h = H / m
        road = torch.tensor(np.append(np.repeat(u_coarse, m), 0.0))[None]
        traj = simulate(p[None], road, h, method)
        x = torch.cat([traj.vel[0, -1], traj.disp[0, -1]]).numpy()
        errors.append(np.linalg.norm(x - exact) / np.linalg.norm(exact))
    rates = [math.log2(a / b) for a, b in zip(errors, errors[1:])]
    assert abs(rates[-1] - order) < 0.2, (errors, rates)
    if method == "rk4":
        assert errors[-1] < 1e-7


def test_recorded_acceleration_is_the_equation_of_motion_at_each_step():
    g = torch.Generator().manual_seed(1)
    p = reference_params() * (1 + 0.05 * torch.randn(5, 10, generator=g, dtype=torch.float64))
    road = 0.01 * torch.randn(5, 200, generator=g, dtype=torch.float64)
    for method in METHODS:
        traj = simulate(p, road, 0.01, method)
        D, S = params_to_matrices(p)
        b = torch.zeros_like(traj.accel)
        b[..., 2] = road_gain(p)[:, None] * road
        expected = traj.vel @ D.transpose(-1, -2) + traj.disp @ S.transpose(-1, -2) + b
        torch.testing.assert_close(traj.accel, expected, rtol=1e-12, atol=1e-12)
        assert traj.vel[:, 0].abs().max() == 0 and traj.disp[:, 0].abs().max() == 0  # from rest
    # scaled_road=True takes p_u u directly
    traj = simulate(p, road, 0.01)
    scaled = simulate(p, road_gain(p)[:, None] * road, 0.01, scaled_road=True)
    torch.testing.assert_close(traj.accel, scaled.accel, rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(SemiExplicitEuler(0.01)(p, road), traj.accel, rtol=0, atol=0)


def test_semi_explicit_euler_recursion():
    g = torch.Generator().manual_seed(2)
    p = reference_params()[None].repeat(2, 1)
    traj = simulate(p, 0.01 * torch.randn(2, 50, generator=g, dtype=torch.float64), 0.02)
    torch.testing.assert_close(traj.vel[:, 1:], traj.vel[:, :-1] + 0.02 * traj.accel[:, :-1], rtol=1e-13, atol=1e-16)
    torch.testing.assert_close(traj.disp[:, 1:], traj.disp[:, :-1] + 0.02 * traj.vel[:, 1:], rtol=1e-13, atol=1e-16)


def test_simulate_is_differentiable_in_p():
    p = reference_params()[None].clone().requires_grad_(True)
    road = 0.01 * torch.sin(torch.linspace(0, 20, 100, dtype=torch.float64))[None]
    accel = simulate(p, road, 0.01).accel
    (grad,) = torch.autograd.grad(accel[..., 0].pow(2).sum(), p)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    # finite-difference check of one partial derivative (p2)
    eps = 1e-6 * p[0, 1].item()
    pp, pm = p.detach().clone(), p.detach().clone()
    pp[0, 1] += eps
    pm[0, 1] -= eps
    fd = (simulate(pp, road, 0.01).accel[..., 0].pow(2).sum() - simulate(pm, road, 0.01).accel[..., 0].pow(2).sum()) / (
        2 * eps
    )
    assert grad[0, 1].item() == pytest.approx(fd.item(), rel=1e-5)


def test_simulate_rejects_bad_input():
    p = reference_params()[None]
    with pytest.raises(ValueError, match="integrator"):
        simulate(p, torch.zeros(1, 5), 0.01, "euler")
    with pytest.raises(ValueError, match="h must be > 0"):
        simulate(p, torch.zeros(1, 5), 0.0)
    with pytest.raises(ValueError, match=r"\[batch, 10\]"):
        simulate(p[0], torch.zeros(1, 5), 0.01)
    with pytest.raises(ValueError, match="road"):
        simulate(p, torch.zeros(2, 5), 0.01)
    with pytest.raises(ValueError, match="at least one time step"):
        simulate(p, torch.zeros(1, 0), 0.01)


def conservative_params() -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """No damping (p1 = p3 = p4 = p7 = p8 = 0); returns p, masses and the stiffness matrix K."""
    c = V
    p = torch.tensor(
        [[0, c.K3 / c.m3, 0, 0, c.K3 / c.m2, c.K2 / c.m2, 0, 0, c.K2 / c.m1, (c.K2 + c.K1) / c.m1]], dtype=torch.float64
    )
    K = np.array([[c.K3, -c.K3, 0], [-c.K3, c.K3 + c.K2, -c.K2], [0, -c.K2, c.K2 + c.K1]])
    return p, np.array([c.m3, c.m2, c.m1]), K


def test_energy_semi_explicit_euler_bounded_forward_euler_grows():
    """Undamped, no road after a short kick: semi-explicit (symplectic) Euler conserves the modified
    energy E - h/2 v^T K q exactly and keeps E within a few tens of percent for 200 s; implicit
    midpoint conserves E itself; forward Euler's energy grows without bound."""
    p, m, K = conservative_params()
    h, n, kick = 0.01, 6000, 20
    road = torch.zeros(1, n, dtype=torch.float64)
    road[0, :kick] = 1.0

    def energies(method):
        traj = simulate(p, road, h, method, scaled_road=True)
        v, q = traj.vel[0, kick + 1 :].numpy(), traj.disp[0, kick + 1 :].numpy()
        with np.errstate(all="ignore"):
            E = 0.5 * (m * v**2).sum(-1) + 0.5 * np.einsum("ki,ij,kj->k", q, K, q)
            modified = E - 0.5 * h * np.einsum("ki,ij,kj->k", v, K, q)
        return E, modified

    E, modified = energies("semi_explicit_euler")
    assert np.ptp(modified) / modified[0] < 1e-10
    assert E.max() / E.min() < 1.25
    E_mid, _ = energies("implicit_midpoint")
    assert np.ptp(E_mid) / E_mid[0] < 1e-10
    E_fe, _ = energies("forward_euler")
    assert not np.isfinite(E_fe[-1]) or E_fe[-1] / E_fe[0] > 1e6
    assert E_fe[1000] / E_fe[0] > 10


# --------------------------------------------------------------------------- the stored data


def test_stored_accelerations_satisfy_equation_of_motion(tiny_dataset):
    for split in ("train", "test"):
        data = read_split(tiny_dataset, split, ("accel", "vel", "disp", "road", "params"))
        assert data["h"] == 0.01
        p = data["params"]
        v, q, u = (data[k].astype(np.float64) for k in ("vel", "disp", "road"))
        for i in range(p.shape[0]):
            D, S = spec_matrices(p[i])
            b = np.zeros_like(v[i])
            b[:, 2] = (p[i, 9] - p[i, 8]) * u[i]
            expected = v[i] @ D.T + q[i] @ S.T + b
            # float32 storage: ~6e-8 relative on v, q, u, amplified by |p| * |state|
            scale = (np.abs(v[i]) @ np.abs(D).T + np.abs(q[i]) @ np.abs(S).T + np.abs(b)).max()
            np.testing.assert_allclose(data["accel"][i], expected, rtol=0, atol=1e-6 * scale)
        # the Euler recursion holds between stored steps too
        a = data["accel"].astype(np.float64)
        np.testing.assert_allclose(v[:, 1:], v[:, :-1] + 0.01 * a[:, :-1], rtol=1e-5, atol=1e-6 * np.abs(v).max())
        np.testing.assert_allclose(q[:, 1:], q[:, :-1] + 0.01 * v[:, 1:], rtol=1e-5, atol=1e-6 * np.abs(q).max())


def test_every_stored_system_is_stable(tiny_dataset):
    h = 0.01
    for split in ("train", "test"):
        p = read_split(tiny_dataset, split, ("params",))["params"]
        assert (p > 0).all()
        for row in p:
            assert np.linalg.eigvals(spec_system(row)).real.max() < 0
            D, S = spec_matrices(row)
            I = np.eye(3)
            step = np.block([[I + h * D, h * S], [h * (I + h * D), I + h * h * S]])
            assert np.abs(np.linalg.eigvals(step)).max() < 1
