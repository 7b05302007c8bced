"""The exact continuous-time simulator against independent references: a tight scipy ODE
integration of the continuous road, the closed-form steady state of one sinusoid, and rest."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from hybridqcm.physics.continuous import simulate_continuous
from hybridqcm.physics.parameters import reference_params, road_gain, system_matrix
from hybridqcm.physics.prior import build_prior
from hybridqcm.physics.road import RoadProfile

SPEED = 30 / 3.6


def _roads(n, n_waves=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    road = RoadProfile(n_waves=n_waves)
    amplitude, phase = road.draw(torch.randint(0, 3, (n,), generator=g), g)
    return road, amplitude, phase


def _rel(a, b):
    """max abs difference per channel over the channel's peak, worst channel."""
    return float((np.abs(a - b).max(axis=(0, 1)) / np.abs(b).max(axis=(0, 1))).max())


def test_matches_a_tight_ode_integration_of_the_continuous_road():
    params = build_prior("thesis", h=None).sample(3, torch.Generator().manual_seed(1)).params
    road, amplitude, phase = _roads(3)
    omega_t = road.omega * SPEED
    h, n_steps = 0.01, 150
    warmup = torch.tensor([0.0, 1.3, 2.05])
    out = simulate_continuous(params, amplitude, phase, omega_t, n_steps, h, warmup)
    for i in range(3):
        A = system_matrix(params[i]).numpy()
        pu = float(road_gain(params[i]))
        a, ph, w = amplitude[i].numpy(), phase[i].numpy(), omega_t.numpy()

        def u(t, a=a, w=w, ph=ph):
            return float((a * np.sin(w * t - ph)).sum())

        def rhs(t, x, A=A, pu=pu, u=u):
            dx = A @ x
            dx[2] += pu * u(t)
            return dx

        t_eval = float(warmup[i]) + h * np.arange(n_steps)
        sol = solve_ivp(rhs, (0.0, t_eval[-1]), np.zeros(6), method="DOP853", t_eval=t_eval, rtol=1e-12, atol=1e-15)
        x = sol.y.T  # [T, 6]
        road_ref = np.array([u(t) for t in t_eval])
        accel = x[:, :3] @ A[:3, :3].T + x[:, 3:] @ A[:3, 3:].T
        accel[:, 2] += pu * road_ref
        assert _rel(out.accel[i : i + 1].numpy(), accel[None]) <= 1e-6
        assert _rel(out.vel[i : i + 1].numpy(), x[None, :, :3]) <= 1e-6
        assert _rel(out.disp[i : i + 1].numpy(), x[None, :, 3:]) <= 1e-6
        np.testing.assert_allclose(out.road[i].numpy(), road_ref, rtol=0, atol=1e-12)


def test_single_sinusoid_reaches_the_closed_form_steady_state():
    p = reference_params()[None]
    A = system_matrix(p[0]).numpy()
    pu = float(road_gain(p[0]))
    w, amp, phi = 11.0, 0.01, 0.4  # one wave: u = amp sin(w t - phi)
    h, n_steps, warmup = 0.01, 200, 900.0  # slowest mode (chassis) decays like e^{-0.042 t}: gone by 900 s
    out = simulate_continuous(p, torch.tensor([[amp]]), torch.tensor([[phi]]), torch.tensor([w]), n_steps, h, warmup)
    B = np.zeros(6, complex)
    B[2] = pu
    G = np.linalg.solve(1j * w * np.eye(6) - A, B)  # the analytic 6x6 complex solve
    t = warmup + h * np.arange(n_steps)
    x = np.imag(G[None, :] * amp * np.exp(1j * (w * t[:, None] - phi)))
    accel = np.imag((1j * w) * G[None, :3] * amp * np.exp(1j * (w * t[:, None] - phi)))  # a = dv/dt
    assert _rel(out.vel.numpy(), x[None, :, :3]) <= 1e-6
    assert _rel(out.disp.numpy(), x[None, :, 3:]) <= 1e-6
    assert _rel(out.accel.numpy(), accel[None]) <= 1e-6


