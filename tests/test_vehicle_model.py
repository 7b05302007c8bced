"""The half car and the full car (issue 30): the equations of motion against independent derivations.

* sympy derives the equations from T, V and the Rayleigh function U (Lagrange), the module assembles
  them from spring-damper elements: the matrices must agree, and the half car's pitch row must be the
  corrected one of SPEC § 10;
* every stored sample of a simulated file satisfies Newton's and Euler's laws written body by body
  here (forces of each spring and damper, moments about the centre of mass), not the module's matrices;
* the half car whose pitch inertia decouples the axles (I = m2 l_f l_b) is two quarter cars, simulated
  by the quarter car's own simulator (physics/continuous.py);
* the symmetric full car on identical left and right roads is the half car (half its masses);
* without dampers the energy T + V changes exactly by the road's work.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hybridqcm.physics.sedan import place_source_seats, reference_physical, seat
from hybridqcm.physics.two_track_road import TwoTrackRoad
from hybridqcm.physics.vehicle_geometry import Seat, VehicleLayout, columns, physical_problems
from hybridqcm.physics.vehicle_model import VehicleModel, vehicle_matrices
from hybridqcm.physics.vehicle_response import linear_response

HALF = VehicleLayout("half_car")
FULL = VehicleLayout("full_car")
FULL_TWO_SEATS_DAMPED = VehicleLayout("full_car", (seat("driver"), seat("source")), tyre_damping=True)


def _perturbed(layout: VehicleLayout, seed: int = 0, n: int = 1) -> torch.Tensor:
    """Physical parameters [n, P]: the sedan with every value moved by up to ±20 % (seats kept on the body)."""
    generator = torch.Generator().manual_seed(seed)
    base = reference_physical(layout)[None].expand(n, -1)
    factor = 1 + 0.2 * (2 * torch.rand(base.shape, generator=generator, dtype=torch.float64) - 1)
    out = base * factor
    return place_source_seats(layout, out)


# --------------------------------------------------------------------------------------- sympy
def _sympy_matrices(layout: VehicleLayout):
    """(M, C, K, F, G, symbols) by Lagrange's equations from T, V, U written with sympy."""
    import sympy as sp

    t = sp.symbols("t")
    names = layout.param_names
    p = {n: sp.Symbol(n) for n in names}
    q = [sp.Function(d)(t) for d in layout.dofs]
    u = [sp.Function(f"u{w}")(t) for w in layout.wheels]
    dof = dict(zip(layout.dofs, q))
    z2, pitch = dof["z2"], dof["pitch"]
    roll = dof.get("roll", 0)

    def point(x, y):
        return z2 + x * pitch + y * roll

    place = {"f": (p["l_f"], 0), "b": (-p["l_b"], 0)}
    if layout.full:
        place = {
            "fl": (p["l_f"], -p["w_l"]),
            "fr": (p["l_f"], p["w_r"]),
            "bl": (-p["l_b"], -p["w_l"]),
            "br": (-p["l_b"], p["w_r"]),
        }
    T = V = U = 0
    for s in layout.seat_names:
        z3 = dof[f"z3{layout.suffix(s)}"]
        x, y = p[layout.seat_param("x_s", s)], (p[layout.seat_param("y_s", s)] if layout.full else 0)
        stretch = z3 - point(x, y)
        T += p[layout.seat_param("m3", s)] * sp.diff(z3, t) ** 2 / 2
        V += p[layout.seat_param("k3", s)] * stretch**2 / 2
        U += p[layout.seat_param("c3", s)] * sp.diff(stretch, t) ** 2 / 2
    T += p["m2"] * sp.diff(z2, t) ** 2 / 2 + p["I_pitch"] * sp.diff(pitch, t) ** 2 / 2
    if layout.full:
        T += p["I_roll"] * sp.diff(roll, t) ** 2 / 2
    for w, road in zip(layout.wheels, u):
        z1 = dof[f"z1{w}"]
        suspension = point(*place[w]) - z1
        tyre = z1 - road
        T += p[f"m1{w}"] * sp.diff(z1, t) ** 2 / 2
        V += p[f"k2{w}"] * suspension**2 / 2 + p[f"k1{w}"] * tyre**2 / 2
        U += p[f"c2{w}"] * sp.diff(suspension, t) ** 2 / 2 + p[f"c1{w}"] * sp.diff(tyre, t) ** 2 / 2
    # Lagrange: d/dt dT/dq' - dT/dq + dU/dq' + dV/dq = 0, one row per coordinate
    rows = [
        sp.expand(sp.diff(sp.diff(T, sp.diff(c, t)), t) - sp.diff(T, c) + sp.diff(U, sp.diff(c, t)) + sp.diff(V, c))
        for c in q
    ]
    # plain symbols for q'', q', q, u', u to read the coefficients off
    n = len(q)
    acc = sp.symbols(f"A0:{n}")
    vel = sp.symbols(f"V0:{n}")
    pos = sp.symbols(f"Q0:{n}")
    uu = sp.symbols(f"U0:{len(u)}")
    ud = sp.symbols(f"D0:{len(u)}")
    subs = {}
    for i, c in enumerate(q):
        subs[sp.diff(c, t, 2)] = acc[i]
    for i, c in enumerate(q):
        subs[sp.diff(c, t)] = vel[i]
    for j, r in enumerate(u):
        subs[sp.diff(r, t)] = ud[j]
    rows = [r.subs(subs) for r in rows]
    subs2 = {c: pos[i] for i, c in enumerate(q)}
    subs2.update({r: uu[j] for j, r in enumerate(u)})
    rows = [r.subs(subs2) for r in rows]
    M = sp.Matrix(n, n, lambda i, j: sp.diff(rows[i], acc[j]))
    C = sp.Matrix(n, n, lambda i, j: sp.diff(rows[i], vel[j]))
    K = sp.Matrix(n, n, lambda i, j: sp.diff(rows[i], pos[j]))
    F = sp.Matrix(n, len(u), lambda i, j: -sp.diff(rows[i], uu[j]))
    G = sp.Matrix(n, len(u), lambda i, j: -sp.diff(rows[i], ud[j]))
    # the rows are linear: nothing is left once the coefficients are taken out
    for i, r in enumerate(rows):
        rest = r - sum(M[i, j] * acc[j] + C[i, j] * vel[j] + K[i, j] * pos[j] for j in range(n))
        rest += sum(F[i, j] * uu[j] + G[i, j] * ud[j] for j in range(len(u)))
        assert sp.simplify(rest) == 0
    return M, C, K, F, G, p


