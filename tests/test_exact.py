"""Exact discretisation layer: Jacobian (FD, autograd), continuous-time references, closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from hybridqcm.estimation._expm import discrete_maps, expm_taylor, expm_with_tangents
from hybridqcm.estimation.exact import exact_outputs, exact_sensitivities
from hybridqcm.estimation.hold import HOLDS, held_input, spline_matrix
from hybridqcm.estimation.sensitivity import euler_accelerations
from hybridqcm.physics import params_to_matrices, reference_params, road_gain, system_matrix
from hybridqcm.physics.linear_models import LinearModel, QuarterCarRoad, SeatBaseExcitation, SprungBaseExcitation
from hybridqcm.testing import synthetic_samples

H = 0.01
F64 = torch.float64
# low-frequency road made of sines, evaluated in continuous time: (amplitude m, frequency Hz, phase)
SINES = ((0.010, 0.7, 0.3), (0.006, 1.9, 1.1), (0.003, 3.1, 2.0))


def road(t):
    """u(t) for a numpy or torch array of times."""
    lib = torch if isinstance(t, torch.Tensor) else np
    return sum(a * lib.sin(2 * math.pi * f * t + ph) for a, f, ph in SINES)


@pytest.fixture(scope="module")
def samples():
    return synthetic_samples(3, n_steps=40, seed=5)


def _x0(batch, n, seed=0, scale=0.01):
    return scale * torch.randn(batch, n, generator=torch.Generator().manual_seed(seed), dtype=F64)


def _model_case(name, samples):
    p = samples["params"]
    u = samples["road"].to(F64)[..., None]
    if name == "quarter":
        return QuarterCarRoad(), p, u
    if name == "quarter_scaled":
        return QuarterCarRoad(scaled_road=True), p, road_gain(p)[:, None, None] * u
    accel = samples["accel"].to(F64)
    if name == "seat":
        return SeatBaseExcitation(), p[:, :2], accel[..., 1:2]
    return SprungBaseExcitation(), p[:, :6], accel[..., 2:3]


def _reference_outputs(model, p, x0, w, h, hold, substeps, start=0, n_steps=None, degree=5, states=None):
    """Plain differentiable implementation: torch.linalg.matrix_exp per sub-step, explicit loop over
    the window start .. start + n_steps - 1 (the spline through all samples); ``states``, a list,
    receives x_k."""
    A, B, C, E = model.matrices(p)
    n, m = model.n_state, model.n_input
    m_sub = substeps if hold == "spline" else 1
    tau = h / m_sub
    b = p.shape[0]
    zeros = lambda r, c: torch.zeros(b, r, c, dtype=F64)  # noqa: E731
    M = torch.cat(
        [
            torch.cat([A * tau, B * tau, zeros(n, m)], -1),
            torch.cat([zeros(m, n + m), torch.eye(m, dtype=F64).expand(b, m, m)], -1),
            zeros(m, n + 2 * m),
        ],
        -2,
    )
    F = torch.linalg.matrix_exp(M)
    phi, F1, F2 = F[:, :n, :n], F[:, :n, n : n + m], F[:, :n, n + m :]
    g0, g1 = (F1, torch.zeros_like(F2)) if hold == "zoh" else (F1 - F2, F2)
    T_in = w.shape[1]
    T = T_in - start if n_steps is None else n_steps
    fine = torch.einsum("st,btc->bsc", spline_matrix(T_in, m_sub, degree), w) if hold == "spline" else w
    x = x0 if x0 is not None else torch.zeros(p.shape[0], n, dtype=F64)
    ys = []
    for k in range(start, start + T):
        if states is not None:
            states.append(x)
        ys.append(torch.einsum("bon,bn->bo", C, x) + torch.einsum("bom,bm->bo", E, w[:, k]))
        for j in range(m_sub if k < start + T - 1 else 0):
            x = (
                torch.einsum("bij,bj->bi", phi, x)
                + torch.einsum("bij,bj->bi", g0, fine[:, k * m_sub + j])
                + torch.einsum("bij,bj->bi", g1, fine[:, k * m_sub + j + 1])
            )
    return torch.stack(ys, 1)


# ----------------------------------------------------------------------------- models
def test_quarter_car_matrices_agree_with_parameters(samples):
    p = samples["params"]
    for scaled in (False, True):
        A, B, C, E = QuarterCarRoad(scaled).matrices(p)
        D, S = params_to_matrices(p)
        torch.testing.assert_close(A, system_matrix(p), rtol=0, atol=0)
        torch.testing.assert_close(C, torch.cat([D, S], -1), rtol=0, atol=0)
        gain = torch.ones(3, dtype=F64) if scaled else road_gain(p)
        expected_b = torch.zeros(3, 6, 1, dtype=F64)
        expected_b[:, 2, 0] = gain
        torch.testing.assert_close(B, expected_b, rtol=0, atol=0)
        torch.testing.assert_close(E, expected_b[:, :3], rtol=0, atol=0)


@pytest.mark.parametrize(
    "model",
    [QuarterCarRoad(), QuarterCarRoad(True), SeatBaseExcitation(), SprungBaseExcitation()],
    ids=lambda m: m.name,
)
def test_linear_derivatives_match_jacfwd(model, samples):
    p = samples["params"][:, : model.n_params]
    closed = model.matrix_derivatives(p)
    generic = LinearModel.matrix_derivatives.__get__(model)  # same method, forced through jacfwd below
    model.linear_in_params = False
    try:
        jac = generic(p)
    finally:
        del model.linear_in_params
    for c, j in zip(closed, jac):
        assert c.shape == j.shape
        torch.testing.assert_close(c, j, rtol=0, atol=1e-15)


def test_euler_convention_rows_match_euler_layer(samples):
    """C x + E w with the Euler states is the Euler layer's acceleration (same output map)."""
    p, u = samples["params"], samples["road"].to(F64)
    _, _, C, E = QuarterCarRoad().matrices(p)
    x = torch.cat([samples["vel"], samples["disp"]], -1).to(F64)
    y = torch.einsum("bon,btn->bto", C, x) + E[:, None, :, 0] * u[..., None]
    torch.testing.assert_close(y, euler_accelerations(p, u, H), rtol=1e-6, atol=1e-6)


# ----------------------------------------------------------------------------- matrix exponential
def test_expm_taylor_and_tangents_against_torch():
    g = torch.Generator().manual_seed(1)
    M = (
        torch.randn(5, 8, 8, generator=g, dtype=F64)
        * torch.tensor([0.1, 1.0, 6.0, 30.0, 0.0], dtype=F64)[:, None, None]
    )
    dM = torch.randn(5, 3, 8, 8, generator=g, dtype=F64)
    ref = torch.linalg.matrix_exp(M)
    torch.testing.assert_close(expm_taylor(M), ref, rtol=1e-12, atol=1e-13 * ref.abs().amax())
    E, dE = expm_with_tangents(M, dM)
    torch.testing.assert_close(E, ref, rtol=1e-12, atol=1e-13 * ref.abs().amax())
    # Fréchet derivative: top-right block of exp([[M, dM], [0, M]]) ...
    block = torch.zeros(5, 3, 16, 16, dtype=F64)
    block[..., :8, :8] = M[:, None]
    block[..., 8:, 8:] = M[:, None]
    block[..., :8, 8:] = dM
    frechet = torch.linalg.matrix_exp(block)[..., :8, 8:]
    scale = frechet.abs().amax((-1, -2), keepdim=True)
    torch.testing.assert_close(dE, frechet, rtol=1e-11, atol=1e-12 * scale.amax())
    # ... and forward-mode autograd of torch.linalg.matrix_exp
    for j in range(3):
        _, jvp = torch.func.jvp(torch.linalg.matrix_exp, (M,), (dM[:, j],))
        torch.testing.assert_close(dE[:, j], jvp, rtol=1e-11, atol=1e-12 * scale.amax())


# ----------------------------------------------------------------------------- Jacobian
@pytest.mark.parametrize("hold", HOLDS)
@pytest.mark.parametrize("case", ["quarter", "quarter_scaled", "seat", "sprung"])
def test_jacobian_matches_autograd_through_matrix_exp(samples, case, hold):
    model, p, w = _model_case(case, samples)
    p, w = p[:2], w[:2]
    x0 = _x0(2, model.n_state)
    out = exact_sensitivities(model, p, x0, w, H, hold=hold, substeps=3)
    assert out.shape == (2, w.shape[1], model.n_output, 1 + model.n_params + model.n_state) and out.dtype == F64
    ref = _reference_outputs(model, p, x0, w, H, hold, 3)
    torch.testing.assert_close(out[..., 0], ref, rtol=1e-10, atol=1e-10 * ref.abs().amax())
    jac_p = torch.func.jacrev(lambda q: _reference_outputs(model, q, x0, w, H, hold, 3))(p)
    jac_x = torch.func.jacrev(lambda x: _reference_outputs(model, p, x, w, H, hold, 3))(x0)
    reference = torch.cat(
        [torch.stack([jac_p[i, :, :, i] for i in range(2)]), torch.stack([jac_x[i, :, :, i] for i in range(2)])], -1
    )
    scale = reference.abs().amax((0, 1, 2))
    err = (out[..., 1:] - reference).abs().amax((0, 1, 2))
    assert (err <= 1e-9 * scale + 1e-14).all(), f"relative errors {(err / scale).tolist()}"