def test_transient_is_the_matrix_exponential_of_the_steady_state_offset():
    p = reference_params()[None]
    A = system_matrix(p[0]).numpy()
    pu = float(road_gain(p[0]))
    w, amp, phi = 7.0, 0.02, 1.1
    out = simulate_continuous(p, torch.tensor([[amp]]), torch.tensor([[phi]]), torch.tensor([w]), 50, 0.01, 0.5)
    B = np.zeros(6, complex)
    B[2] = pu
    G = np.linalg.solve(1j * w * np.eye(6) - A, B)
    t = 0.5 + 0.01 * np.arange(50)
    xp = np.imag(G[None, :] * amp * np.exp(1j * (w * t[:, None] - phi)))
    xp0 = np.imag(G * amp * np.exp(-1j * phi))
    x = xp - np.stack([expm(A * tk) @ xp0 for tk in t])
    assert _rel(out.vel.numpy(), x[None, :, :3]) <= 1e-7


def test_warmup_zero_starts_from_rest_and_state0_is_the_first_sample():
    params = build_prior("thesis", h=None).sample(4, torch.Generator().manual_seed(2)).params
    road, amplitude, phase = _roads(4, n_waves=200)
    out = simulate_continuous(
        params, amplitude, phase, road.omega * SPEED, 20, 0.01, torch.tensor([0.0, 0.0, 3.0, 7.5])
    )
    scale = out.vel.abs().max()
    assert float(out.state0[:2].abs().max()) <= 1e-12 * float(scale) + 1e-15
    assert float(out.state0[2:].abs().min()) > 0  # mid-drive: moving
    torch.testing.assert_close(out.state0, torch.cat([out.vel[:, 0], out.disp[:, 0]], -1), rtol=0, atol=0)
    # the road seen is the same road, shifted in time by the warm-up
    later = simulate_continuous(
        params[2:3], amplitude[2:3], phase[2:3], road.omega * SPEED, 1, 0.01, torch.tensor([3.05], dtype=torch.float64)
    )
    torch.testing.assert_close(later.road[0, 0], out.road[2, 5], rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(later.accel[0, 0], out.accel[2, 5], rtol=1e-9, atol=1e-14)


def test_the_fallback_solve_agrees_with_the_eigendecomposition():
    params = build_prior("thesis", h=None).sample(3, torch.Generator().manual_seed(3)).params
    road, amplitude, phase = _roads(3)
    args = (params, amplitude, phase, road.omega * SPEED, 64, 0.01, torch.tensor([0.0, 0.5, 2.0]))
    fast = simulate_continuous(*args)
    slow = simulate_continuous(*args, eig_tol=-1.0)  # every sample takes the fallback
    assert fast.n_fallback == 0 and slow.n_fallback == 3
    assert _rel(slow.accel.numpy(), fast.accel.numpy()) <= 1e-9
    for tol in (1e-17, 3e-17, 1e-16, 3e-16, 1e-15, 3e-15, 1e-14):  # some sample on each path
        mixed = simulate_continuous(*args, eig_tol=tol)
        if 0 < mixed.n_fallback < 3:
            break
    assert 0 < mixed.n_fallback < 3
    assert _rel(mixed.accel.numpy(), fast.accel.numpy()) <= 1e-9
    assert _rel(mixed.vel.numpy(), fast.vel.numpy()) <= 1e-9


def test_bad_input_is_one_line():
    p = reference_params()[None]
    one = torch.tensor([[0.01]])
    with pytest.raises(ValueError, match="h > 0"):
        simulate_continuous(p, one, one, torch.tensor([1.0]), 10, 0.0)
    with pytest.raises(ValueError, match="warmup"):
        simulate_continuous(p, one, one, torch.tensor([1.0]), 10, 0.01, -1.0)
    assert math.isfinite(float(simulate_continuous(p, one, one, torch.tensor([1.0]), 10, 0.01).accel.abs().max()))


def test_euler_mid_drive_is_the_recursion_from_rest_cut_after_the_warmup():
    from hybridqcm.data.simulate import simulate_samples
    from hybridqcm.physics.integrators import simulate

    prior, road = build_prior("thesis", h=0.01), RoadProfile(n_waves=60)
    out = simulate_samples(
        prior,
        road,
        torch.tensor([0, 1]),
        40,
        0.01,
        SPEED,
        torch.Generator().manual_seed(5),
        3,
        physics="euler",
        warmup_s=(0.5, 2.0),
    )
    g = torch.Generator().manual_seed(5)
    amplitude, phase = road.draw(torch.tensor([0, 1]), g)  # same draws, same order
    for i in range(6):
        steps = int(round(float(out["warmup"][i]) / 0.01))
        assert 50 <= steps <= 200
        s = SPEED * 0.01 * torch.arange(steps + 40, dtype=torch.float64)
        u = road.evaluate(amplitude[i // 3 : i // 3 + 1], phase[i // 3 : i // 3 + 1], s)
        ref = simulate(out["params"][i : i + 1], u, 0.01)
        torch.testing.assert_close(out["accel"][i], ref.accel[0, steps:], rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(out["road"][i], u[0, steps:], rtol=1e-9, atol=1e-14)
        torch.testing.assert_close(
            out["state0"][i], torch.cat([ref.vel[0, steps], ref.disp[0, steps]]), rtol=1e-9, atol=1e-14
        )


def test_euler_at_100_hz_is_another_vehicle():
    """The Euler recursion at 100 Hz is another vehicle (SPEC §9): several % apart in a3, a1."""
    from hybridqcm.data.simulate import simulate_samples

    prior, road = build_prior("thesis", h=0.01), RoadProfile()
    kw = dict(n_steps=400, h=0.01, speed_mps=SPEED, samples_per_profile=20, warmup_s=(0.0, 0.0))
    euler = simulate_samples(
        prior, road, torch.tensor([0, 1]), generator=torch.Generator().manual_seed(6), physics="euler", **kw
    )
    exact = simulate_samples(
        prior, road, torch.tensor([0, 1]), generator=torch.Generator().manual_seed(6), physics="continuous", **kw
    )
    torch.testing.assert_close(euler["params"], exact["params"])
    rel = ((euler["accel"] - exact["accel"]).pow(2).mean((0, 1)) / exact["accel"].pow(2).mean((0, 1))).sqrt()
    assert 0.01 < float(rel[0]) < 0.5 and 0.05 < float(rel[2]) < 0.6, rel


def test_euler_converges_to_the_exact_response_at_first_order():
    """An independent check of both: semi-explicit Euler is first order, so halving h halves its
    distance to the exact response (ratio 2 within the pre-asymptotic spread)."""
    from hybridqcm.data.simulate import simulate_samples

    prior, road = build_prior("thesis", h=0.01), RoadProfile(n_waves=300)
    errors = []
    for h in (0.002, 0.001):
        kw = dict(n_steps=int(round(1.0 / h)), h=h, speed_mps=SPEED, samples_per_profile=5, warmup_s=(0.0, 0.0))
        euler = simulate_samples(
            prior, road, torch.tensor([0, 2]), generator=torch.Generator().manual_seed(8), physics="euler", **kw
        )
        exact = simulate_samples(
            prior, road, torch.tensor([0, 2]), generator=torch.Generator().manual_seed(8), physics="continuous", **kw
        )
        errors.append(
            ((euler["accel"] - exact["accel"]).pow(2).mean((0, 1)) / exact["accel"].pow(2).mean((0, 1))).sqrt()
        )
    ratio = errors[0] / errors[1]
    assert bool(((ratio > 1.8) & (ratio < 2.2)).all()), ratio