@pytest.mark.parametrize("layout", [HALF, FULL, FULL_TWO_SEATS_DAMPED], ids=["half", "full", "full_2seats_damped"])
def test_matrices_are_lagrange_equations_of_the_energies(layout):
    """The module's M, C, K, F, G equal sympy's Lagrange equations of T, V, U at random parameters."""
    import sympy as sp

    symbolic = _sympy_matrices(layout)
    physical = _perturbed(layout, seed=3)
    values = {symbolic[5][n]: float(v) for n, v in zip(layout.param_names, physical[0])}
    ours = vehicle_matrices(layout, physical)
    for name, theirs, mine in zip("MCKFG", symbolic[:5], ours):
        expected = np.array(sp.Matrix(theirs).subs(values).evalf(), dtype=float)
        np.testing.assert_allclose(
            mine[0].numpy(), expected, rtol=1e-12, atol=1e-9 * np.abs(expected).max(), err_msg=name
        )


def test_half_car_pitch_row_is_the_corrected_one():
    """SPEC § 10: with the seat at x_s = -L_b, the pitch row's α̇ coefficient (on the right-hand side) is
    -(L_b² (C3 + C2b) + L_f² C2f) and its α coefficient -(L_b² (K3 + K2b) + L_f² K2f), not the source's print."""
    import sympy as sp

    M, C, K, F, G, p = _sympy_matrices(HALF)
    i = HALF.angle_dof("pitch")
    at_back = {p["x_s"]: -p["l_b"]}
    lf, lb = p["l_f"], p["l_b"]
    assert sp.simplify(-C[i, i].subs(at_back) + (lb**2 * (p["c3"] + p["c2b"]) + lf**2 * p["c2f"])) == 0
    assert sp.simplify(-K[i, i].subs(at_back) + (lb**2 * (p["k3"] + p["k2b"]) + lf**2 * p["k2f"])) == 0
    # the source's misprint differs
    printed = lb**2 * (p["c3"] - p["c2b"]) - lf**2 * p["c2f"]
    assert sp.simplify(-C[i, i].subs(at_back) - printed) != 0