@pytest.mark.parametrize("hold", ["spline", "foh"])
def test_jacobian_matches_finite_differences(samples, hold):
    model, p, w = _model_case("quarter", samples)
    x0 = _x0(3, 6, seed=2)
    out = exact_sensitivities(model, p, x0, w, H, hold=hold)
    for j in range(10):
        step = 1e-5 * p[:, j]
        plus, minus = p.clone(), p.clone()
        plus[:, j] += step
        minus[:, j] -= step
        fd = (exact_outputs(model, plus, x0, w, H, hold) - exact_outputs(model, minus, x0, w, H, hold)) / (2 * step)[
            :, None, None
        ]
        assert (out[..., 1 + j] - fd).abs().amax() <= 1e-6 * fd.abs().amax(), f"p{j + 1}"
    for i in range(6):
        plus, minus = x0.clone(), x0.clone()
        plus[:, i] += 1e-3
        minus[:, i] -= 1e-3
        fd = (exact_outputs(model, p, plus, w, H, hold) - exact_outputs(model, p, minus, w, H, hold)) / 2e-3
        assert (out[..., 11 + i] - fd).abs().amax() <= 1e-8 * fd.abs().amax(), f"x0[{i}]"
    without = exact_sensitivities(model, p, x0, w, H, hold=hold, with_x0=False)
    assert without.shape[-1] == 11
    torch.testing.assert_close(without, out[..., :11], rtol=1e-13, atol=1e-13)


# ----------------------------------------------------------------------------- continuous-time references
def _continuous_quarter_car(p: torch.Tensor, t: np.ndarray) -> np.ndarray:
    """Accelerations [len(t), 3] of the continuous quarter car from rest, road(t) in continuous time."""
    A = system_matrix(p).numpy()
    gain = float(road_gain(p))
    b = np.zeros(6)
    b[2] = gain
    sol = solve_ivp(
        lambda s, x: A @ x + b * road(s), (t[0], t[-1]), np.zeros(6), method="DOP853", t_eval=t, rtol=1e-12, atol=1e-15
    )
    x = sol.y.T
    return x @ A[:3].T + np.outer(road(t), b[:3])


def test_holds_converge_to_the_continuous_solution():
    p = torch.stack([reference_params(), synthetic_samples(1, n_steps=2, seed=7)["params"][0]])
    T = 100
    t = np.arange(T) * H
    reference = torch.tensor(np.stack([_continuous_quarter_car(p[i : i + 1][0], t) for i in range(2)]))
    w = road(torch.tensor(t))[None, :, None].expand(2, T, 1)
    model = QuarterCarRoad()

    def rel_err(hold, substeps=4):
        y = exact_outputs(model, p, None, w, H, hold, substeps)
        return float((y - reference).norm() / reference.norm())

    foh, zoh = rel_err("foh"), rel_err("zoh")
    spline = [rel_err("spline", m) for m in (1, 2, 4, 8)]
    assert spline[0] == pytest.approx(foh, rel=1e-9)  # one sub-step: the spline at the knots is the samples
    assert all(a > b for a, b in zip(spline, spline[1:])), spline  # decreasing with substeps
    assert spline[2] < foh / 5 and foh < zoh / 5, (foh, zoh, spline)
    assert spline[2] < 1e-3 and foh < 1e-2


def test_euler_layer_converges_to_exact_as_h_goes_to_zero():
    p = synthetic_samples(2, n_steps=2, seed=11)["params"]
    errors = []
    for h in (0.004, 0.002, 0.001):
        t = torch.arange(round(1.0 / h)) * h
        u = road(t)[None].expand(2, -1).to(F64)
        exact = exact_outputs(QuarterCarRoad(), p, None, u[..., None], h, "spline")
        errors.append(float((euler_accelerations(p, u, h) - exact).norm() / exact.norm()))
    ratios = [a / b for a, b in zip(errors, errors[1:])]
    assert all(1.7 < r < 2.3 for r in ratios), (errors, ratios)  # first order in h


# ----------------------------------------------------------------------------- exactness
def test_foh_is_exact_for_piecewise_linear_input():
    """Seat model driven by a piecewise-linear a2: closed form per piece (particular solution
    alpha + beta t of x' = A x + B (w0 + r t)), independent of Van Loan."""
    model = SeatBaseExcitation()
    p = torch.tensor([[7.7, 1237.0], [3.0, 400.0]], dtype=F64)
    T = 30
    knots = torch.randn(2, T, generator=torch.Generator().manual_seed(4), dtype=F64)
    x0 = _x0(2, 2, seed=6, scale=0.1)
    A, B, C, E = model.matrices(p)
    x, expected = x0.clone(), []
    for k in range(T):
        expected.append(torch.einsum("bon,bn->bo", C, x) + E[:, :, 0] * knots[:, k : k + 1])
        if k == T - 1:
            break
        rate = (knots[:, k + 1] - knots[:, k]) / H
        beta = -torch.linalg.solve(A, B[..., 0] * rate[:, None])
        alpha = torch.linalg.solve(A, beta - B[..., 0] * knots[:, k : k + 1])
        x = torch.einsum("bij,bj->bi", torch.linalg.matrix_exp(A * H), x - alpha) + alpha + beta * H
    expected = torch.stack(expected, 1)
    y = exact_outputs(model, p, x0, knots[..., None], H, "foh")
    torch.testing.assert_close(y, expected, rtol=0, atol=1e-12 * expected.abs().amax())
    ys = exact_sensitivities(model, p, x0, knots[..., None], H, "foh")[..., 0]
    torch.testing.assert_close(ys, expected, rtol=0, atol=1e-12 * expected.abs().amax())


@pytest.mark.parametrize("hold", HOLDS)
def test_free_response_is_the_matrix_exponential(samples, hold):
    p = samples["params"]
    x0 = _x0(3, 6, seed=8)
    T = 50
    y = exact_outputs(QuarterCarRoad(), p, x0, torch.zeros(3, T, 1, dtype=F64), H, hold)
    A, _, C, _ = QuarterCarRoad().matrices(p)
    t = torch.arange(T, dtype=F64) * H
    x = torch.einsum("btij,bj->bti", torch.linalg.matrix_exp(A[:, None] * t[None, :, None, None]), x0)
    expected = torch.einsum("bon,btn->bto", C, x)
    torch.testing.assert_close(y, expected, rtol=0, atol=1e-11 * expected.abs().amax())
    sens = exact_sensitivities(QuarterCarRoad(), p, x0, torch.zeros(3, T, 1, dtype=F64), H, hold)
    torch.testing.assert_close(sens[..., 0], expected, rtol=0, atol=1e-11 * expected.abs().amax())


def test_spline_matrix_reproduces_cubics():
    T, m = 9, 4
    t = torch.arange(T, dtype=F64)
    fine_t = torch.arange((T - 1) * m + 1, dtype=F64) / m
    cubic = lambda s: 0.3 - 1.2 * s + 0.5 * s**2 - 0.07 * s**3  # noqa: E731
    torch.testing.assert_close(spline_matrix(T, m) @ cubic(t), cubic(fine_t), rtol=0, atol=1e-12)
    assert spline_matrix(T, m).shape == ((T - 1) * m + 1, T)


@pytest.mark.parametrize("degree", [3, 5])
def test_spline_matrix_reproduces_polynomials_of_its_degree(degree):
    T, m = 14, 4
    t = torch.arange(T, dtype=F64)
    fine_t = torch.arange((T - 1) * m + 1, dtype=F64) / m
    g = torch.Generator().manual_seed(degree)
    for deg in range(degree + 2):
        coef = torch.randn(deg + 1, generator=g, dtype=F64) * 0.5 ** torch.arange(deg + 1)
        poly = lambda s: sum(c * (s - 6) ** i for i, c in enumerate(coef))  # noqa: B023, E731
        err = (spline_matrix(T, m, degree) @ poly(t) - poly(fine_t)).abs().amax() / poly(fine_t).abs().amax()
        if deg <= degree:
            assert err < 1e-12, (deg, float(err))
        else:  # one degree higher is not reproduced: the check can fail
            assert err > 1e-6, (deg, float(err))