# --------------------------------------------------------------------------------------- stored samples
def _newton_residual(layout: VehicleLayout, physical, accel, vel, disp, road, road_vel=None):
    """Newton's law per body, Euler's per angle, from each element's force — written out here.
    Returns residual / mass [M, T, n_dof] (units of acceleration)."""
    d = {name: i for i, name in enumerate(layout.dofs)}
    P = dict(zip(layout.param_names, physical.T))  # each [M]
    z2, th = disp[..., d["z2"]], disp[..., d["pitch"]]
    v2, om = vel[..., d["z2"]], vel[..., d["pitch"]]
    ph = disp[..., d["roll"]] if layout.full else 0 * z2
    w_ph = vel[..., d["roll"]] if layout.full else 0 * z2
    force = {name: np.zeros_like(z2) for name in layout.dofs}  # generalised forces on each coordinate

    def on_body(f, x, y):  # a vertical force f acting up on the body at (x, y)
        force["z2"] += f
        force["pitch"] += f * x
        if layout.full:
            force["roll"] += f * y

    for s in layout.seat_names:
        key = f"z3{layout.suffix(s)}"
        x = P[layout.seat_param("x_s", s)][:, None]
        y = P[layout.seat_param("y_s", s)][:, None] if layout.full else 0
        stretch = disp[..., d[key]] - (z2 + x * th + y * ph)
        rate = vel[..., d[key]] - (v2 + x * om + y * w_ph)
        f = -P[layout.seat_param("k3", s)][:, None] * stretch - P[layout.seat_param("c3", s)][:, None] * rate
        force[key] += f  # on the seat
        on_body(-f, x, y)  # reaction on the body
    for j, w in enumerate(layout.wheels):
        x = P["l_f"][:, None] if w.startswith("f") else -P["l_b"][:, None]
        y = 0 if not layout.full else (P["w_r"][:, None] if w.endswith("r") else -P["w_l"][:, None])
        key = f"z1{w}"
        stretch = (z2 + x * th + y * ph) - disp[..., d[key]]
        rate = (v2 + x * om + y * w_ph) - vel[..., d[key]]
        f = P[f"k2{w}"][:, None] * stretch + P[f"c2{w}"][:, None] * rate  # pulls the wheel up, the body down
        force[key] += f
        on_body(-f, x, y)
        tyre = -P[f"k1{w}"][:, None] * (disp[..., d[key]] - road[..., j])
        if road_vel is not None:
            tyre = tyre - P[f"c1{w}"][:, None] * (vel[..., d[key]] - road_vel[..., j])
        force[key] += tyre
    mass = {f"z3{layout.suffix(s)}": P[layout.seat_param("m3", s)] for s in layout.seat_names}
    mass.update({"z2": P["m2"], "pitch": P["I_pitch"], **{f"z1{w}": P[f"m1{w}"] for w in layout.wheels}})
    if layout.full:
        mass["roll"] = P["I_roll"]
    return np.stack([accel[..., d[n]] - force[n] / mass[n][:, None] for n in layout.dofs], -1)


@pytest.mark.parametrize(
    "layout",
    [HALF, VehicleLayout("full_car", (seat("driver"), seat("passenger"), seat("source")), tyre_damping=True)],
    ids=["half", "full_3seats_damped"],
)
def test_every_stored_sample_satisfies_the_equations_of_motion(tmp_path, layout):
    """Target: |residual| <= 1e-6 of each degree of freedom's RMS acceleration at every stored sample."""
    from hybridqcm.data.hdf5 import read_split
    from hybridqcm.data.vehicle_simulate import write_vehicle_dataset
    from hybridqcm.physics.vehicle_prior import VehiclePrior

    path = tmp_path / "v.h5"
    write_vehicle_dataset(
        path,
        {"test": {"profiles": {"A": 1, "C": 1}}},
        VehiclePrior(layout),
        TwoTrackRoad(),
        256,
        0.01,
        30 / 3.6,
        3,
        5,
        progress=False,
    )
    keys = ("accel", "vel", "disp", "road", "physical") + (("road_vel",) if layout.tyre_damping else ())
    a = read_split(path, "test", keys)
    residual = _newton_residual(
        layout, a["physical"], a["accel"].astype(np.float64), a["vel"], a["disp"], a["road"], a.get("road_vel")
    )
    rms = np.sqrt((a["accel"].astype(np.float64) ** 2).mean(1, keepdims=True))
    worst = float((np.abs(residual) / rms).max())
    assert worst <= 1e-6, worst


# --------------------------------------------------------------------------------------- reductions
def _sum_of_sines(n_rec: int, seed: int):
    road = TwoTrackRoad()
    draw = road.draw(torch.tensor([1] * n_rec), torch.Generator().manual_seed(seed))
    return road, draw


def test_half_car_with_decoupling_pitch_inertia_is_two_quarter_cars():
    """I_pitch = m2 l_f l_b: the body's front and back points move as point masses m2 l_b/L and m2 l_f/L,
    so the source's half car (seat at the back) is a front quarter car without a seat and a back quarter
    car with it — each simulated by physics/continuous.py, to 1e-10 of the signals' RMS."""
    from hybridqcm.physics.continuous import simulate_continuous

    physical = _perturbed(HALF, seed=5, n=2)
    P = columns(HALF.param_names, physical)
    L = P["l_f"] + P["l_b"]
    physical[:, HALF.param_names.index("I_pitch")] = P["m2"] * P["l_f"] * P["l_b"]
    P = columns(HALF.param_names, physical)
    speed, n_steps, h, warmup = 30 / 3.6, 300, 0.01, torch.tensor([3.0, 7.5])
    road, draw = _sum_of_sines(2, 11)
    z = road.wheel_amplitudes(draw, HALF.wheels, speed, L, torch.zeros(2))
    model = VehicleModel(HALF)
    A, B, C, E = model.matrices(model.model_params(physical))
    out = linear_response(A, B, z, road.omega * speed, n_steps, h, warmup)
    x = out.states
    accel = x @ C.transpose(1, 2) + out.inputs @ E.transpose(1, 2)
    d = {name: i for i, name in enumerate(HALF.dofs)}
    n = HALF.n_dof

    def quarter(m3, c3, k3, m2, c2, k2, m1, k1):
        zero = torch.zeros_like(m2)
        p1, p2 = (c3 / m3, k3 / m3) if m3 is not None else (zero, zero)
        return torch.stack([p1, p2, c3 / m2, c2 / m2, k3 / m2, k2 / m2, c2 / m1, c2 / m1, k2 / m1, (k2 + k1) / m1], -1)

    zero = torch.zeros(2, dtype=torch.float64)
    front = quarter(None, zero, zero, P["m2"] * P["l_b"] / L, P["c2f"], P["k2f"], P["m1f"], P["k1f"])
    back = quarter(P["m3"], P["c3"], P["k3"], P["m2"] * P["l_f"] / L, P["c2b"], P["k2b"], P["m1b"], P["k1b"])
    omega_t = road.omega * speed
    delay = omega_t[None, :] * (L / speed)[:, None]
    qf = simulate_continuous(front, draw.amplitude, draw.phase_left, omega_t, n_steps, h, warmup)
    qb = simulate_continuous(back, draw.amplitude, draw.phase_left + delay, omega_t, n_steps, h, warmup)
    lf, lb = P["l_f"][:, None], P["l_b"][:, None]
    pairs = [
        (x[..., n + d["z2"]] + lf * x[..., n + d["pitch"]], qf.disp[..., 1]),
        (x[..., n + d["z1f"]], qf.disp[..., 2]),
        (x[..., n + d["z2"]] - lb * x[..., n + d["pitch"]], qb.disp[..., 1]),
        (x[..., n + d["z3"]], qb.disp[..., 0]),
        (x[..., n + d["z1b"]], qb.disp[..., 2]),
        (accel[..., d["z2"]] + lf * accel[..., d["pitch"]], qf.accel[..., 1]),
        (accel[..., d["z1f"]], qf.accel[..., 2]),
        (accel[..., d["z3"]], qb.accel[..., 0]),
        (accel[..., d["z2"]] - lb * accel[..., d["pitch"]], qb.accel[..., 1]),
        (accel[..., d["z1b"]], qb.accel[..., 2]),
    ]
    for ours, theirs in pairs:
        scale = theirs.square().mean(1, keepdim=True).sqrt()
        assert float(((ours - theirs).abs() / scale).max()) < 1e-10
    # and the other inertia couples them: the same comparison fails by orders of magnitude
    assert float((qf.accel[..., 1]).abs().max()) > 0