def test_own_cubic_is_scipys_not_a_knot_cubic():
    from scipy.interpolate import make_interp_spline

    for T in (4, 7, 20):
        fine = np.arange((T - 1) * 3 + 1) / 3
        reference = make_interp_spline(np.arange(T, dtype=float), np.eye(T), k=3)(fine)
        torch.testing.assert_close(spline_matrix(T, 3, 3), torch.tensor(reference), rtol=0, atol=1e-13)
    # too few samples for the quintic: it falls back to the cubic
    torch.testing.assert_close(spline_matrix(5, 3, 5), spline_matrix(5, 3, 3), rtol=0, atol=0)


@pytest.mark.parametrize("hold", HOLDS)
def test_window_is_the_full_run_restarted_from_its_state(samples, hold):
    """Outputs (and Jacobian) for start/n_steps = the full run's samples, restarted from its state at
    `start`; the spline uses every input sample, so nothing depends on where the window lies."""
    model, p, w = _model_case("quarter", samples)
    x0 = _x0(3, 6, seed=3)
    states = []
    full = _reference_outputs(model, p, x0, w, H, hold, 4, states=states)
    start, n_steps = 11, 20
    window = exact_outputs(model, p, states[start], w, H, hold, 4, start=start, n_steps=n_steps)
    assert window.shape == (3, n_steps, 3)
    scale = full.abs().amax()
    torch.testing.assert_close(window, full[:, start : start + n_steps], rtol=0, atol=1e-11 * scale)
    sens = exact_sensitivities(model, p, states[start], w, H, hold, 4, start=start, n_steps=n_steps)
    torch.testing.assert_close(sens[..., 0], window, rtol=0, atol=1e-12 * scale)
    x_s = states[start]
    jac_p = torch.func.jacrev(lambda q: _reference_outputs(model, q, x_s, w, H, hold, 4, start, n_steps))(p)
    jac_x = torch.func.jacrev(lambda x: _reference_outputs(model, p, x, w, H, hold, 4, start, n_steps))(x_s)
    reference = torch.cat(
        [torch.stack([jac_p[i, :, :, i] for i in range(3)]), torch.stack([jac_x[i, :, :, i] for i in range(3)])], -1
    )
    err = (sens[..., 1:] - reference).abs().amax((0, 1, 2))
    assert (err <= 1e-9 * reference.abs().amax((0, 1, 2)) + 1e-14).all()
    # numpy integers are accepted; the default window is everything from start on
    torch.testing.assert_close(
        exact_outputs(model, p, states[start], w, H, hold, 4, start=np.int64(start), n_steps=np.int64(n_steps)),
        window,
        rtol=0,
        atol=0,
    )
    torch.testing.assert_close(
        exact_outputs(model, p, states[start], w, H, hold, 4, start=start), full[:, start:], rtol=0, atol=1e-11 * scale
    )


def test_margins_remove_the_edge_error_against_continuous_time():
    """Mid-drive window of the continuous simulator: held input through the window's samples only
    (spline end conditions at the edges) vs through 20 extra samples each side."""
    from hybridqcm.physics.continuous import simulate_continuous
    from hybridqcm.physics.prior import build_prior
    from hybridqcm.physics.road import RoadProfile

    g = torch.Generator().manual_seed(4)
    params = build_prior("thesis", h=None).sample(4, g).params.to(F64)
    road = RoadProfile(n_waves=200)
    amplitude, phase = road.draw(torch.randint(0, 3, (4,), generator=g), g)
    margin, T = 20, 100
    out = simulate_continuous(
        params, amplitude, phase, road.omega * (30 / 3.6), T + 2 * margin, H, torch.full((4,), 3.0)
    )
    x_start = torch.cat([out.vel[:, margin], out.disp[:, margin]], -1)  # (v3 v2 v1 q3 q2 q1) at the window start
    truth = out.accel[:, margin : margin + T]
    u = out.road[..., None]
    model = QuarterCarRoad()
    worst = {}
    for degree in (3, 5):
        bare = exact_outputs(model, params, x_start, u[:, margin : margin + T], H, substeps=16, spline_degree=degree)
        wide = exact_outputs(model, params, x_start, u, H, substeps=16, start=margin, n_steps=T, spline_degree=degree)
        scale = truth.abs().amax(1, keepdim=True)  # per sample and channel
        bare_err = ((bare - truth).abs() / scale).amax((0, 2))  # worst relative error per step [T]
        wide_err = ((wide - truth).abs() / scale).amax((0, 2))
        edge = torch.cat([bare_err[:5], bare_err[-5:]]).amax()
        assert edge > 5 * bare_err[20:80].amax(), (degree, bare_err.tolist())  # the problem: the edges
        assert wide_err.amax() < edge / (3 if degree == 3 else 10), (degree, float(wide_err.amax()), float(edge))
        assert wide_err.amax() < 2 * bare_err[20:80].amax()  # the edges now as good as the interior
        worst[degree] = float(wide_err.amax())
    assert worst[5] < worst[3] / 3, worst  # and the quintic beats the cubic (this road reaches 25 Hz)


# ----------------------------------------------------------------------------- base-excitation models
def test_seat_transmissibility_closed_form():
    model = SeatBaseExcitation()
    p = torch.tensor([[7.7, 1237.0], [12.0, 800.0]], dtype=F64)
    omega = 2 * math.pi * torch.tensor([1.5, 4.0], dtype=F64)
    p1, p2 = p.unbind(-1)
    denominator = -(omega**2) + 1j * p1 * omega + p2
    Z = -1 / denominator  # steady-state phasor of z for a2 = sin(omega t) = Im(e^{i omega t})
    H_closed = (1j * p1 * omega + p2) / denominator
    x0 = torch.stack([(1j * omega * Z).imag, Z.imag], -1)  # start on the steady state: no transient
    t = torch.arange(200, dtype=F64) * H
    a2 = torch.sin(omega[:, None] * t)
    expected = (H_closed[:, None] * torch.exp(1j * omega[:, None] * t)).imag
    # what is left is the FOH error on the sub-steps, ~(omega h/m)^2/12: it falls with m
    for substeps, tol in ((4, 1e-3), (16, 1e-4)):
        a3 = exact_outputs(model, p, x0, a2[..., None], H, "spline", substeps)[..., 0]
        torch.testing.assert_close(a3, expected, rtol=0, atol=tol * expected.abs().amax())


def test_sprung_model_reproduces_quarter_car_simulation():
    p = torch.stack([reference_params(), synthetic_samples(1, n_steps=2, seed=3)["params"][0]])
    T = 100
    t = np.arange(T) * H
    a_full = torch.tensor(np.stack([_continuous_quarter_car(p[i], t) for i in range(2)]))  # [2, T, (a3, a2, a1)]
    y = exact_outputs(SprungBaseExcitation(), p[:, :6], None, a_full[..., 2:3], H, "spline")
    err = (y - a_full[..., :2]).norm() / a_full[..., :2].norm()
    assert err < 1e-3, float(err)


# ----------------------------------------------------------------------------- validation
def test_bad_input_raises_one_line_errors(samples):
    model, p, w = _model_case("quarter", samples)
    bad = [
        dict(params=p[:, :9]),
        dict(inputs=w[:2]),
        dict(inputs=w[..., 0, None, None]),
        dict(x0=torch.zeros(3, 5)),
        dict(h=0.0),
        dict(h=-0.01),
        dict(h=float("nan")),
        dict(hold="cubic"),
        dict(substeps=0),
        dict(substeps=1.5),
        dict(inputs=torch.zeros(3, 0, 1)),
        dict(start=-1),
        dict(start=40),
        dict(n_steps=0),
        dict(n_steps=41),
        dict(start=30, n_steps=11),
        dict(start=1.0),
        dict(spline_degree=4),
        dict(spline_degree=9),  # 3, 5 and 7 are the degrees offered
    ]
    for fn in (exact_outputs, exact_sensitivities):
        for override in bad:
            kwargs = dict(model=model, params=p, x0=None, inputs=w, h=H, hold="spline", substeps=4)
            kwargs.update(override)
            with pytest.raises(ValueError) as info:
                fn(**kwargs)
            assert "\n" not in str(info.value) and str(info.value).startswith("exact:"), override
    with pytest.raises(ValueError, match="params must be"):
        QuarterCarRoad().matrices(p[:, :9])


def test_single_sample_and_two_dimensional_input(samples):
    model, p, w = _model_case("quarter", samples)
    y = exact_outputs(model, p, None, w[:, :1], H)
    assert y.shape == (3, 1, 3)
    torch.testing.assert_close(exact_outputs(model, p, None, w[..., 0], H), exact_outputs(model, p, None, w, H))
    maps = discrete_maps(model, p, H, "spline", 4)
    assert maps[0].shape == (3, 6, 6) and maps[1].shape == (3, 5, 6, 1)