def test_symmetric_full_car_on_identical_tracks_is_the_half_car():
    """Left = right (wheels, half-tracks) with the seat on the centre line, both tracks the same profile:
    no roll, left wheels = right wheels, and z3, z2, pitch, z1f, z1b those of the half car with half the
    body (m2, I_pitch, the seat's m3, k3, c3 halved)."""
    full_layout = VehicleLayout("full_car", (Seat("centre", -0.6, 0.0),))
    half_layout = VehicleLayout("half_car", (Seat("centre", -0.6),))
    half = _perturbed(half_layout, seed=9)[0]
    H = dict(zip(half_layout.param_names, half.tolist()))
    values = {
        "m2": 2 * H["m2"],
        "I_pitch": 2 * H["I_pitch"],
        "I_roll": 480.0,
        "m3": 2 * H["m3"],
        "k3": 2 * H["k3"],
        "c3": 2 * H["c3"],
        "l_f": H["l_f"],
        "l_b": H["l_b"],
        "w_l": 0.8,
        "w_r": 0.8,
        "x_s": H["x_s"],
        "y_s": 0.0,
    }
    for w in full_layout.wheels:
        for base in ("m1", "k1", "c1", "k2", "c2"):
            values[f"{base}{w}"] = H[f"{base}{w[0]}"]
    full = torch.tensor([[values[n] for n in full_layout.param_names]], dtype=torch.float64)
    speed, n_steps, h = 30 / 3.6, 200, 0.01
    road = TwoTrackRoad(coherence="identical")
    draw = road.draw(torch.tensor([2]), torch.Generator().manual_seed(4))
    results = {}
    for layout, physical in ((full_layout, full), (half_layout, half[None])):
        P = columns(layout.param_names, physical)
        z = road.wheel_amplitudes(draw, layout.wheels, speed, P["l_f"] + P["l_b"], torch.full((1,), 1.6))
        model = VehicleModel(layout)
        A, B, C, E = model.matrices(model.model_params(physical))
        out = linear_response(A, B, z, road.omega * speed, n_steps, h, torch.tensor([4.0]))
        results[layout.kind] = (out.states @ C.transpose(1, 2) + out.inputs @ E.transpose(1, 2))[0]
    fa, ha = results["full_car"], results["half_car"]
    fd = {n: i for i, n in enumerate(full_layout.dofs)}
    hd = {n: i for i, n in enumerate(half_layout.dofs)}
    scale = ha.square().mean(0).sqrt()
    for full_name, half_name in [
        ("z3", "z3"),
        ("z2", "z2"),
        ("pitch", "pitch"),
        ("z1fl", "z1f"),
        ("z1fr", "z1f"),
        ("z1bl", "z1b"),
        ("z1br", "z1b"),
    ]:
        k = hd[half_name]
        assert float((fa[:, fd[full_name]] - ha[:, k]).abs().max() / scale[k]) < 1e-10, full_name
    assert float(fa[:, fd["roll"]].abs().max()) < 1e-10 * float(scale[hd["pitch"]])


def test_undamped_energy_changes_by_the_roads_work():
    """No dampers: T + V (V with the tyre springs' ½ k1 (z1 - u)²) is constant in free vibration (to 1e-10
    over 2 s), and on a road it changes by the road's work ∫ Σ_w k1w (u_w - z1w) u̇_w dt (to 1e-7 of the
    energy, Simpson on a 0.2 ms grid): the inertia, stiffness and input matrices are one conservative
    system."""
    layout = VehicleLayout("full_car", (seat("driver"), seat("rear_right")))
    physical = _perturbed(layout, seed=2)
    names = layout.param_names
    for j, n in enumerate(names):
        if n.startswith(("c2", "c3", "c1")):
            physical[0, j] = 0.0
    M, C, K, F, G = (m[0] for m in vehicle_matrices(layout, physical))
    model = VehicleModel(layout)
    A, B, _, _ = model.matrices(model.model_params(physical))
    n = layout.n_dof
    x0 = torch.randn(2 * n, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 1e-2
    k1 = torch.diag(F.T @ F).sqrt()  # tyre stiffness per wheel (F holds k1w in the wheel's row)

    def energy(x, u):
        v, q = x[..., :n], x[..., n:]
        kinetic = 0.5 * (v @ M * v).sum(-1)
        tyre_free = 0.5 * (q @ K * q).sum(-1)  # includes the tyres' ½ k1 z1²
        coupling = -(q @ F * u).sum(-1) + 0.5 * (k1 * u * u).sum(-1)  # ... - k1 z1 u + ½ k1 u²
        return kinetic + tyre_free + coupling

    times = torch.linspace(0, 2.0, 401, dtype=torch.float64)
    free = torch.stack([torch.linalg.matrix_exp(A[0] * t) @ x0 for t in times])
    e = energy(free, torch.zeros(len(times), len(layout.wheels), dtype=torch.float64))
    assert float((e - e[0]).abs().max() / e[0]) < 1e-10  # matrix_exp round-off over 2 s
    road, draw = _sum_of_sines(1, 3)
    speed, h = 30 / 3.6, 2e-4
    P = columns(names, physical)
    z = road.wheel_amplitudes(draw, layout.wheels, speed, P["l_f"] + P["l_b"], P["w_l"] + P["w_r"])
    omega_t = road.omega * speed
    out = linear_response(A, B, torch.cat([z]), omega_t, 10001, h, torch.tensor([1.0]))
    dz = torch.stack([(1j * omega_t * z[0, w]) for w in range(len(layout.wheels))])
    from hybridqcm.physics.continuous import time_basis

    basis = time_basis(omega_t, 10001, h)
    shift = torch.polar(torch.ones_like(omega_t), omega_t * 1.0)
    road_vel = (torch.view_as_real(dz * shift).reshape(len(layout.wheels), -1) @ basis).T  # [T, n_w]
    x, u = out.states[0], out.inputs[0]
    # E's road terms are -qᵀF u + ½ k1 u²; with M q̈ + K q = F u, dE/dt = (k1 u - Fᵀq) · u̇
    power = ((k1 * u - x[:, n:] @ F) * road_vel).sum(-1)
    # Simpson's rule on pairs of steps (the road reaches 25 Hz: the trapezoid's error would be ~1e-5)
    pieces = h / 3 * (power[0:-2:2] + 4 * power[1:-1:2] + power[2::2])
    work = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(pieces, 0)])
    e = energy(x, u)[::2]
    scale = e.abs().max()
    assert float(((e - e[0]) - work).abs().max() / scale) < 1e-7


def test_layout_names_and_bad_parameters():
    assert HALF.dofs == ("z3", "z2", "z1f", "z1b", "pitch")
    assert FULL.dofs == ("z3", "z2", "z1fl", "z1fr", "z1bl", "z1br", "pitch", "roll")
    two = VehicleLayout("full_car", (seat("driver"), seat("rear_left")))
    assert two.dofs[:2] == ("z3_driver", "z3_rear_left")
    assert "m3_driver" in two.param_names and "x_s_rear_left" in two.param_names and "m3" not in two.param_names
    assert FULL.model_param_names == tuple(n for n in FULL.param_names if not n.startswith("c1"))
    good = reference_physical(FULL)[None]
    assert physical_problems(FULL, good) == []
    bad = good.clone()
    bad[0, FULL.param_names.index("I_pitch")] = -5.0
    assert "(I_pitch) = -5.0: an inertia must be > 0" in physical_problems(FULL, bad)[0]
    outside = good.clone()
    outside[0, FULL.param_names.index("x_s")] = 3.0
    message = physical_problems(FULL, outside)[0]
    assert "seat 'source'" in message and "outside the chassis" in message
    with pytest.raises(ValueError, match="seat names must be unique"):
        VehicleLayout("full_car", (seat("driver"), seat("driver")))
    with pytest.raises(ValueError, match="vehicle='boat'"):
        VehicleLayout("boat")