def test_long_recording_uses_only_the_samples_near_the_window():
    """A window deep inside a long input equals the same window cut with 70 samples each side
    (beyond the spline's reach the weights are below round-off), and costs no [T_in, T_in] matrix."""
    T_in, start, n_steps = 20000, 12345, 50
    u = road(torch.arange(T_in, dtype=F64) * H)[None, :, None] + 1e-3 * torch.randn(
        1, T_in, 1, generator=torch.Generator().manual_seed(9), dtype=F64
    )
    p = reference_params()[None]
    x0 = _x0(1, 6, seed=1)
    long = exact_outputs(QuarterCarRoad(), p, x0, u, H, start=start, n_steps=n_steps)
    cut = exact_outputs(QuarterCarRoad(), p, x0, u[:, start - 70 : start + n_steps + 70], H, start=70, n_steps=n_steps)
    torch.testing.assert_close(long, cut, rtol=0, atol=1e-14 * cut.abs().amax())
    assert long.shape == (1, n_steps, 3)


def test_per_sample_output_derivatives_take_the_general_path(samples):
    """A model without constant derivative matrices (jacfwd, one per sample) gives the same
    Jacobian as the linear model's shared-matrix shortcut."""

    class GenericQuarterCar(QuarterCarRoad):
        linear_in_params = False

    model, p, w = _model_case("quarter", samples)
    x0 = _x0(3, 6, seed=4)
    assert GenericQuarterCar().matrix_derivatives(p)[2].stride(0) != 0
    shortcut = exact_sensitivities(model, p, x0, w, H)
    general = exact_sensitivities(GenericQuarterCar(), p, x0, w, H)
    torch.testing.assert_close(general, shortcut, rtol=1e-12, atol=1e-12 * shortcut.abs().amax())


# ----------------------------------------------------------------------------- modal evaluation
def _random_case(name: str, batch: int, n_in: int, seed: int):
    """Thesis-prior parameters (scattered by 30 %) and a white-noise input of n_in samples."""
    g = torch.Generator().manual_seed(seed)
    p = synthetic_samples(batch, n_steps=2, seed=seed)["params"].to(F64)
    p = p * (1 + 0.3 * torch.rand(p.shape, generator=g, dtype=F64) - 0.15)
    model = {"quarter": QuarterCarRoad(), "seat": SeatBaseExcitation(), "sprung": SprungBaseExcitation()}[name]
    w = torch.randn(batch, n_in, 1, generator=g, dtype=F64) * (0.01 if name == "quarter" else 1.0)
    return model, p[:, : model.n_params], w


def _column_error(new: torch.Tensor, old: torch.Tensor) -> float:
    """Largest difference relative to each output column's largest value."""
    scale = old.abs().amax((0, 1)).clamp_min(1e-300)
    return float(((new - old).abs().amax((0, 1)) / scale).max())


@pytest.mark.parametrize("hold", HOLDS)
@pytest.mark.parametrize("case", ["quarter", "seat", "sprung"])
def test_modal_evaluation_matches_the_step_recursion(case, hold):
    model, p, w = _random_case(case, 48, 130, seed=11)
    x0 = _x0(48, model.n_state, seed=3)
    for x, with_x0, start, n_steps in [
        (x0, True, 9, 100),
        (x0, False, 0, 130),
        (None, True, 20, 7),
        (None, False, 0, 2),
    ]:
        kwargs = dict(hold=hold, substeps=5, with_x0=with_x0, start=start, n_steps=n_steps)
        old = exact_sensitivities(model, p, x, w, H, method="recursion", **kwargs)
        new = exact_sensitivities(model, p, x, w, H, **kwargs)
        assert new.shape == old.shape
        # two float64 evaluation orders of 130 steps: ~1e-10 of a column (1.8e-10 seen on the quarter car's
        # spline hold with one BLAS build); a wrong modal term is off by O(1)
        assert _column_error(new, old) <= 1e-9, (with_x0, start, n_steps)


@pytest.mark.parametrize("delta", [0.0, 1e-7, -1e-7, 1e-4, 1e-2])
def test_modal_hands_nearly_repeated_eigenvalues_to_the_recursion(delta):
    """Seat damped near critically, p1^2 = 4 p2 (1 + delta)^2: a double eigenvalue at delta = 0."""
    from hybridqcm.estimation._expm import balance
    from hybridqcm.estimation._modal import modal_sensitivities
    from hybridqcm.estimation.hold import held_input

    model = SeatBaseExcitation()
    p2 = torch.tensor([400.0, 150.0], dtype=F64)
    p = torch.stack([2 * p2.sqrt() * (1 + delta), p2], 1)
    w = torch.randn(2, 120, 1, generator=torch.Generator().manual_seed(1), dtype=F64)
    x0 = _x0(2, 2, seed=4)
    old = exact_sensitivities(model, p, x0, w, H, method="recursion", start=8, n_steps=100)
    new = exact_sensitivities(model, p, x0, w, H, start=8, n_steps=100)
    assert torch.isfinite(new).all() and _column_error(new, old) <= 1e-10
    A, B, C, E = model.matrices(p)
    fine = held_input(w, "spline", 4, 8, 100).permute(2, 1, 0)
    _, ok = modal_sensitivities(
        (A, B, C, E), model.matrix_derivatives(p), balance(A), x0, fine, w[:, 8:108], H, "spline", True
    )
    assert bool(ok.all()) == (abs(delta) > 1e-3)


@pytest.mark.parametrize("hold", HOLDS)
@pytest.mark.parametrize("case", ["quarter", "seat", "sprung"])
def test_modal_outputs_match_the_step_recursion(case, hold):
    model, p, w = _random_case(case, 48, 130, seed=12)
    x0 = _x0(48, model.n_state, seed=5)
    for x, start, n_steps in [(x0, 9, 100), (None, 0, 130), (x0, 20, 7), (None, 0, 2), (x0, 3, 1)]:
        kwargs = dict(hold=hold, substeps=5, start=start, n_steps=n_steps)
        old = exact_outputs(model, p, x, w, H, method="recursion", **kwargs)
        for method in ("modal", "auto"):
            new = exact_outputs(model, p, x, w, H, method=method, **kwargs)
            assert new.shape == old.shape
            assert _column_error(new, old) <= 1e-10, (method, start, n_steps)


@pytest.mark.parametrize("path", ["kernel", "torch"])
@pytest.mark.parametrize("rows", [3, 700])  # below and above _modal._SCAN_ROW: blocked, and step by step
@pytest.mark.parametrize("n_steps", [1, 2, 7, 30, 101, 500])
def test_blocked_scan_matches_the_step_recursion(n_steps, rows, path, monkeypatch):
    """_scan (the compiled loop, or in torch the modal basis' recursion in blocks) against the plain steps
    z_k = mu z_(k-1) + F_k (and, for the (z, dz) pairs, dz_k += h z_k after each step) on random forcing, and
    against the closed form of the pairs' free response, z_k = mu^k z_0, dz_k = mu^k (dz_0 + k h z_0)."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._modal import _scan

    if path == "torch":
        monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    assert _kernels.applies(torch.zeros(1, dtype=torch.complex128)) == (path == "kernel")

    g = torch.Generator().manual_seed(n_steps + rows)
    rate = torch.complex(
        -0.2 * torch.rand(rows, 2, 1, 1, generator=g, dtype=F64), torch.rand(rows, 2, 1, 1, generator=g, dtype=F64)
    )
    rate = rate.expand(rows, 2, 2, 1)  # the pair's two kinds share their mode's rate
    forcing = torch.complex(*torch.randn(2, n_steps, rows, 2, 2, 1, generator=g, dtype=F64))
    for h in (None, H):
        shape = rate.shape if h is not None else rate[:, :, 0].shape
        mu = torch.exp(rate if h is not None else rate[:, :, 0])
        steps = forcing.clone() if h is not None else forcing[:, :, :, 0].clone()
        for k in range(1, n_steps):
            steps[k] += mu * steps[k - 1]
            if h is not None:
                steps[k][..., 1, :] += h * steps[k][..., 0, :]
        blocked = forcing.clone() if h is not None else forcing[:, :, :, 0].clone()
        _scan(blocked, rate if h is not None else rate[:, :, 0], h)
        assert blocked.shape == (n_steps, *shape)
        torch.testing.assert_close(blocked, steps, rtol=0, atol=1e-12 * float(steps.abs().amax()))
    free = torch.zeros(n_steps, *rate.shape, dtype=torch.complex128)
    free[0] = forcing[0]
    _scan(free, rate, H)
    k = torch.arange(n_steps, dtype=F64).view(-1, 1, 1, 1)
    power = torch.exp(k * rate[..., 0, :])
    z0, dz0 = forcing[0][..., 0, :], forcing[0][..., 1, :]
    torch.testing.assert_close(free[..., 0, :], power * z0, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(free[..., 1, :], power * (dz0 + k * H * z0), rtol=1e-12, atol=1e-14)


def test_the_compiled_scan_gives_the_same_numbers_stored_batch_first():
    """_modal's basis buffer is stored batch first where the compiled scan runs (_basis_buffer): the loop then takes
    one sample's steps in order. Each value takes the same operations as in a time-first buffer: equal bit for bit,
    with and without the (z, dz) pairs."""
    from hybridqcm.estimation import _kernels

    g = torch.Generator().manual_seed(4)
    n_steps, rows = 40, 9
    rate = torch.complex(
        -0.1 * torch.rand(rows, 3, 2, 2, generator=g, dtype=F64), torch.rand(rows, 3, 2, 2, generator=g, dtype=F64)
    )
    forcing = torch.complex(*torch.randn(2, n_steps, rows, 3, 2, 2, generator=g, dtype=F64))
    for h in (None, H):
        time_first = forcing.clone()
        batch_first = forcing.transpose(0, 1).contiguous().transpose(0, 1)
        assert batch_first.stride(1) > batch_first.stride(0)
        _kernels.modal_scan(time_first, rate, h)
        _kernels.modal_scan(batch_first, rate, h)
        assert torch.equal(batch_first, time_first)
        assert not torch.equal(time_first, forcing)


@pytest.mark.parametrize("with_x0", [False, True])
def test_the_compiled_state_recursion_equals_the_torch_steps(with_x0, monkeypatch):
    """exact._primal_states, x_(k+1) = Phi x_k + F_k per sample, by the compiled loop against the torch steps and
    against the closed form of a diagonal Phi's free response, x_k = Phi^k x_0."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation.exact import _primal_states

    g = torch.Generator().manual_seed(11)
    n, b, T = 6, 37, 90
    phi = 0.3 * torch.randn(n, n, b, generator=g, dtype=F64) / n**0.5
    forcing = torch.randn(T - 1, n, b, generator=g, dtype=F64)
    x0 = torch.randn(b, n, generator=g, dtype=F64) if with_x0 else None
    assert _kernels.applies(phi)
    compiled = _primal_states(phi, forcing, x0, b, n, T, "cpu")
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    steps = _primal_states(phi, forcing, x0, b, n, T, "cpu")
    torch.testing.assert_close(compiled, steps, rtol=1e-13, atol=1e-13 * float(steps.abs().amax()))
    monkeypatch.delenv("HYBRIDQCM_KERNELS")
    diagonal = torch.diag_embed(torch.rand(b, n, generator=g, dtype=F64)).permute(1, 2, 0).contiguous()
    free = _primal_states(diagonal, torch.zeros_like(forcing), x0, b, n, T, "cpu")
    start = x0.t() if with_x0 else torch.zeros(n, b, dtype=F64)
    powers = torch.diagonal(diagonal, dim1=0, dim2=1).t()[None] ** torch.arange(T, dtype=F64).view(-1, 1, 1)
    torch.testing.assert_close(free, powers * start, rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("path", ["kernel", "torch"])
@pytest.mark.parametrize("m_sub", [1, 4, 16])
def test_hold_weights_integrate_constant_and_ramp_inputs_exactly(m_sub, path, monkeypatch):
    """_modal._hold_weights (the compiled loop, or torch's ops) against closed forms of one step of psi' = lambda psi + s(t)
    from psi = 0: a constant input held as 1 at every sub-step gives (e^(lambda h) - 1) / lambda under either hold, a
    ramp s = t (exact under the first-order hold) (e^(lambda h) - 1 - lambda h) / lambda^2; d l_j / d lambda against
    central differences of l_j in lambda (the weights are analytic in lambda); and the two paths against each other."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._modal import _hold_weights

    if path == "torch":
        monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    assert _kernels.applies(torch.zeros(1, dtype=torch.complex128)) == (path == "kernel")
    # |lambda tau| below and above 1 (the series and the recurrence), a real mode, a nearly zero one
    lam = torch.tensor(
        [[-3.0 + 30.0j, -40.0 + 0.0j, -1e-7 + 0.0j], [-600.0 + 2500.0j, -9000.0 + 0.0j, -25.0 - 180.0j]],
        dtype=torch.complex128,
    )
    tau = H / m_sub
    for hold in ("zoh", "spline"):
        ell, dell = _hold_weights(lam, H, hold, m_sub)
        assert ell.shape == dell.shape == (m_sub + 1, 2, 3)
        # per mode phi_1(lambda h) h and the ramp's integral, by the series where lambda h is small
        z = lam * H
        small = z.abs() < 1e-3
        step = torch.where(small, H * (1 + z / 2 + z * z / 6), torch.expm1(z) / lam)
        ramp = torch.where(small, H * H * (0.5 + z / 6 + z * z / 24), (torch.expm1(z) - z) / lam**2)
        torch.testing.assert_close(ell.sum(0), step, rtol=1e-12, atol=0)
        if hold != "zoh":
            times = (torch.arange(m_sub + 1, dtype=F64) * tau).view(-1, 1, 1)
            torch.testing.assert_close((ell * times).sum(0), ramp, rtol=1e-11, atol=0)
        eps = 1e-6 * lam.abs().clamp_min(1 / H)  # at least 1e-6 / h: a nearly zero mode needs no smaller one
        up, _ = _hold_weights(lam + eps, H, hold, m_sub)
        down, _ = _hold_weights(lam - eps, H, hold, m_sub)
        fd = (up - down) / (2 * eps)
        torch.testing.assert_close(dell, fd, rtol=1e-6, atol=1e-9 * float(dell.abs().amax()))
        monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch" if path == "kernel" else "")
        other = _hold_weights(lam, H, hold, m_sub)
        monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch" if path == "torch" else "")
        for mine, theirs in zip((ell, dell), other):
            torch.testing.assert_close(mine, theirs, rtol=1e-13, atol=1e-15 * float(theirs.abs().amax()))


def test_the_compiled_balance_equals_torchs(monkeypatch):
    """_expm.balance by the compiled loop and by torch's ops: the same powers of two, on matrices whose rows span eight
    decades, with a zero matrix, a zero column and a non-finite entry among them."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._expm import balance

    g = torch.Generator().manual_seed(5)
    M = torch.randn(64, 6, 6, generator=g, dtype=F64) * torch.logspace(-3, 5, 6, dtype=F64)[None, :, None]
    M[0] = 0.0
    M[1, :, 2] = 0.0
    M[2, 3, 4] = math.inf
    assert _kernels.applies(M)
    compiled = balance(M)
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    reference = balance(M)
    assert compiled.shape == (64, 6)
    torch.testing.assert_close(compiled, reference, rtol=0, atol=0, equal_nan=True)
    finite = compiled[3:]
    assert bool((torch.exp2(torch.round(torch.log2(finite))) == finite).all())  # powers of two: an exact scaling
    assert bool((compiled[0] == 1).all())


@pytest.mark.parametrize("hold", HOLDS)
@pytest.mark.parametrize("case", ["quarter", "seat", "sprung"])
def test_the_compiled_van_loan_maps_integrate_constant_and_ramp_inputs_exactly(case, hold, monkeypatch):
    """_expm.van_loan_maps without tangents by the compiled loop: Phi = exp(A h) (torch.linalg.matrix_exp), the
    forcing of a constant input sum_j Lam_j = A^-1 (Phi - I) B and, under the first-order holds, of the ramp
    s_j = j tau: sum_j j tau Lam_j = (A^-2 (Phi - I) - h A^-1) B (closed forms of the variation of constants); and
    torch's batch-innermost ops give the same maps."""
    from hybridqcm.estimation._expm import van_loan_maps

    model, p, _ = _random_case(case, 7, 10, seed=21)
    substeps = 5
    m_sub = substeps if hold == "spline" else 1
    phi, lam = van_loan_maps(model, p, H, hold, substeps, False)  # [n, n, b], [m_sub + 1, n, m, b]
    A, B, _, _ = model.matrices(p)
    eye = torch.eye(model.n_state, dtype=F64)
    expected_phi = torch.linalg.matrix_exp(A * H)
    torch.testing.assert_close(phi.permute(2, 0, 1), expected_phi, rtol=1e-13, atol=1e-13)
    A_inv = torch.linalg.inv(A)
    constant = A_inv @ (expected_phi - eye) @ B
    torch.testing.assert_close(lam.sum(0).permute(2, 0, 1), constant, rtol=1e-11, atol=1e-13 * constant.abs().amax())
    if hold != "zoh":  # the zero-order hold holds s_0 over the step: a ramp is not what it integrates
        tau = H / m_sub
        ramp = (A_inv @ A_inv @ (expected_phi - eye) - H * A_inv) @ B
        weights = torch.arange(m_sub + 1, dtype=F64)[:, None, None, None] * tau
        torch.testing.assert_close(
            (lam * weights).sum(0).permute(2, 0, 1), ramp, rtol=1e-10, atol=1e-12 * ramp.abs().amax()
        )
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    torch_phi, torch_lam = van_loan_maps(model, p, H, hold, substeps, False)
    torch.testing.assert_close(phi, torch_phi, rtol=1e-13, atol=1e-15 * torch_phi.abs().amax())
    torch.testing.assert_close(lam, torch_lam, rtol=1e-13, atol=1e-15 * torch_lam.abs().amax())


def test_preload_loads_a_loop_only_where_the_loops_run(monkeypatch):
    """qcm-estimate's runner loads numba before its solve's clock starts; with the loops off it loads nothing."""
    from hybridqcm.estimation import _kernels

    monkeypatch.setattr(_kernels, "_compiled", {})
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    assert _kernels.preload() is False and _kernels._compiled == {}
    monkeypatch.delenv("HYBRIDQCM_KERNELS")
    assert _kernels.preload() is True and list(_kernels._compiled) == ["_states_loop"]


@pytest.mark.parametrize("hold", HOLDS)
@pytest.mark.parametrize("case", ["quarter", "seat", "sprung"])
def test_the_compiled_van_loan_maps_with_tangents_equal_the_block_exponential(case, hold, monkeypatch):
    """_expm.van_loan_maps_batch_first by the compiled loop (forward-mode tangents through the Taylor products and the
    folded sub-steps) against torch's: the Frechet derivatives as blocks of exp([[M, dM_j], [0, M]]) by
    torch.linalg.matrix_exp, folded by per-sample products; and against central differences of the maps."""
    from hybridqcm.estimation._expm import van_loan_maps_batch_first

    model, p, _ = _random_case(case, 5, 10, seed=23)
    compiled = van_loan_maps_batch_first(model, p, H, hold, 5)
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    reference = van_loan_maps_batch_first(model, p, H, hold, 5)
    for got, want in zip(compiled, reference):
        assert got.shape == want.shape
        torch.testing.assert_close(got, want, rtol=1e-11, atol=1e-13 * want.abs().amax())
    monkeypatch.delenv("HYBRIDQCM_KERNELS")
    for j in (0, p.shape[1] - 1):
        step = torch.zeros_like(p)
        step[:, j] = 1e-4 * p[:, j]  # smaller: the maps' rounding (g0 = F1 - F2) would dominate the difference
        up, down = (
            van_loan_maps_batch_first(model, p + step, H, hold, 5),
            van_loan_maps_batch_first(model, p - step, H, hold, 5),
        )
        for k, tangent in ((0, compiled[2][:, j]), (1, compiled[3][:, j])):
            fd = (up[k] - down[k]) / (2 * step[:, j].view(-1, *([1] * (up[k].ndim - 1))))
            torch.testing.assert_close(tangent, fd, rtol=1e-5, atol=1e-7 * fd.abs().amax())


def test_the_compiled_van_loan_maps_keep_a_non_finite_sample_to_itself():
    """A NaN parameter gives that sample NaN maps, with and without tangents; the batch's other samples get the maps
    they get alone, also beside a sample whose matrix is 1e6 times larger (the scaling 2^-s is chosen per sample: a
    profile's wide trial must not move its batch mates' maps), and a mismatched shape is refused in one line."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._expm import van_loan_maps, van_loan_maps_batch_first

    model = QuarterCarRoad()
    p = reference_params().expand(4, 10).clone()
    p[1, 0] = math.nan
    p[3] *= 1e6
    phi, lam = van_loan_maps(model, p, H, "spline", 4, False)
    assert bool(phi[..., 1].isnan().all()) and bool(lam[..., 1].isnan().all())
    assert bool(torch.isfinite(phi[..., 3]).all())
    for i in (0, 2, 3):
        alone = van_loan_maps(model, p[i : i + 1], H, "spline", 4, False)
        torch.testing.assert_close(phi[..., i : i + 1], alone[0], rtol=0, atol=0)
        torch.testing.assert_close(lam[..., i : i + 1], alone[1], rtol=0, atol=0)
    tangent = van_loan_maps_batch_first(model, p, H, "spline", 4)  # the fallback's maps, per sample
    assert all(bool(x[1].isnan().all()) for x in tangent)
    for i in (0, 2):
        for got, alone in zip(tangent, van_loan_maps_batch_first(model, p[i : i + 1], H, "spline", 4)):
            torch.testing.assert_close(got[i : i + 1], alone, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"^_kernels: d must be \[3, 8\], got \[3, 7\]$"):
        _kernels.van_loan_maps(torch.zeros(8, 8, 3, dtype=F64), torch.ones(3, 7, dtype=F64), 6, False, 4, 11, 0.25)


@pytest.mark.parametrize("sort", [False, True])
def test_the_compiled_modes_equal_torchs_and_rebuild_A(sort, monkeypatch):
    """_modal._decompose by the compiled loop and by torch's ops: the same eigenvalues in the same order, V, V^-1,
    condition numbers, flags and counts, on quarter-car and seat system matrices, a matrix with real eigenvalues only,
    a defective one (a Jordan block: eigenvectors parallel to rounding, cond(V) beyond 1e10) and a non-finite one;
    where ok and well conditioned, V diag(lambda) V^-1 rebuilds A."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._expm import balance
    from hybridqcm.estimation._modal import _decompose

    g = torch.Generator().manual_seed(3)
    params = synthetic_samples(6, n_steps=2, seed=4)["params"].to(F64)
    A = torch.zeros(10, 6, 6, dtype=F64)
    A[:6] = system_matrix(params)
    A[6] = torch.diag(-torch.arange(1.0, 7.0, dtype=F64)) + 0.1 * torch.triu(torch.ones(6, 6, dtype=F64), 1)
    A[7] = -2.0 * torch.eye(6, dtype=F64) + torch.diag(torch.ones(5, dtype=F64), 1)  # one Jordan block
    A[8] = torch.randn(6, 6, generator=g, dtype=F64)
    A[9] = A[0]
    A[9, 2, 3] = math.nan
    scale = balance(A)
    assert _kernels.applies(A)
    compiled = _decompose(A, scale, sort)
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    reference = _decompose(A, scale, sort)
    lam, V, V_inv, cond, ok, n_first = compiled
    assert torch.equal(ok, reference[4]) and torch.equal(n_first, reference[5])
    assert ok[:7].all() and ok[8] and not ok[9] and (not ok[7] or cond[7] > 1e10)
    good = (ok & (cond < 1e8)).nonzero().flatten()
    assert good.numel() == 8
    assert torch.equal(lam[good], reference[0][good])  # LAPACK's values, reordered alike
    for mine, theirs in zip((V, V_inv, cond), reference[1:4]):
        torch.testing.assert_close(mine[good], theirs[good], rtol=1e-10, atol=1e-12 * float(theirs[good].abs().amax()))
    rebuilt = (V[good] * lam[good][:, None, :]) @ V_inv[good]
    torch.testing.assert_close(rebuilt.real, A[good], rtol=0, atol=1e-9 * float(A[good].abs().amax()))
    assert float(rebuilt.imag.abs().amax()) < 1e-9 * float(A[good].abs().amax())
    if sort:  # the upper members of the pairs first, then the real ones
        key = torch.where(lam.imag > 0, 0, torch.where(lam.imag == 0, 1, 2))
        assert bool((key[good].diff(dim=1) >= 0).all())


def test_a_balancing_that_underflows_is_not_ok_and_raises_nothing(monkeypatch):
    """A wild trial's matrix (entries 1e300 and 1e-300: a body fit run off on a recording it cannot explain) balances
    to a scale of 0 and inf. The compiled loop once divided V^-1 by that 0 in complex arithmetic, which numba turns
    into ZeroDivisionError whatever its error model (`qcm-estimate experiment=occupant_roadfree
    occupant.models=[body1] delay=null` on a delayed file stopped so); now the sample is not ok, as by torch's ops."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._expm import balance
    from hybridqcm.estimation._modal import _decompose

    A = torch.zeros(2, 4, 4, dtype=F64)
    A[:, 2, 3], A[:, 3, 2], A[:, 2, 1] = 1.0, -1.0, 1.0
    A[0, 0, 1], A[0, 1, 0], A[0, 1, 2] = 1e300, 1e-300, 1e-300
    A[1, 0, 1], A[1, 1, 0], A[1, 1, 2] = 2.0, -3.0, 0.5  # an ordinary batch mate
    scale = balance(A)
    assert (scale[0] == 0).any() and _kernels.applies(A)
    compiled = _decompose(A, scale, True)
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    reference = _decompose(A, scale, True)
    assert compiled[4].tolist() == reference[4].tolist() == [False, True]
    for mine, theirs in zip(compiled[:4], reference[:4]):
        torch.testing.assert_close(mine[1], theirs[1], rtol=1e-12, atol=1e-12)


def _person_case(name: str, batch: int, n_in: int, seed: int):
    """A person (one or two body modes) on the road-free seat or in the quarter car, parameters scattered by 30 %
    around a 5 Hz body: derivatives per sample (the models are not linear in their parameters)."""
    from hybridqcm.physics.linear_models import QuarterCarOccupantRoad, SeatOccupantBaseExcitation

    g = torch.Generator().manual_seed(seed)
    n_modes = 2 if name.endswith("2") else 1
    body = []
    for r, f, zeta in ((0.6, 5.0, 0.4), (0.3, 9.0, 0.3))[:n_modes]:
        w = 2 * math.pi * f
        body += [r, w * w, 2 * zeta * w]
    vehicle = synthetic_samples(batch, n_steps=2, seed=seed)["params"].to(F64)
    if name.startswith("seat"):
        model, base = SeatOccupantBaseExcitation(n_modes), vehicle[:, :2]
    else:
        model, base = QuarterCarOccupantRoad(n_modes), vehicle
    p = torch.cat([base, torch.tensor(body, dtype=F64).expand(batch, -1)], 1)
    p = p * (1 + 0.3 * torch.rand(p.shape, generator=g, dtype=F64) - 0.15)
    w = torch.randn(batch, n_in, 1, generator=g, dtype=F64) * (0.01 if name.startswith("quarter") else 1.0)
    return model, p, w


@pytest.mark.parametrize("case", ["quarter", "sprung", "seat_body1", "seat_body2", "quarter_body1"])
def test_the_compiled_modal_coefficients_equal_torchs(case, monkeypatch):
    """modal_sensitivities with its coefficients (V^-1 dA_j V, the Sylvester terms, the real form's weights) from the
    compiled loop and from torch's ops: the same ok flags and the same result to rounding, for a linear model's
    shared derivatives and a person's per-sample ones, with x0 or from rest, with x0's columns or not, with the
    targets' columns or not; a sample with a NaN and one damped nearly critically (the spread test) are not ok on
    both paths and change no other sample. The modal result against the step recursion, an independent evaluation
    (test_modal_evaluation_matches_the_step_recursion's bound)."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._expm import balance
    from hybridqcm.estimation._modal import modal_sensitivities

    batch = 12
    if case in ("quarter", "sprung"):
        model, p, w = _random_case(case, batch, 110, seed=21)
    else:
        model, p, w = _person_case(case, batch, 110, seed=21)
    A, B, C, E = model.matrices(p)
    derivatives = model.matrix_derivatives(p)
    A = A.clone()
    A[3, 0, 0] = math.nan
    fine = held_input(w, "spline", 4, 8, 100).permute(2, 1, 0)
    x0 = _x0(batch, model.n_state, seed=8)
    targets = torch.randn(batch, 100, model.n_output, generator=torch.Generator().manual_seed(2), dtype=F64)
    assert _kernels.applies(A)
    for x, with_x0, t in [(x0, True, targets), (None, False, None), (x0, False, None), (None, True, targets)]:
        args = ((A, B, C, E), derivatives, balance(A), x, fine, w[:, 8:108], H, "spline", with_x0, t)
        compiled, ok = modal_sensitivities(*args)
        monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
        reference, ok_reference = modal_sensitivities(*args)
        monkeypatch.delenv("HYBRIDQCM_KERNELS")
        assert torch.equal(ok, ok_reference) and not ok[3] and int(ok.sum()) >= batch - 2
        assert _column_error(compiled[ok], reference[ok]) <= 1e-12
        good = ok.nonzero().flatten()
        recursion = exact_sensitivities(
            model, p[good], None if x is None else x[good], w[good], H, "spline", 4, with_x0, 8, 100, method="recursion"
        )
        if t is not None:
            recursion[..., 0] -= t[good]
        assert _column_error(compiled[good], recursion) <= 1e-9
    seat = SeatBaseExcitation()
    p2 = torch.tensor([400.0, 150.0], dtype=F64)
    p_seat = torch.stack([2 * p2.sqrt() * (1 + torch.tensor([1e-6, 1e-1], dtype=F64)), p2], 1)  # one nearly double
    A, B, C, E = seat.matrices(p_seat)
    fine = held_input(w[:2], "spline", 4, 8, 100).permute(2, 1, 0)
    args = ((A, B, C, E), seat.matrix_derivatives(p_seat), balance(A), None, fine, w[:2, 8:108], H, "spline", False)
    compiled, ok = modal_sensitivities(*args)
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    reference, ok_reference = modal_sensitivities(*args)
    assert ok.tolist() == ok_reference.tolist() == [False, True]
    assert _column_error(compiled[1:], reference[1:]) <= 1e-12


def test_the_compiled_modal_coefficients_refuse_a_wrong_shape():
    """The loop indexes without bounds checks: a derivative of the wrong shape is one line naming it."""
    from hybridqcm.estimation import _kernels
    from hybridqcm.estimation._expm import balance
    from hybridqcm.estimation._modal import _modes

    model, p, _ = _random_case("seat", 3, 10, seed=1)
    A, B, C, E = model.matrices(p)
    dA, dB, dC, dE = model.matrix_derivatives(p)
    lam, V, V_inv, cond, ok, omega = _modes(A, balance(A))
    with pytest.raises(ValueError, match=r"^_kernels: dA must be \[3, 2, 2, 2\], got \[3, 2, 2, 3\]$"):
        _kernels.modal_coefficients(
            lam, V, V_inv, cond, ok, (A, B, C, E), (torch.zeros(3, 2, 2, 3, dtype=F64), dB, dC, dE), None, False,
            omega, 0, 12, (1e5, 1e3),
        )  # fmt: skip


@pytest.mark.parametrize("delta", [0.0, 1e-8, -1e-8, 1e-6, 1e-2])
def test_modal_outputs_hand_ill_conditioned_eigenvectors_to_the_recursion(delta):
    """Seat damped near critically (as above): the outputs alone stay accurate much closer to the
    double eigenvalue than the sensitivities, down to cond(V) = 1e4 (delta ~ 1e-7)."""
    from hybridqcm.estimation._expm import balance
    from hybridqcm.estimation._modal import modal_outputs

    model = SeatBaseExcitation()
    p2 = torch.tensor([400.0, 150.0], dtype=F64)
    p = torch.stack([2 * p2.sqrt() * (1 + delta), p2], 1)
    w = torch.randn(2, 120, 1, generator=torch.Generator().manual_seed(1), dtype=F64)
    x0 = _x0(2, 2, seed=4)
    old = exact_outputs(model, p, x0, w, H, method="recursion", start=8, n_steps=100)
    new = exact_outputs(model, p, x0, w, H, method="modal", start=8, n_steps=100)
    assert torch.isfinite(new).all() and _column_error(new, old) <= 1e-10
    A, B, C, E = model.matrices(p)
    fine = held_input(w, "spline", 4, 8, 100).permute(2, 1, 0)
    _, ok = modal_outputs((A, B, C, E), balance(A), x0, fine, w[:, 8:108], H, "spline")
    assert bool(ok.all()) == (abs(delta) > 1e-7)


@pytest.mark.parametrize("path", ["kernel", "torch"])
@pytest.mark.parametrize("hold", HOLDS)
@pytest.mark.parametrize("case", ["quarter", "seat", "sprung"])
def test_stacked_fallback_matches_the_step_recursion(case, hold, path, monkeypatch):
    """The modal path's fallback for a few samples (one block-diagonal product per step, or the compiled loop) is
    the batch-innermost step recursion in another order of operations."""
    from hybridqcm.estimation.exact import _recursion_sensitivities, _stacked_sensitivities

    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch" if path == "torch" else "")
    model, p, w = _random_case(case, 9, 60, seed=13)
    x0 = _x0(9, model.n_state, seed=6)
    for x, with_x0, start, n_steps in [(x0, True, 5, 50), (None, False, 0, 60), (x0, True, 7, 2), (None, True, 2, 1)]:
        held = held_input(w, hold, 3, start, n_steps)
        args = (model, p, x, w, H, hold, 3, with_x0, start, n_steps, held)
        old, new = _recursion_sensitivities(*args), _stacked_sensitivities(*args)
        assert new.shape == old.shape
        assert _column_error(new, old) <= 1e-12, (with_x0, start, n_steps)


def test_batched_matmul_matches_torch():
    """The numpy (OpenBLAS) products of the estimation layers: broadcast, transposed, conjugated and
    negated operands, and a strided output, as torch.matmul computes them."""
    from hybridqcm.estimation._blas import batched_matmul

    g = torch.Generator().manual_seed(3)
    a = torch.randn(5, 1, 4, 6, generator=g, dtype=F64)
    b = torch.randn(5, 3, 6, 2, generator=g, dtype=F64)
    torch.testing.assert_close(batched_matmul(a, b), a @ b, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(batched_matmul(b.transpose(-1, -2), b), b.transpose(-1, -2) @ b, rtol=1e-14, atol=1e-14)
    z = torch.randn(5, 4, 4, generator=g, dtype=torch.complex128)
    for view in (z.conj(), -z.conj(), z.transpose(1, 2)):
        torch.testing.assert_close(batched_matmul(view, z), view @ z, rtol=1e-14, atol=1e-14)
    buffer = torch.zeros(7, 5, 9, dtype=F64)  # time first; the product written batch first into columns 1..3
    c, d = torch.randn(5, 7, 6, generator=g, dtype=F64), torch.randn(5, 6, 3, generator=g, dtype=F64)
    batched_matmul(c, d, out=buffer[:, :, 1:4].transpose(0, 1))
    torch.testing.assert_close(buffer[:, :, 1:4].transpose(0, 1), c @ d, rtol=1e-14, atol=1e-14)
    assert not buffer[:, :, 0].any() and not buffer[:, :, 4:].any()


@pytest.mark.parametrize("by_torch", [False, True])
def test_the_gram_matrix_by_either_library_is_the_sum_of_outer_products(by_torch, monkeypatch):
    """_blas.gram_matrix by numpy's per-sample products or by one torch GEMM (the library is chosen by the CPU's
    maker): aᵀa of a contiguous [b, r, w] equals the sum over rows of the outer products (float64 einsum of a
    different contraction order), symmetric, and the numpy path dispatches no torch product."""
    from hybridqcm.estimation import _blas

    monkeypatch.setattr(_blas, "_GRAM_BY_TORCH", by_torch)
    g = torch.Generator().manual_seed(8)
    a = torch.randn(9, 300, 17, generator=g, dtype=F64)
    expected = sum(torch.einsum("bi,bj->bij", a[:, r], a[:, r]) for r in range(300))
    if not by_torch:
        monkeypatch.setattr(torch, "matmul", lambda *args, **kw: (_ for _ in ()).throw(AssertionError("torch")))
    gram = _blas.gram_matrix(a)
    monkeypatch.undo()
    torch.testing.assert_close(gram, expected, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(gram, gram.transpose(1, 2), rtol=0, atol=1e-12)


def test_unknown_method_raises(samples):
    model, p, w = _model_case("quarter", samples)
    with pytest.raises(ValueError, match="unknown method 'fast'"):
        exact_sensitivities(model, p, None, w, H, method="fast")
    with pytest.raises(ValueError, match="unknown method 'fast'"):
        exact_outputs(model, p, None, w, H, method="fast")


def test_prepared_inputs_give_the_same_outputs_and_jacobian_per_chunk():
    """A solver holds the input of a window once (ResponseModel.prepare) and evaluates chunks of samples
    from it: the numbers equal those computed from the raw inputs of the same samples."""
    from hybridqcm.estimation.response import base_excitation_response

    model, p, w = _random_case("seat", 24, 160, seed=5)
    theta = torch.cat([p, _x0(24, 2, seed=6)], 1)
    chunk = torch.tensor([3, 17, 0, 9])
    for hold in HOLDS:
        response = base_excitation_response("seat", H, hold=hold)
        prepared = response.prepare(w, 10, 120)
        m_sub = 4 if hold == "spline" else 1
        assert prepared.held.shape == (m_sub + 119 * m_sub + 1, 1, 24)
        for call in (response.outputs, response.sensitivities):
            from_raw = call(theta[chunk], w[chunk], 10, 120)
            assert _column_error(call(theta[chunk], prepared[chunk], 10, 120), from_raw) <= 1e-13
        with pytest.raises(ValueError, match="prepared for the window start=10, n_steps=120"):
            response.outputs(theta, prepared, 10, 100)


class _TwoInputSeat(LinearModel):
    """The seat driven by two measured inputs (the second through half the gain): a multi-input model
    for the layouts of the held input."""

    name = "seat2"
    param_names = SeatBaseExcitation.param_names
    state_names = SeatBaseExcitation.state_names
    input_names = ("w1", "w2")
    output_names = SeatBaseExcitation.output_names

    def matrices(self, p):
        A, B, C, E = SeatBaseExcitation().matrices(p)
        return A, torch.cat([B, 0.5 * B], -1), C, torch.cat([E, 0.5 * E], -1)


@pytest.mark.parametrize("case", ["seat", "sprung", "two_inputs"])
def test_outputs_from_a_batch_first_held_input_equal_the_time_first_ones(case):
    """exact_outputs reads a held input stored batch first (PreparedInputs) by its own forcing path:
    the same outputs as from the time-first held input and as from the raw samples, every hold."""
    model, p, w = _random_case("sprung" if case == "sprung" else "seat", 20, 150, seed=7)
    if case == "two_inputs":
        model = _TwoInputSeat()
        w = torch.cat([w, torch.randn(w.shape, generator=torch.Generator().manual_seed(8), dtype=F64)], -1)
    x0 = _x0(20, model.n_state, seed=9)
    for hold in HOLDS:
        held = held_input(w, hold, 4, 6, 130)
        batch_first = held.permute(2, 1, 0).contiguous().permute(2, 1, 0)
        assert batch_first.stride(2) != 1  # the other layout indeed
        raw = exact_outputs(model, p, x0, w, H, hold, 4, start=6, n_steps=130)
        for given in (held, batch_first):
            out = exact_outputs(model, p, x0, w, H, hold, 4, start=6, n_steps=130, held=given)
            assert _column_error(out, raw) <= 1e-13


def test_an_eigen_decomposition_that_fails_to_converge_is_one_not_ok_sample(monkeypatch):
    """LAPACK raises for the whole batch when one matrix's QR iteration fails (seen on trial steps): the others keep
    their decomposition, that one is not ok (the step recursion takes it)."""
    import numpy as np

    from hybridqcm.estimation import _modal

    real_eig = np.linalg.eig
    sentinel = 12345.0

    def eig(M):
        if bool((M[..., 0, 0] == sentinel).any()):
            raise np.linalg.LinAlgError("Eigenvalues did not converge")
        return real_eig(M)

    A = torch.randn(3, 4, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    scale = torch.ones(3, 4, dtype=torch.float64)
    lam_all, *_ = _modal._eigen(A, scale)
    A[1, 0, 0] = sentinel
    monkeypatch.setattr(_modal.np.linalg, "eig", eig)
    lam, V, V_inv, cond, ok = _modal._eigen(A, scale)
    assert ok.tolist() == [True, False, True]
    torch.testing.assert_close(lam[[0, 2]], lam_all[[0, 2]])
    torch.testing.assert_close(V[[0, 2]] @ torch.diag_embed(lam[[0, 2]]) @ V_inv[[0, 2]], A[[0, 2]].to(lam.dtype))


# A line search's trial matrix (body1 + seat, log-space step) on which MKL's dgeev, through torch.linalg.eig,
# fails to converge and corrupts the heap: a loop of torch.linalg.eig on it aborted the process within 20 calls
# (`double free or corruption`), as qcm-estimate did on data/persons/body1_n5.h5's block 5 in about half its runs.
_HEAP_BREAKER = [
    ["-0x1.13f584f7794c2p+573", "0x1.ad6c71afd888cp+244", "-0x1.1e431906c8eb0p-12", "0x1.6e06f7c33ab58p+125"],
    ["0x1.13f584f7794c2p+334", "-0x1.2ed8478a1f184p+6", "0x1.1e431906c8eb0p-251", "-0x1.0222ac91385a1p-113"],
    ["0x1.0000000000000p+25", "0x0.0p+0", "0x0.0p+0", "0x0.0p+0"],
    ["0x0.0p+0", "0x1.0000000000000p+125", "0x0.0p+0", "0x0.0p+0"],
]


def test_the_modal_eigen_decomposition_survives_the_matrix_that_broke_mkl_geev():
    """_eig on that matrix, 200 times with allocations between, in a child process (a corrupted heap would take
    pytest with it): the child exits cleanly, and the dominant eigenvalue, the one double precision can resolve
    next to it (backward error ~ eps x 1e172), is mpmath's at 400 digits."""
    import subprocess
    import sys
    import textwrap

    import mpmath

    code = textwrap.dedent(
        f"""
        import torch
        from hybridqcm.estimation._modal import _eig
        M = torch.tensor([[float.fromhex(x) for x in row] for row in {_HEAP_BREAKER!r}], dtype=torch.float64)[None]
        for _ in range(200):
            lam, V, ok = _eig(M)
            junk = [torch.randn(64, 64) for _ in range(20)]
        print(*[f"{{z.real!r}} {{z.imag!r}}" for z in lam[0].tolist()])
        """
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-500:]
    words = [float(w) for w in run.stdout.split()]
    lam = np.array([complex(words[2 * i], words[2 * i + 1]) for i in range(4)])
    with mpmath.workdps(400):
        exact, _ = mpmath.eig(mpmath.matrix([[float.fromhex(x) for x in row] for row in _HEAP_BREAKER]))
        dominant = complex(max(exact, key=abs))
    assert abs(lam[np.argmax(np.abs(lam))] - dominant) <= 1e-12 * abs(dominant)