def test_analytic_derivatives_match_forward_mode():
    from hybridqcm.physics.linear_models import LinearModel

    for layout in (HALF, FULL_TWO_SEATS_DAMPED):
        model = VehicleModel(layout)
        p = model.model_params(_perturbed(layout, seed=7, n=3))
        ours = model.matrix_derivatives(p)
        reference = LinearModel.matrix_derivatives(model, p)  # torch.func.jacfwd of matrices()
        for a, b in zip(ours, reference):
            assert float((a - b).abs().max()) <= 1e-12 * float(b.abs().max())


def test_prior_draws_are_vehicles_around_the_sedan():
    from hybridqcm.physics.vehicle_prior import VehiclePrior

    layout = VehicleLayout("full_car", (seat("driver"), seat("source")))
    draw = VehiclePrior(layout).sample(400, torch.Generator().manual_seed(0))
    physical = draw.params
    assert physical.shape == (400, len(layout.param_names)) and draw.n_drawn == 400
    assert physical_problems(layout, physical) == []
    P = columns(layout.param_names, physical)
    assert 30 <= float(P["m3_driver"].min()) and float(P["m3_driver"].max()) <= 150
    torch.testing.assert_close(P["x_s_source"], -P["l_b"])  # the source's seat follows its wheel
    torch.testing.assert_close(P["y_s_source"], -P["w_l"])
    ratio = P["k2fl"] / reference_physical(layout)[layout.param_names.index("k2fl")]
    assert abs(float(ratio.log().std()) - 0.1) < 0.02
    assert bool((P["k3_driver"] == 98935.0).all())  # the seat's specification


def test_two_track_coherence():
    """γ(Ω) = Ω B K1(Ω B) (isotropic road, waviness 2): 1 for long waves, small for short, and the drawn
    tracks show it: their cross-spectrum over the power at each wave, averaged over many draws."""
    road = TwoTrackRoad()
    gamma = road.coherence(torch.tensor([1.5]))[0]
    assert float(gamma[0]) > 0.98 and float(gamma[-1]) < 1e-8
    x = 2.0
    width = torch.tensor([x / float(road.omega[500])], dtype=torch.float64)
    assert float(road.coherence(width)[0, 500]) == pytest.approx(
        x * 0.13986588181652243, rel=1e-10
    )  # K1(2) = 0.1398658818...
    draw = road.draw(torch.zeros(4000, dtype=torch.long), torch.Generator().manual_seed(0))
    z = road.wheel_amplitudes(draw, ("fl", "fr"), 30 / 3.6, torch.full((4000,), 2.7), torch.full((4000,), 1.5))
    cross = (z[:, 0] * z[:, 1].conj()).real.mean(0) / (z[:, 0].abs().square().mean(0))
    wave = [10, 100, 300]
    np.testing.assert_allclose(cross[wave].numpy(), gamma[wave].numpy(), atol=0.05)
    # the rear wheel is the front one delayed by wheelbase / speed
    z = road.wheel_amplitudes(draw[:1], ("fl", "bl"), 10.0, torch.tensor([2.5]), torch.tensor([1.5]))
    torch.testing.assert_close(
        z[0, 1], z[0, 0] * torch.polar(torch.ones(1000, dtype=torch.float64), -road.omega * 10.0 * 0.25)
    )


def test_stability_and_modes_of_the_sedan():
    """Ride near 1.2-1.4 Hz, wheel hop near 12 Hz, seat near 6 Hz: the sedan of physics/sedan.py."""
    model = VehicleModel(FULL)
    A, _, _, _ = model.matrices(model.model_params(reference_physical(FULL)[None]))
    lam = torch.linalg.eigvals(A[0])
    assert float(lam.real.max()) < 0
    hz = sorted(float(v) / (2 * math.pi) for v in lam.abs()[lam.imag > 0])
    assert 1.0 < hz[0] < 1.4 and 5.5 < hz[3] < 7 and 11 < hz[-1] < 13.5
