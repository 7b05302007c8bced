"""Recordings from a simulator that is not ours: the estimator's check against physics, not our generator.

    .venv/bin/python bench/foreign_sim.py make --out data/foreign.h5 --n 300 [--noise 0.05 --bias 0.2]
    .venv/bin/python bench/foreign_sim.py make --out data/foreign.csv --n 1 --steps 6000   (one drive, qcm-import)
    .venv/bin/python bench/foreign_sim.py make --out data/persons.h5 --n 400 --occupant mixed --delay-ms-range -20 20
    .venv/bin/python bench/foreign_sim.py score RUN_DIR [--data data/foreign.h5] [--json score.json]
    .venv/bin/python bench/foreign_sim.py drives --out data/drives --n 300 [--stop-s 10 --change | --two-files]
    .venv/bin/python bench/foreign_sim.py score-drives RUN_DIR --truth data/drives/truth.json   (aggregate=drive)

Deliberately shares no code with `hybridqcm` (numpy, scipy and h5py only) and differs from
`physics/continuous.py` wherever a real car's simulator could:

* vehicle: physical constants (m1, m2, C2, K2, K1 ±10 %, occupant m3 ~ U(30, 150) kg, optionally the
  seat's C3, K3 and a tyre damper C1 acting on the wheel-road *relative* velocity), Newton's law
  written out per body, not the p-matrices;
* road: ISO 8608 (displacement PSD G_d(n0) = 16e-6 · 4^class m³ at n0 = 0.1 cycles/m, waviness 2)
  synthesised by an inverse FFT on a fine spatial grid over ISO's band [0.011, 2.83] cycles/m,
  linear between grid points (our generator: 1 000 equally spaced sines in angular frequency);
* time stepping: first-order hold on a fine step (h / sub) from one matrix exponential per vehicle
  (scipy's expm of the Van Loan block) — exact for that piecewise-linear road; batched over vehicles;
* every drive starts at rest at t = 0 on the road as it is, and the logger's window starts after a
  warm-up drawn per recording;
* logger: accelerations from the bodies' forces at t_k = t0 + k h, additive white noise of a given
  fraction of each channel's RMS and a constant bias per channel, any rate h;
* occupant (`--occupant`): `rigid` (the default) is one mass m3 ~ U(30, 150) kg on the seat's K3, C3, seat
  included, exactly as before these options existed (same random stream, byte-identical files). Otherwise
  the seat pan m_pan ~ U(3, 12) kg (rigid) sits on K3, C3 and carries a seated person of static mass
  M ~ U(30, 150) kg (the old m3 draw): a rigid part m_r (20-40 % of M) moving with the pan, and the rest hung
  on the pan as body masses (apparent mass: Fairley & Griffin 1989; Wei & Griffin 1998; ISO 5982):
  - `body1`: one mass m_b = M - m_r on the pan through k_b, c_b; natural frequency sqrt(k_b/m_b)/2pi
    ~ U(4, 6) Hz, damping ratio c_b/(2 sqrt(k_b m_b)) ~ U(0.3, 0.5). Its apparent-mass peak then lies at
    3.2-5.4 Hz, mean 4.3 (below the natural frequency: the damping), |M_app|/M 1.25-1.74 there.
  - `body2`: a series chain pan <- k_a, c_a -> m_a <- k_b, c_b -> m_b (not two masses in parallel, so not a
    model an estimator fits), m_b = U(0.1, 0.3) of the chain. Drawn as the chain's fixed-pan undamped
    frequencies f1 ~ U(4.5, 6.5), f2 ~ U(9, 13) Hz (the softer of the two stiffness pairs that give them),
    element damping ratios c_a/(2 sqrt(k_a m_a)) ~ U(0.3, 0.5), c_b/(2 sqrt(k_b m_b)) ~ U(0.15, 0.3), and
    redrawn until |M_app| (rigid part included) has exactly two maxima on 0.5-20 Hz, the first in 4-6 Hz,
    the second in 8-12 Hz (most draws pass). Resulting ranges over 20 000 persons: maxima at
    4.0-6.0 Hz (mean 4.8; |M_app|/M 1.13-2.01) and 8.0-12.0 Hz (mean 9.8; |M_app|/M 0.59-1.47); m_a/M
    0.42-0.72, m_b/M 0.06-0.24; sqrt(k_a/m_a) 7.5-12.9 Hz (k_a/M 980-4 700 N/m/kg), sqrt(k_b/m_b) 4.6-7.8 Hz
    (k_b/M 52-530 N/m/kg); c_a 510-7 950, c_b 17-715 Ns/m;
  - `mixed`: rigid (pan + M, all rigid), body1 or body2 with probability 1/3 each.
  Person draws come from their own stream (seed, 1): the vehicles, roads and noise of a file are those of
  the rigid file with the same seed. `/test/truth_m3` is the static mass on the seat spring, the mass an
  estimator is asked for: m_pan + M (the seat's apparent mass at 0 Hz); p1 = C3/(m_pan + M),
  p2 = K3/(m_pan + M), p3..p10 as for a rigid occupant. a3 is the seat pan's acceleration;
* two logger clocks (`--delay-ms`, `--delay-ms-range`): a3's logger runs tau behind a2's: a3 is sampled at
  t_k - tau while a2, a1 and the road are at t_k (tau > 0: a3 late). The state at t_k - tau comes from the
  same first-order hold over the fraction of a fine step (one more Van Loan exponential per recording):
  exact for any tau, not interpolated; a whole number of fine steps uses the fine state itself. Delays per
  recording ~ U(A, B) come from their own stream (seed, 2).

* foam seat (`--seat-law power --seat-exponent e`, `--pan-mass m`, `--known-loads L1 L2 ...`; issue 31): a rigid
  seat pan of m kg sits on the spring under the (rigid) occupant; with the power law the seat's K3 and C3 are the
  reference's times (S / 80 kg)^e, S the static load on the spring (pan + occupant), so no single K3 fits all
  occupants. `--known-loads` replaces the occupants by ballast of those masses, cycled over the recordings
  (a calibration drive per recording; 0 = the empty seat) and writes them as `/test/known_mass` [M] (kg);
  truth: `/test/truth_occupant_mass` (the occupant alone), `/test/truth_pan`, `/test/truth_K3`, `/test/truth_C3`
  per recording (the law in truth_K3's attrs); `/test/truth_m3` stays the static mass on the spring (pan +
  occupant), as for persons. A person (`--occupant body1` ...) gets its pan set to --pan-mass.

`make` writes what another producer would: `/test/accel` float64 [M, steps, 3] (a3, a2, a1), `/test/road`
(sampled at the logger's instants), `/test/params` (p1..p10 from the constants, for scoring), attrs
`schema` and `h` only (no `physics`: a foreign file is continuous with an unknown initial state), plus
`/test/truth_m3`, `/test/truth_K3` for scoring; with a person also `/test/truth_occupant` (int8: 0 rigid,
1 body1, 2 body2), `/test/truth_pan` [kg] and `/test/truth_body` [M, 8] with the columns PERSON_COLUMNS
(person M, rigid part m_r, m_a, k_a, c_a, m_b, k_b, c_b in kg, N/m, Ns/m; body1 uses the b columns, its
mass hung on the pan; body2 hangs a on the pan and b on a; unused columns 0; also the dataset's attr
`columns`), and with a delay `/test/truth_delay_s`. With a `.csv` output it writes one long drive of the
first vehicle in the layout `qcm-import` reads (t, a3, a2, a1 in m/s²), its truth in a `.json` beside.
`drives` writes drives of any length (minutes to an hour) of one vehicle each, for qcm-import: one CSV with
a recording column (t, a3, a2 on one clock), or per drive a seat and a floor logger's CSV (phone-app columns,
own clock, rate, jitter, tilt, gravity), and truth.json; made by the exact convolution of the road with each
vehicle's first-order-hold impulse response (impulse_responses; see docs/design/drives.md). `score-drives`
scores a qcm-estimate aggregate=drive run folder against it (mean / worst drive error, coverage, time to
±5 / ±2 %, splits at an occupant change and without one).
`score` reads a qcm-estimate run folder and prints the occupant mass error and status counts, how many
answers more than a tolerance off are still called `converged`, the chosen occupant models, the 95 %
interval coverage of m3, and the honesty count: `converged`, more than 10 % off and the truth outside
[m3_low, m3_high]; `--json OUT` writes those numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.linalg

# Reference vehicle (SPEC §1): the centre of the draws.
REF = {"C3": 615.0, "C2": 4761.0, "K3": 98935.0, "K2": 149171.0, "K1": 40000.0, "m2": 2160.0, "m1": 145.0}
ISO_CLASSES = "ABCDEFGH"
OCCUPANTS = ("rigid", "body1", "body2")
PERSON_COLUMNS = ("M", "m_r", "m_a", "k_a", "c_a", "m_b", "k_b", "c_b")
# body2's draws (see the module docstring for the constants they give)
BODY2_RANGES = {
    "f_fixed_pan_hz": ((4.5, 6.5), (9.0, 13.0)),
    "zeta": ((0.3, 0.5), (0.15, 0.3)),
    "b_share_of_chain": (0.1, 0.3),
    "peaks_hz": ((4.0, 6.0), (8.0, 12.0)),
}
PEAK_GRID_HZ = np.linspace(0.5, 20.0, 1951)  # where body2's apparent-mass maxima are looked for (0.01 Hz)


def draw_vehicles(n: int, rng: np.random.Generator, rel: float = 0.1, seat_rel: float = 0.0, c1_max: float = 0.0):
    """Physical constants of n vehicles, each a dict of arrays [n]. The seat's C3, K3 stay at the
    reference unless seat_rel > 0; the tyre damper C1 ~ U(0, c1_max)."""
    v = {k: REF[k] * (1 + rel * rng.standard_normal(n)) for k in ("C2", "K2", "K1", "m2", "m1")}
    v["C3"] = REF["C3"] * (1 + seat_rel * rng.standard_normal(n))
    v["K3"] = REF["K3"] * (1 + seat_rel * rng.standard_normal(n))
    v["m3"] = rng.uniform(30.0, 150.0, n)
    v["C1"] = rng.uniform(0.0, c1_max, n) if c1_max > 0 else np.zeros(n)
    return v


def parameters(v) -> np.ndarray:
    """p1..p10 of SPEC §1 from physical constants, [n, 10]."""
    return np.stack(
        [
            v["C3"] / v["m3"],
            v["K3"] / v["m3"],
            v["C3"] / v["m2"],
            v["C2"] / v["m2"],
            v["K3"] / v["m2"],
            v["K2"] / v["m2"],
            v["C2"] / v["m1"],
            (v["C2"] + v["C1"]) / v["m1"],
            v["K2"] / v["m1"],
            (v["K2"] + v["K1"]) / v["m1"],
        ],
        axis=1,
    )


BODY1_RANGES = {"rigid_share": (0.2, 0.4), "f_hz": (4.0, 6.0), "zeta": (0.3, 0.5)}  # the literature's (docstring)


def draw_persons(v, occupant: str, rng: np.random.Generator, body1: dict | None = None):
    """Seat pan + seated person in place of the rigid occupant of `v` (in place; see the module docstring).

    The person's static mass M is the old draw v["m3"]; afterwards v["m3"] = m_pan + M (the static mass on
    the seat spring, so `parameters` gives p1 = C3/(m_pan + M), p2 = K3/(m_pan + M)) and v gains
    "occupant" (0/1/2), "pan", "m_s" (the pan's body: m_pan + m_r) and PERSON_COLUMNS, each [n]. ``body1``:
    other ranges than BODY1_RANGES for the rigid share and the one-mode body (persons outside the literature's
    ranges; the same random draws, scaled to them)."""
    r = {**BODY1_RANGES, **(body1 or {})}
    n = len(v["m3"])
    kind = rng.integers(0, 3, n) if occupant == "mixed" else np.full(n, OCCUPANTS.index(occupant))
    M = v["m3"].copy()
    pan = rng.uniform(3.0, 12.0, n)
    rigid = np.where(kind == 0, 1.0, rng.uniform(*r["rigid_share"], n)) * M
    f_b = rng.uniform(*r["f_hz"], n)  # body1: natural frequency and damping ratio of the body mode
    zeta_b = rng.uniform(*r["zeta"], n)
    body = {k: np.zeros(n) for k in PERSON_COLUMNS}
    body["M"], body["m_r"] = M, rigid
    one = kind == 1
    body["m_b"][one] = M[one] - rigid[one]
    body["k_b"][one] = body["m_b"][one] * (2 * np.pi * f_b[one]) ** 2
    body["c_b"][one] = 2 * zeta_b[one] * np.sqrt(body["k_b"][one] * body["m_b"][one])
    for i in np.flatnonzero(kind == 2):
        chain = _draw_chain(M[i] - rigid[i], rigid[i], rng)
        for k, value in chain.items():
            body[k][i] = value
    v.update(body)
    v["occupant"], v["pan"], v["m_s"] = kind.astype(np.int8), pan, pan + rigid
    v["m3"] = pan + M
    return v


def _draw_chain(mass: float, m_r: float, rng: np.random.Generator) -> dict:
    """body2's chain pan <- k_a, c_a -> m_a <- k_b, c_b -> m_b of total mass `mass`, redrawn until its apparent
    mass has its two maxima in BODY2_RANGES["peaks_hz"]. Fixed pan, undamped: with x = k_a/m_a,
    y = k_b/m_b, mu = m_b/m_a the frequencies w1, w2 solve x + (1 + mu) y = w1² + w2², x y = w1² w2²."""
    r, grid = BODY2_RANGES, PEAK_GRID_HZ
    while True:
        share = rng.uniform(*r["b_share_of_chain"])
        w1, w2 = (2 * np.pi * rng.uniform(*band) for band in r["f_fixed_pan_hz"])
        z_a, z_b = (rng.uniform(*band) for band in r["zeta"])
        m_b = share * mass
        m_a = mass - m_b
        mu, S, P = m_b / m_a, w1**2 + w2**2, w1**2 * w2**2
        disc = S * S - 4 * (1 + mu) * P
        if disc < 0:
            continue
        y = (S - np.sqrt(disc)) / (2 * (1 + mu))  # the softer upper spring
        k_a, k_b = P / y * m_a, y * m_b
        chain = {"m_a": m_a, "k_a": k_a, "c_a": 2 * z_a * np.sqrt(k_a * m_a), "m_b": m_b, "k_b": k_b}
        chain["c_b"] = 2 * z_b * np.sqrt(k_b * m_b)
        mag = np.abs(apparent_mass(m_r, chain, 2j * np.pi * grid, kind=2))
        top = np.flatnonzero((mag[1:-1] > mag[:-2]) & (mag[1:-1] > mag[2:])) + 1
        if len(top) == 2 and all(lo <= grid[t] <= hi for t, (lo, hi) in zip(top, r["peaks_hz"])):
            return chain


def apparent_mass(m_r, body, s, kind: int):
    """The person's force on the pan over the pan's acceleration at the Laplace variable s (rigid part m_r,
    body constants as in PERSON_COLUMNS): m_r + m_b T_b (body1), m_r + (m_a + m_b T_b) T_a' (body2) with
    T_b = (c_b s + k_b)/(m_b s² + c_b s + k_b), T_a' = (c_a s + k_a)/(s² (m_a + m_b T_b) + c_a s + k_a)."""
    if kind == 0:
        return m_r + 0 * s
    T_b = (body["c_b"] * s + body["k_b"]) / (body["m_b"] * s**2 + body["c_b"] * s + body["k_b"])
    if kind == 1:
        return m_r + body["m_b"] * T_b
    upper = body["m_a"] + body["m_b"] * T_b
    z_a = body["c_a"] * s + body["k_a"]
    return m_r + upper * z_a / (s**2 * upper + z_a)


def _state_space(v, i: int):
    """x = (q3, q2, q1[, qa, qb], v3, v2, v1[, va, vb]), input w = (u, du/dt): dx/dt = A x + B w, from
    Newton's law per body. With a person (draw_persons) body 3 is the seat pan with the rigid part and
    bodies a, b are the person's masses (an unused one: mass 1, no links, stays at rest)."""
    C3, C2, C1, K3, K2, K1 = (v[k][i] for k in ("C3", "C2", "C1", "K3", "K2", "K1"))
    if "occupant" not in v:  # the rigid occupant of old, written out
        m = np.array([v["m3"][i], v["m2"][i], v["m1"][i]])
        # Forces on (seat, chassis, wheel) per unit of (q, v): the seat spring/damper between 3 and 2,
        # the suspension between 2 and 1, the tyre between 1 and the road.
        Kq = np.array([[-K3, K3, 0.0], [K3, -K3 - K2, K2], [0.0, K2, -K2 - K1]])
        Cv = np.array([[-C3, C3, 0.0], [C3, -C3 - C2, C2], [0.0, C2, -C2 - C1]])
        Fu = np.array([[0.0, 0.0], [0.0, 0.0], [K1, C1]])  # tyre force from (u, du/dt)
    else:
        kind = int(v["occupant"][i])
        m_a, m_b = v["m_a"][i], v["m_b"][i]
        m = np.array([v["m_s"][i], v["m2"][i], v["m1"][i], m_a if kind == 2 else 1.0, m_b if kind else 1.0])
        # Links (body, body, k, c); index 5 is the road. Newton per body: m_i a_i = sum over its links of
        # k (q_j - q_i) + c (v_j - v_i).
        links = [(0, 1, K3, C3), (1, 2, K2, C2), (2, 5, K1, C1)]
        if kind == 1:
            links.append((4, 0, v["k_b"][i], v["c_b"][i]))  # body1: m_b on the pan
        elif kind == 2:
            links += [(3, 0, v["k_a"][i], v["c_a"][i]), (4, 3, v["k_b"][i], v["c_b"][i])]  # pan <- a <- b
        Kq, Cv, Fu = np.zeros((5, 5)), np.zeros((5, 5)), np.zeros((5, 2))
        for a, b, k, c in links:
            Kq[a, a] -= k
            Cv[a, a] -= c
            if b == 5:
                Fu[a] += (k, c)  # tyre force from (u, du/dt)
                continue
            Kq[a, b] += k
            Cv[a, b] += c
            Kq[b, b] -= k
            Cv[b, b] -= c
            Kq[b, a] += k
            Cv[b, a] += c
    nb = len(m)
    A = np.zeros((2 * nb, 2 * nb))
    A[:nb, nb:] = np.eye(nb)
    A[nb:, :nb] = Kq / m[:, None]
    A[nb:, nb:] = Cv / m[:, None]
    B = np.zeros((2 * nb, 2))
    B[nb:] = Fu / m[:, None]
    return A, B


def _foh(A: np.ndarray, B: np.ndarray, dt: float, frac: float = 1.0):
    """x_{j+1} = Ad x_j + G0 w_j + G1 w_{j+1} for w linear between steps (Van Loan block exponential).
    With frac < 1: the state at t_j + frac dt from the same w_j, w_{j+1} (w still linear over dt)."""
    n, m = B.shape
    blk = np.zeros((n + 2 * m, n + 2 * m))
    blk[:n, :n] = A * dt * frac if frac != 1.0 else A * dt
    blk[:n, n : n + m] = B * dt * frac if frac != 1.0 else B * dt
    blk[n : n + m, n + m :] = np.eye(m) * frac
    E = scipy.linalg.expm(blk)
    Ad, P1, P2 = E[:n, :n], E[:n, n : n + m], E[:n, n + m :]
    return Ad, P1 - P2, P2


def iso_road(
    n_points: int, dx: float, road_class: int, rng: np.random.Generator, band=(0.011, 2.83), n0: float = 0.1
) -> np.ndarray:
    """Road height [m] at x_j = j dx, j < n_points: ISO 8608 G_d(n) = G0 (n/n0)^-2 on `band` (cycles/m),
    random phases, by one inverse real FFT over a period at least twice the drive."""
    n_fft = 1 << int(np.ceil(np.log2(2 * n_points)))
    length = n_fft * dx
    n = np.arange(n_fft // 2 + 1) / length
    g0 = 16e-6 * 4.0**road_class
    inside = (n >= band[0]) & (n <= band[1])
    amp = np.zeros_like(n)
    amp[inside] = np.sqrt(2 * g0 * (n[inside] / n0) ** -2 / length)  # cosine amplitude per line (Δn = 1/L)
    coef = amp * np.exp(1j * rng.uniform(0, 2 * np.pi, n.shape)) * (n_fft / 2)
    return np.fft.irfft(coef, n_fft)[:n_points]


def apply_seat(v, law: str, exponent: float, pan_mass: float | None, known_loads=None):
    """A foam seat (in place; see the module docstring): the occupant's mass becomes a known load where
    `known_loads` is given (recording i carries known_loads[i % len]), a rigid seat pan of `pan_mass` kg
    moves with a rigid occupant (a person's pan is set to it), and with law `power` the seat's K3 and C3
    become K3 (S / 80 kg)^exponent, C3 (S / 80 kg)^exponent, S = everything on the seat spring (pan +
    occupant). Adds v["occupant_mass"] (the occupant alone, [n]) and v["pan"]."""
    n = len(v["m3"])
    if known_loads is not None:
        v["m3"] = np.resize(np.asarray(known_loads, float), n)
    if "occupant" in v:  # a person: its own pan, unless one is given
        if pan_mass is not None:
            v["m_s"] = v["m_s"] - v["pan"] + pan_mass
            v["pan"] = np.full(n, float(pan_mass))
        v["occupant_mass"] = v["M"].copy()
        v["m3"] = v["pan"] + v["M"]
    else:  # a rigid occupant rigidly on a rigid pan: one mass on the spring
        v["pan"] = np.full(n, float(pan_mass or 0.0))
        v["occupant_mass"] = v["m3"].copy()
        v["m3"] = v["m3"] + v["pan"]
    if law == "power":
        factor = (v["m3"] / 80.0) ** exponent
        v["K3"], v["C3"] = v["K3"] * factor, v["C3"] * factor
    return v


def simulate(
    v,
    steps: int,
    h: float,
    rng: np.random.Generator,
    *,
    speed_mps: float = 30 / 3.6,
    classes=(0, 1, 2),
    warmup=(2.0, 20.0),
    sub: int = 10,
    delay_s=None,
):
    """Recordings [n, steps, 3] (a3, a2, a1), road [n, steps], window start times [n], road class [n].

    Each drive: from rest at t = 0 on its own road; states advanced by the first-order hold on the fine
    step h / sub (the road is linear between fine points); the window is `steps` samples from t0 on.
    delay_s [n] (optional): a3 is sampled at t0 + k h - delay_s, the other channels and the road at t0 + k h."""
    n_veh = len(v["m3"])
    dt = h / sub
    t0 = np.round(rng.uniform(*warmup, n_veh) / h) * h
    start = np.round(t0 / dt).astype(int)
    # a3's clock: fine step start + k sub + lag + frac (lag whole, 0 <= frac < 1; frac = 0 within 1e-9)
    shift = np.zeros(n_veh) if delay_s is None else -np.asarray(delay_s, float) / dt
    lag = np.floor(shift + 1e-9).astype(int)
    frac = np.where(shift - lag > 1e-9, shift - lag, 0.0)
    if np.any(start + lag < 0):
        raise ValueError("a delay longer than the warm-up: a3 would be sampled before the drive starts")
    n_fine = int(max(start.max(), (start + lag + (frac > 0)).max())) + (steps - 1) * sub + 1
    cls = rng.choice(np.asarray(classes), n_veh)
    # Road in time on the fine grid (x = speed t) and its slope, both linear in the state update.
    u = np.stack([iso_road(n_fine + 1, speed_mps * dt, int(c), rng) for c in cls])
    du = np.diff(u, axis=1) / dt  # slope on each fine interval; the hold uses it at both ends
    u_next = u[:, 1:]
    u = u[:, :n_fine]
    systems = [_state_space(v, i) for i in range(n_veh)]
    nb = systems[0][0].shape[0] // 2
    mats = [_foh(A, B, dt) for A, B in systems]
    Ad = np.stack([m[0] for m in mats])
    G0 = np.stack([m[1] for m in mats])
    G1 = np.stack([m[2] for m in mats])
    part = np.flatnonzero(frac > 0)  # recordings whose a3 falls between fine points: the hold over frac dt
    mats_f = [_foh(*systems[i], dt, frac[i]) for i in part]
    Pd, P0, P1 = (np.stack([m[c] for m in mats_f]) if len(part) else None for c in range(3))
    # w = (u, du/dt) with du/dt piecewise constant: hold u linearly and du/dt as a zero-order hold,
    # i.e. G0 @ (u_j, s_j) + G1 @ (u_{j+1}, s_j) with s_j the slope on interval j (exact).
    x = np.zeros((n_veh, 2 * nb))
    accel = np.empty((n_veh, steps, 3))
    road = np.empty((n_veh, steps))
    Ac = np.stack([A[nb : nb + 3] for A, _ in systems])  # [n, 3, 2 nb] accelerations from the state
    Bc = np.stack([B[nb : nb + 3] for _, B in systems])  # [n, 3, 2] and from (u, du/dt)
    rows = np.arange(n_veh)
    start3 = start + lag
    for j in range(n_fine):
        k = (j - start) // sub
        rec = ((j - start) % sub == 0) & (k >= 0) & (k < steps)
        k3 = (j - start3) // sub
        rec3 = ((j - start3) % sub == 0) & (k3 >= 0) & (k3 < steps)
        if rec.any() or rec3.any():
            s_here = du[rows, j]  # the slope on the interval starting here (the tyre damper's view)
            w = np.stack([u[rows, j], s_here], axis=1)
            a = np.einsum("nij,nj->ni", Ac, x) + np.einsum("nij,nj->ni", Bc, w)
            accel[rec, k[rec], 1:] = a[rec, 1:]  # rows of A, B below the identity: (a3, a2, a1)
            road[rec, k[rec]] = u[rec, j]
            on = rec3 & (frac == 0)
            accel[on, k3[on], 0] = a[on, 0]
            q = np.flatnonzero(rec3[part])  # a3 at t_j + frac dt: the state there, the road and slope there
            if len(q):
                i = part[q]
                w0 = np.stack([u[i, j], du[i, j]], axis=1)
                w1 = np.stack([u_next[i, j], du[i, j]], axis=1)
                xf = np.einsum("nij,nj->ni", Pd[q], x[i]) + np.einsum("nij,nj->ni", P0[q], w0)
                xf += np.einsum("nij,nj->ni", P1[q], w1)
                wf = np.stack([u[i, j] + frac[i] * dt * du[i, j], du[i, j]], axis=1)
                accel[i, k3[i], 0] = np.einsum("nj,nj->n", Ac[i, 0], xf) + np.einsum("nj,nj->n", Bc[i, 0], wf)
        if j + 1 < n_fine:
            w0 = np.stack([u[:, j], du[:, j]], axis=1)
            w1 = np.stack([u[:, j + 1], du[:, j]], axis=1)
            x = np.einsum("nij,nj->ni", Ad, x) + np.einsum("nij,nj->ni", G0, w0) + np.einsum("nij,nj->ni", G1, w1)
    return accel, road, t0, cls


def add_sensor(
    accel: np.ndarray, rng: np.random.Generator, noise: float, bias: float, noise_abs: float = 0.0
) -> np.ndarray:
    """Additive white noise of `noise` x each channel's RMS over the window plus `noise_abs` m/s² (a
    MEMS floor, the same on every channel), and a constant bias of `bias` x the RMS with a random sign
    per channel and recording."""
    rms = np.sqrt(np.mean(accel**2, axis=1, keepdims=True))
    out = accel + np.hypot(noise * rms, noise_abs) * rng.standard_normal(accel.shape)
    return out + bias * rms * rng.choice([-1.0, 1.0], size=rms.shape)


def _body1_ranges(args) -> dict:
    """make's --body-f-hz / --body-zeta / --body-rigid-share, each two bounds LO < HI (BODY1_RANGES where not given)."""
    out = {}
    for key, flag in (("f_hz", "body_f_hz"), ("zeta", "body_zeta"), ("rigid_share", "body_rigid_share")):
        value = getattr(args, flag, None)
        if value is None:
            continue
        lo, hi = value
        if not (0 < lo < hi) or (key != "f_hz" and hi >= 1 + (key == "zeta")):
            sys.exit(
                f"foreign_sim: --{flag.replace('_', '-')} {lo} {hi}: two bounds 0 < LO < HI (shares < 1, zeta < 2)"
            )
        out[key] = (lo, hi)
    return out


def make(args) -> None:
    for key, value, ok in (
        ("--n", args.n, args.n >= 1),
        ("--steps", args.steps, args.steps >= 2),
        ("--h", args.h, args.h > 0),
        ("--sub", args.sub, args.sub >= 1),
        ("--speed-kmh", args.speed_kmh, args.speed_kmh > 0),
        ("--noise", args.noise, args.noise >= 0),
        ("--noise-abs", args.noise_abs, args.noise_abs >= 0),
        ("--bias", args.bias, args.bias >= 0),
        ("--warmup", args.warmup, 0 <= args.warmup[0] <= args.warmup[1]),
        ("--delay-ms", args.delay_ms, np.isfinite(args.delay_ms)),
        (
            "--delay-ms-range",
            args.delay_ms_range,
            args.delay_ms_range is None or args.delay_ms_range[0] <= args.delay_ms_range[1],
        ),
    ):
        if not ok:
            sys.exit(f"foreign_sim make: {key} = {value} is out of range")
    if any(c not in ISO_CLASSES for c in args.classes):
        sys.exit(f"foreign_sim make: --classes {args.classes}: each one of {list(ISO_CLASSES)}")
    if args.delay_ms_range is not None and args.delay_ms != 0:
        sys.exit("foreign_sim make: --delay-ms and --delay-ms-range: give one")
    if args.pan_mass is not None and not (np.isfinite(args.pan_mass) and args.pan_mass >= 0):
        sys.exit(f"foreign_sim make: --pan-mass = {args.pan_mass} is out of range (>= 0 kg)")
    if not (np.isfinite(args.seat_exponent) and args.seat_exponent < 1):
        sys.exit(f"foreign_sim make: --seat-exponent = {args.seat_exponent}: give a number below 1")
    if args.known_loads is not None:
        if args.occupant != "rigid":
            sys.exit("foreign_sim make: --known-loads are ballast: they take --occupant rigid")
        if any(not (np.isfinite(x) and x >= 0) for x in args.known_loads):
            sys.exit(f"foreign_sim make: --known-loads {args.known_loads}: each a load >= 0 kg")
        if min(args.known_loads) + (args.pan_mass or 0.0) <= 0:
            sys.exit("foreign_sim make: an empty seat (load 0) needs a seat pan (--pan-mass > 0)")
    late = args.delay_ms if args.delay_ms_range is None else args.delay_ms_range[1]
    if late / 1000 > args.warmup[0]:
        sys.exit(f"foreign_sim make: a3 {late} ms late needs a warm-up of at least that (--warmup {args.warmup[0]})")
    out = Path(args.out)
    if out.exists():
        sys.exit(f"{out}: exists; choose another --out")
    rng = np.random.default_rng(args.seed)
    v = draw_vehicles(args.n, rng, seat_rel=args.seat_rel, c1_max=args.c1_max)
    person = args.occupant != "rigid"
    if person:
        draw_persons(v, args.occupant, np.random.default_rng([args.seed, 1]), _body1_ranges(args))
    seat = args.seat_law != "linear" or args.pan_mass is not None or args.known_loads is not None
    if seat:
        apply_seat(v, args.seat_law, args.seat_exponent, args.pan_mass, args.known_loads)
    delay_s = None
    if args.delay_ms_range is not None:
        delay_s = np.random.default_rng([args.seed, 2]).uniform(*args.delay_ms_range, args.n) / 1000
    elif args.delay_ms != 0:
        delay_s = np.full(args.n, args.delay_ms / 1000)
    accel, road, t0, cls = simulate(
        v,
        args.steps,
        args.h,
        rng,
        speed_mps=args.speed_kmh / 3.6,
        classes=[ISO_CLASSES.index(c) for c in args.classes],
        warmup=tuple(args.warmup),
        sub=args.sub,
        delay_s=delay_s,
    )
    accel = add_sensor(accel, rng, args.noise, args.bias, args.noise_abs)
    out.parent.mkdir(parents=True, exist_ok=True)
    params = parameters(v)
    tmp = out.with_name(out.name + ".partial")  # renamed into place complete: no half-written file looks valid
    if out.suffix == ".csv":
        t = np.arange(args.steps) * args.h
        table = np.column_stack([t, accel[0], road[0]])
        truth = {"params": params[0].tolist(), "m3": float(v["m3"][0]), "K3": float(v["K3"][0]), "h": args.h}
        if person:
            truth |= {"occupant": OCCUPANTS[v["occupant"][0]], "pan": float(v["pan"][0])}
            truth["body"] = {k: float(v[k][0]) for k in PERSON_COLUMNS}
        if delay_s is not None:
            truth["delay_s"] = float(delay_s[0])
        out.with_suffix(".json").write_text(json.dumps(truth, indent=1))
        np.savetxt(tmp, table, delimiter=",", header="t,a3,a2,a1,road", comments="", fmt="%.10g")
        tmp.rename(out)
    else:
        import h5py

        with h5py.File(tmp, "w") as f:
            f.attrs["schema"] = "hybridqcm.dataset/2"
            f.attrs["h"] = args.h
            g = f.create_group("test")
            g["accel"] = accel
            g["road"] = road
            g["params"] = params
            g["truth_m3"] = v["m3"]
            g["truth_K3"] = v["K3"]
            g["road_class"] = cls.astype(np.int8)
            g["window_start_s"] = t0
            if person:
                g["truth_occupant"] = v["occupant"]
                g["truth_pan"] = v["pan"]
                g["truth_body"] = np.stack([v[k] for k in PERSON_COLUMNS], axis=1)
                g["truth_body"].attrs["columns"] = ",".join(PERSON_COLUMNS)
            if delay_s is not None:
                g["truth_delay_s"] = delay_s
            if seat:
                g["truth_occupant_mass"] = v["occupant_mass"]
                g["truth_C3"] = v["C3"]
                if not person:
                    g["truth_pan"] = v["pan"]
                law = {"seat_law": args.seat_law, "seat_exponent": args.seat_exponent, "reference_load_kg": 80.0}
                law |= {"K3_ref": REF["K3"], "C3_ref": REF["C3"]}
                g["truth_K3"].attrs.update(law)
                if args.known_loads is not None:
                    g["known_mass"] = v["occupant_mass"]
        tmp.rename(out)
    extra = f", occupant {args.occupant}" if person else ""
    if seat:
        extra += f", seat {args.seat_law}" + (f" e = {args.seat_exponent}" if args.seat_law == "power" else "")
        extra += f", pan {args.pan_mass or 0.0} kg" + (f", known loads {args.known_loads}" if args.known_loads else "")
    if delay_s is not None:
        extra += f", a3 late by {1000 * delay_s.min():.3g}..{1000 * delay_s.max():.3g} ms"
    print(
        f"{out}: {args.n} recordings x {args.steps} steps at h = {args.h} s, noise {args.noise}, bias {args.bias}{extra}"
    )


def score(args) -> None:
    import csv

    import h5py

    run = Path(args.run)
    with open(run / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    summary = json.loads((run / "summary.json").read_text())
    stored = summary.get("data", "")  # the run's data path (a string; a mapping in older summaries)
    data = Path(args.data or (stored.get("path", "") if isinstance(stored, dict) else stored))
    with h5py.File(data, "r") as f:
        truth = f["test/params"][()]
        # a file of ours has no truth_m3: its seat is the reference one (thesis prior, SPEC § 2)
        truth_m3 = f["test/truth_m3"][()] if "truth_m3" in f["test"] else REF["K3"] / truth[:, 1]
        occupant = f["test/truth_occupant"][()] if "truth_occupant" in f["test"] else None
        delay = f["test/truth_delay_s"][()] if "truth_delay_s" in f["test"] else np.zeros(len(truth_m3))
    idx = np.array([int(r["index"]) for r in rows])
    m3 = np.array([float(r["m3"]) for r in rows])
    status = np.array([r["status"] for r in rows])
    err = np.abs(m3 / truth_m3[idx] - 1)
    has_interval = "m3_low" in rows[0] and "m3_high" in rows[0]
    lo = np.array([float(r.get("m3_low", "nan")) for r in rows])
    hi = np.array([float(r.get("m3_high", "nan")) for r in rows])
    inside = (lo <= truth_m3[idx]) & (truth_m3[idx] <= hi)
    cover = np.mean(inside)
    names = [k for k in rows[0] if k.startswith("p") and k[1:].isdigit()]
    perr = np.stack([np.abs(np.array([float(r[k]) for r in rows]) / truth[idx, int(k[1:]) - 1] - 1) for k in names], 1)
    conv = status == "converged"
    print(f"{run}: {len(rows)} recordings")
    print(f"  m3 mean {100 * err.mean():.3g} %, p95 {100 * np.percentile(err, 95):.3g} %, max {100 * err.max():.3g} %")
    within = ", ".join(f"{100 * np.mean(err <= t):.4g} %" for t in (0.005, 0.01, 0.05))
    print(f"  m3 within 0.5 / 1 / 5 %: {within}; 95 % interval covers {100 * cover:.3g} %")
    within_wide = {f"{100 * t:g}": float(np.mean(err <= t)) for t in (0.02, 0.05, 0.10)}
    print(f"  m3 within 2 / 5 / 10 %: {', '.join(f'{100 * w:.4g} %' for w in within_wide.values())}")
    for k, e in zip(names, perr.T):
        line = f"  {k}: mean {100 * e.mean():.3g} %, within 1 % {100 * np.mean(e <= 0.01):.3g} %, 5 % {100 * np.mean(e <= 0.05):.3g} %"
        if f"std_{k}" in rows[0]:  # the 95 % interval est ± 1.96 std
            est = np.array([float(r[k]) for r in rows])
            std = np.array([float(r[f"std_{k}"]) for r in rows])
            covered = np.abs(est - truth[idx, int(k[1:]) - 1]) <= 1.96 * std
            line += f", covered {100 * np.mean(covered):.3g} %"
        print(line)
    counts = {str(k): int(c) for k, c in zip(*np.unique(status, return_counts=True))}
    print(f"  status: {counts}")
    tol = args.tol
    print(f"  converged with m3 > {100 * tol:g} % off: {int(np.sum(conv & (err > tol)))}")
    models = None
    if "occupant_model" in rows[0]:
        models = {str(k): int(c) for k, c in zip(*np.unique([r["occupant_model"] for r in rows], return_counts=True))}
        print(f"  occupant model chosen: {models}")
    by_truth = {}
    if occupant is not None:
        for code, name in enumerate(OCCUPANTS):
            sel = occupant[idx] == code
            if sel.any():
                by_truth[name] = {"n": int(sel.sum()), "m3_mean": float(err[sel].mean())}
                by_truth[name]["within_5"] = float(np.mean(err[sel] <= 0.05))
        print(
            "  by true occupant: "
            + "; ".join(
                f"{k} {d['n']}: mean {100 * d['m3_mean']:.3g} %, within 5 % {100 * d['within_5']:.3g} %"
                for k, d in by_truth.items()
            )
        )
    tau = None
    if "tau" in rows[0]:  # the estimated delay [s] of a3 behind a2, against the file's (0 where it has none)
        miss = np.abs(np.array([float(r["tau"] or "nan") for r in rows]) - delay[idx]) * 1000
        tau = {"mean_abs_ms": float(np.nanmean(miss)), "within_1ms": float(np.mean(miss <= 1.0))}
        print(f"  delay: mean |tau - truth| {tau['mean_abs_ms']:.3g} ms, within 1 ms {100 * tau['within_1ms']:.3g} %")
    # the honesty count: an answer called converged, more than 10 % off, whose interval excludes the truth
    wrong = conv & (err > 0.10) & ~inside if has_interval else conv & (err > 0.10)
    what = "and the truth outside [m3_low, m3_high]" if has_interval else "(no m3_low/m3_high in the run)"
    print(f"  converged, m3 > 10 % off {what}: {int(wrong.sum())} ({100 * wrong.mean():.3g} %)")
    if args.json:
        numbers = {
            "run": str(run),
            "data": str(data),
            "n": len(rows),
            "m3_mean": float(err.mean()),
            "m3_p95": float(np.percentile(err, 95)),
            "m3_max": float(err.max()),
            "within": within_wide,
            "coverage_95": float(cover) if has_interval else None,
            "status": counts,
            "occupant_model": models,
            "by_true_occupant": by_truth or None,
            "delay": tau,
            "converged_wrong_excluded": int(wrong.sum()),
            "converged_wrong_excluded_fraction": float(wrong.mean()),
        }
        Path(args.json).write_text(json.dumps(numbers, indent=1))


# --------------------------------------------------------------------------------------------------
# Drives: minutes to an hour of one vehicle, cut into windows by qcm-import (issue 32)
GRAVITY = 9.80665  # m/s², what an accelerometer at rest reads along the vertical
PHONE_HEADER = "Time (s),Acceleration x (m/s^2),Acceleration y (m/s^2),Acceleration z (m/s^2)"


def _active(A: np.ndarray, B: np.ndarray):
    """(A, B) without the bodies that nothing links (a person's unused body: mass 1, no springs): their
    states never move, and their zero eigenvalues (a Jordan block) have no eigen-decomposition."""
    nb = A.shape[0] // 2
    used = [j for j in range(nb) if np.any(A[nb + j] != 0) or np.any(A[nb:, j] != 0) or np.any(A[nb:, nb + j] != 0)]
    keep = used + [nb + j for j in used]
    return A[np.ix_(keep, keep)], B[keep]


def impulse_responses(v, dt: float, n_max: int) -> np.ndarray:
    """[n, L, 3] accelerations (a3, a2, a1) of each vehicle of `v` (rigid occupant or person) to a unit triangular road
    pulse u_j = δ_j0 on the fine step dt (the road linear between fine points: _foh's first-order hold,
    exact). A drive's response is the causal convolution with u (an LTI system from rest). With
    x_{j+1} = Ad x_j + G0 u_j + G1 u_{j+1}: x_0 = G1, x_1 = Ad G1 + G0, x_j = Ad^(j-1) x_1, so h_0 = Ac G1 + Bc
    and h_j = Re(Ac V Λ^(j-1) V⁻¹ x_1) from the eigen-decomposition Ad = V Λ V⁻¹ (no step loop). L: until every
    mode has decayed to 1e-12, at most n_max (a longer tail never reaches a drive of n_max steps). The
    reference vehicle's chassis bounce is barely damped (the soft tyre spring in series: Re λ ≈ -0.04/s), so
    L is minutes, not seconds."""
    if np.any(v["C1"] != 0):
        raise ValueError("impulse_responses: drives take no tyre damper (the road's slope is not an input here)")
    n = len(v["m3"])
    systems = [_active(*_state_space(v, i)) for i in range(n)]
    mats = [_foh(A, B, dt) for A, B in systems]
    slowest = max(np.max(np.real(np.linalg.eigvals(A))) for A, _ in systems)
    L = int(min(n_max, np.ceil(np.log(1e-12) / (slowest * dt)) + 1))
    out = np.empty((n, L, 3))
    for i, ((A, B), (Ad, G0, G1)) in enumerate(zip(systems, mats)):
        nb = A.shape[0] // 2  # bodies: seat (pan), chassis, wheel[, person's a, b]
        Ac, Bc = A[nb : nb + 3], B[nb : nb + 3, 0]  # accelerations from the state and from u (the tyre spring)
        out[i, 0] = Ac @ G1[:, 0] + Bc
        lam, V = np.linalg.eig(Ad)
        weights = (Ac @ V) * np.linalg.solve(V, Ad @ G1[:, 0] + G0[:, 0])[None, :]  # [3, 6]
        log_lam = np.log(lam.astype(complex))
        for a in range(1, L, 1 << 20):
            j = np.arange(a, min(L, a + (1 << 20)))
            out[i, j] = np.real(np.exp(np.outer(j - 1, log_lam)) @ weights.T)
    return out


def drive_road(n_points: int, dx: float, road_class: int, rng: np.random.Generator, segment: int = 1 << 20):
    """Road height [m] at n_points points dx apart. Up to `segment` points: iso_road. Longer (an hour at
    1 kHz): independent iso_road segments overlap-added under a sine window of half a segment's overlap
    (w² of neighbours sums to one, so the variance and the spectrum above 1/segment stay ISO's)."""
    if n_points <= segment:
        return iso_road(n_points, dx, road_class, rng)
    hop = segment // 2
    window = np.sin(np.pi * (np.arange(segment) + 0.5) / segment)
    out = np.zeros(n_points + segment)
    for start in range(-hop, n_points, hop):
        piece = iso_road(segment, dx, road_class, rng) * window
        lo = max(start, 0)
        out[lo : start + segment] += piece[lo - start :]
    return out[:n_points]


def drive_positions(n_fine: int, dt: float, stop: tuple[float, float] | None) -> np.ndarray:
    """Index of the road point under the car at each fine step: one point per step while driving, the same
    point during `stop` = (start_s, end_s) (the car stands; it stops and drives off at once)."""
    moving = np.ones(n_fine, dtype=np.int64)
    if stop is not None:
        moving[int(round(stop[0] / dt)) : int(round(stop[1] / dt))] = 0
    return np.concatenate([[0], np.cumsum(moving[:-1])])


def drive_accelerations(v, dt: float, n_fine: int, rng: np.random.Generator, *, speed_mps, classes, stop=None):
    """Clean (a3, a2) [n, n_fine, 2] of each vehicle from rest at t = 0 on its own road, at the fine step dt.

    `stop` = (start_s, end_s, v2): the car stands still in [start_s, end_s); the occupant of v2 (the same
    vehicle, another m3) replaces v's at the middle of the stop, when v's motion has died out, and rides
    from there on; each occupant's response is the convolution from rest (the equilibrium shifts with the
    road height the car stands on: accelerations do not see it)."""
    from scipy.signal import oaconvolve

    n = len(v["m3"])
    cls = rng.choice(np.asarray(classes), n)
    positions = drive_positions(n_fine, dt, None if stop is None else stop[:2])
    out = np.empty((n, n_fine, 2))
    h1 = impulse_responses(v, dt, n_fine)
    h2 = impulse_responses(stop[2], dt, n_fine) if stop is not None else None
    change = None if stop is None else int(round(0.5 * (stop[0] + stop[1]) / dt))
    for i in range(n):
        road = drive_road(int(positions[-1]) + 1, speed_mps * dt, int(cls[i]), rng)[positions]
        for c in (0, 1):
            out[i, :, c] = oaconvolve(road - road[0], h1[i, :, c])[:n_fine]
            if change is not None:
                after = oaconvolve(road[change:] - road[change], h2[i, :, c])[: n_fine - change]
                out[i, change:, c] = after
    return out, cls


def _clock(n: int, h: float, jitter: float, rng: np.random.Generator) -> np.ndarray:
    """A logger's own time stamps [n] from 0: steps h (1 + jitter ξ), ξ ~ N(0, 1) clipped to ±3 (irregular
    sampling, as a phone's sensor events come)."""
    steps = h * (1 + jitter * np.clip(rng.standard_normal(n - 1), -3, 3))
    return np.concatenate([[0.0], np.cumsum(steps)])


def _rotation(tilt: float, axis_angle: float, yaw: float) -> np.ndarray:
    """Logger frame -> world: yaw about the vertical after a tilt by `tilt` about the horizontal axis at
    `axis_angle` (rad)."""
    k = np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    tilt_m = np.eye(3) + np.sin(tilt) * K + (1 - np.cos(tilt)) * K @ K
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ tilt_m


def _horizontal(n_fine: int, dt: float, rms: float, rng: np.random.Generator) -> np.ndarray:
    """[n_fine, 2] world-frame horizontal accelerations (longitudinal, lateral): white noise low-passed at
    0.5 Hz (second order), scaled to `rms`, zero mean (braking and cornering, both loggers alike)."""
    from scipy.signal import butter, sosfiltfilt

    if rms == 0:
        return np.zeros((n_fine, 2))
    sos = butter(2, 0.5, fs=1 / dt, output="sos")
    x = sosfiltfilt(sos, rng.standard_normal((2, n_fine)), axis=1).T
    x -= x.mean(0)
    return x * rms / x.std(0)


def write_phone_csv(path: Path, t: np.ndarray, xyz: np.ndarray) -> None:
    """A phone app's CSV: time [s] in the logger's own clock, three axes in m/s² with gravity."""
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "w") as handle:
        handle.write(PHONE_HEADER + "\n")
        for a in range(0, len(t), 100_000):
            block = np.column_stack([t[a : a + 100_000], xyz[a : a + 100_000]])
            np.savetxt(handle, block, delimiter=",", fmt=["%.6f", "%.6f", "%.6f", "%.6f"])
    tmp.rename(path)


def make_drives(args) -> None:
    """Write drives (module docstring of `drives --help`) and their truth.json."""
    for key, value, ok in (
        ("--n", args.n, args.n >= 1),
        ("--duration", args.duration, args.duration > 0),
        ("--h", args.h, args.h > 0),
        ("--noise", args.noise, args.noise >= 0),
        ("--stop-s", args.stop_s, args.stop_s >= 0),
        ("--min-change", args.min_change, 0 <= args.min_change < 1),
        ("--jitter", args.jitter, 0 <= args.jitter < 0.2),
        ("--tilt-max-deg", args.tilt_max_deg, 0 <= args.tilt_max_deg < 80),
        ("--drift-ppm", args.drift_ppm, args.drift_ppm >= 0),
        ("--start-spread-s", args.start_spread_s, args.start_spread_s >= 0),
        ("--horizontal", args.horizontal, args.horizontal >= 0),
    ):
        if not ok:
            sys.exit(f"foreign_sim drives: {key} = {value} is out of range")
    if args.change and args.stop_s <= 0:
        sys.exit("foreign_sim drives: --change happens at a stop: give --stop-s > 0")
    out = Path(args.out)
    if out.exists():
        sys.exit(f"{out}: exists; choose another --out")
    rng = np.random.default_rng(args.seed)
    v = draw_vehicles(args.n, rng)
    v["C1"] = np.zeros(args.n)
    if tuple(args.m3_range) != (30.0, 150.0):  # the same stream; occupants mapped into the range asked for
        v["m3"] = args.m3_range[0] + (v["m3"] - 30.0) / 120.0 * (args.m3_range[1] - args.m3_range[0])
    if args.occupant != "rigid":
        if args.change:
            sys.exit("foreign_sim drives: --change takes rigid occupants")
        draw_persons(v, args.occupant, np.random.default_rng([args.seed, 1]))
    two = bool(args.two_files)
    stop = None
    if args.stop_s > 0:  # the stop half-way, the drive's length is driving time
        half = 0.5 * args.duration
        stop = (half, half + args.stop_s)
    total = args.duration + (args.stop_s if stop else 0.0)
    v2 = None
    if stop is not None:
        v2 = {k: np.array(x, copy=True) for k, x in v.items()}
        if args.change:  # another occupant, at least min_change away, in the same range
            for i in range(args.n):
                while True:
                    m = rng.uniform(30.0, 150.0)
                    if abs(m / v["m3"][i] - 1) >= args.min_change:
                        v2["m3"][i] = m
                        break
    # timing of the two loggers (true time): starts, ends, clock errors, tilts
    rates = [float(r) for r in args.rates] if two else [1 / args.h]
    fine_rate = max(2000.0, 2 * max(rates)) if two else 1 / args.h * args.sub
    dt = 1 / fine_rate
    spread = args.start_spread_s if two else 0.0
    starts = rng.uniform(0, spread, (args.n, 2)) if two else np.zeros((args.n, 2))
    overlap_start = starts.max(1)
    ends = overlap_start[:, None] + total + (rng.uniform(0, 5, (args.n, 2)) if two else 0.0)
    drive_end = ends.max() + 1.0 / min(rates)
    lead = args.warmup_s  # every car drives this long from rest before the (first) logger starts
    n_fine = int(np.ceil((lead + drive_end) / dt)) + 2
    if stop is not None and two:
        sys.exit("foreign_sim drives: a stop (--stop-s) is for one-clock drives")
    stop_fine = None if stop is None else (lead + stop[0], lead + stop[1], v2)  # in the fine grid's time
    print(f"simulating {args.n} drive(s) of {total:g} s on a {fine_rate:g} Hz grid ...", flush=True)
    clean, cls = drive_accelerations(
        v,
        dt,
        n_fine,
        rng,
        speed_mps=args.speed_kmh / 3.6,
        classes=[ISO_CLASSES.index(c) for c in args.classes],
        stop=stop_fine,
    )
    out.mkdir(parents=True)
    params = parameters(v)
    truth = {"h": args.h, "duration_s": total, "noise": args.noise, "K3": REF["K3"], "two_files": two, "drives": {}}
    table = []
    width = len(str(args.n - 1))
    t_fine = np.arange(n_fine) * dt - lead  # the drive's time: 0 where the loggers' time origin is
    for i in range(args.n):
        name = f"drive{i:0{width}d}"
        record = {"m3": float(v["m3"][i]), "p1": float(params[i, 0]), "p2": float(params[i, 1])}
        if "occupant" in v:  # the static mass on the seat spring (pan + person), as `make` reports it
            record["occupant"] = OCCUPANTS[int(v["occupant"][i])]
        record["road_class"] = ISO_CLASSES[int(cls[i])]
        if stop is not None:
            record["stop_s"] = [stop[0], stop[1]]
            record["m3_after"] = float(v2["m3"][i])
            record["change_s"] = 0.5 * (stop[0] + stop[1]) if args.change else None
        # the driving parts' RMS (noise is a fraction of it), per channel
        driving = (t_fine >= 0) & (t_fine < total)
        if stop is not None:
            driving &= ~((t_fine >= stop[0]) & (t_fine < stop[1]))
        rms = np.sqrt(np.mean(clean[i, driving] ** 2, axis=0))
        if not two:
            k = np.arange(int(round(total / args.h)))
            idx = np.round((lead + k * args.h) / dt).astype(int)
            a = clean[i, idx] + args.noise * rms * rng.standard_normal((len(k), 2))
            table.append((name, k * args.h, a))
            truth["drives"][name] = record
            continue
        # two loggers: seat (a3) and floor (a2), each its own clock, start, rate, tilt, noise on every axis
        from scipy.interpolate import CubicSpline

        horizontal = _horizontal(n_fine, dt, args.horizontal, rng)
        clocks = rng.uniform(-0.5, 0.5, 2) * args.drift_ppm * 1e-6  # each clock's rate error: relative <= drift
        order = rng.permutation(rates) if len(rates) == 2 else np.array(rates * 2)
        for role, c in (("seat", 0), ("floor", 1)):
            h_own = 1.0 / order[c]
            n_samples = int((ends[i, c] - starts[i, c]) * order[c])
            stamps = _clock(n_samples, h_own, args.jitter, rng)
            t_true = starts[i, c] + stamps / (1 + clocks[c])
            fine_idx = t_true / dt + lead / dt
            vertical = CubicSpline(np.arange(n_fine), clean[i, :, c])(fine_idx)
            flat = np.column_stack(
                [CubicSpline(np.arange(n_fine), horizontal[:, j])(fine_idx) for j in (0, 1)] + [vertical + GRAVITY]
            )
            tilt = np.radians(rng.uniform(0, args.tilt_max_deg))
            R = _rotation(tilt, rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi))
            xyz = flat @ R  # world -> logger: R^T f, row-wise
            xyz += args.noise * rms[c] * rng.standard_normal(xyz.shape)
            write_phone_csv(out / f"{name}_{role}.csv", stamps, xyz)
            record[f"{role}_rate_hz"] = float(order[c])
            record[f"{role}_tilt_deg"] = float(np.degrees(tilt))
            record[f"{role}_start_s"] = float(starts[i, c])
            record[f"{role}_clock_ppm"] = float(clocks[c] * 1e6)
        # the floor clock at the seat clock's zero, and the relative rate: c_floor = offset + (1 + drift) c_seat
        record["offset_s"] = float((starts[i, 0] - starts[i, 1]) * (1 + clocks[1]))
        record["drift_ppm"] = float(((1 + clocks[1]) / (1 + clocks[0]) - 1) * 1e6)
        record["overlap_s"] = float(ends[i].min() - overlap_start[i])
        truth["drives"][name] = record
    if not two:
        path = out / "drives.csv"
        with open(path.with_name(path.name + ".partial"), "w") as handle:
            handle.write("t,a3,a2,recording\n")
            for name, t, a in table:
                for s in range(0, len(t), 100_000):
                    block = np.column_stack([t[s : s + 100_000], a[s : s + 100_000]])
                    rows = np.char.add(
                        np.char.add(np.char.mod("%.6f,", block[:, 0]), np.char.mod("%.7g,", block[:, 1])),
                        np.char.mod("%.7g," + name, block[:, 2]),
                    )
                    handle.write("\n".join(rows.tolist()) + "\n")
        path.with_name(path.name + ".partial").rename(path)
    if args.whole:  # every drive as one recording (clean, one clock): what bench/occupant_crb.py reads
        import h5py

        n_steps = int(round(total / args.h))
        idx = np.round((lead + np.arange(n_steps) * args.h) / dt).astype(int)
        with h5py.File(out / "whole.partial", "w") as f:
            f.attrs["schema"] = "hybridqcm.dataset/2"
            f.attrs["h"] = args.h
            accel = np.full((args.n, n_steps, 3), np.nan)
            accel[:, :, :2] = clean[:, idx]
            f["test/accel"] = np.nan_to_num(accel)
            f["test/params"] = params
            f["test/truth_m3"] = v["m3"]
            f["test/truth_K3"] = v["K3"]
            if "occupant" in v:  # persons: what bench/occupant_crb.py needs for the body model's bound
                f["test/truth_occupant"] = v["occupant"]
                f["test/truth_pan"] = v["pan"]
                f["test/truth_body"] = np.stack([v[k] for k in PERSON_COLUMNS], axis=1)
                f["test/truth_body"].attrs["columns"] = ",".join(PERSON_COLUMNS)
        (out / "whole.partial").rename(out / "whole.h5")
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    what = "two loggers each" if two else "one clock"
    print(
        f"{out}: {args.n} drive(s) of {total:g} s ({what}), noise {args.noise}"
        + (", occupant change" if args.change else "")
    )


def score_drives(args) -> None:
    """Score a qcm-estimate aggregate=drive run folder (drives.csv) against a `drives` truth.json."""
    import csv

    run = Path(args.run)
    truth = json.loads(Path(args.truth).read_text())
    with open(run / "drives.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    segments: dict[str, list[dict]] = {}
    for row in rows:
        segments.setdefault(row["drive"], []).append(row)
    missing = sorted(set(truth["drives"]) - set(segments))
    tw = args.window_s

    def number(text: str) -> float:
        return float(text) if text not in ("", None) else np.inf

    err, cover, t5, t2, splits, right, chi = [], [], [], [], [], [], []
    seg_err = []
    for name, record in truth["drives"].items():
        if name not in segments:
            continue
        segs = sorted(segments[name], key=lambda r: int(r["segment"]))
        change = record.get("change_s")
        splits.append(len(segs) > 1)
        if change is None:
            if len(segs) == 1:
                m3, lo, hi = (number(segs[0][k]) for k in ("m3", "m3_low", "m3_high"))
                err.append(abs(m3 / record["m3"] - 1))
                cover.append(lo <= record["m3"] <= hi)
                t5.append(number(segs[0]["t_to_5pct_s"]))
                t2.append(number(segs[0]["t_to_2pct_s"]))
                chi.append(number(segs[0].get("chi2_per_dof", "")))
            continue
        stop = record["stop_s"]
        ok = len(segs) == 2 and stop[0] - tw <= float(segs[1]["start_s"]) <= stop[1] + tw
        right.append(ok)
        if ok:  # each segment against its own occupant
            for seg, true_m3 in zip(segs, (record["m3"], record["m3_after"])):
                m3, lo, hi = (number(seg[k]) for k in ("m3", "m3_low", "m3_high"))
                seg_err.append(abs(m3 / true_m3 - 1))
                cover.append(lo <= true_m3 <= hi)
    n = len(truth["drives"]) - len(missing)
    numbers = {"run": str(run), "drives": n, "missing": missing}
    print(f"{run}: {n} drives scored" + (f", {len(missing)} missing from drives.csv: {missing[:5]}" if missing else ""))
    if err:
        e = np.asarray(err)
        numbers |= {
            "m3_mean": float(e.mean()),
            "m3_p95": float(np.percentile(e, 95)),
            "m3_max": float(e.max()),
            "over_3pct": int(np.sum(e > 0.03)),
            "coverage_95": float(np.mean(cover)),
            "median_t_to_5pct_s": float(np.median(t5)),
            "median_t_to_2pct_s": float(np.median(t2)),
            "reached_2pct": float(np.mean(np.isfinite(t2))),
            "median_chi2_per_dof": float(np.median(chi)) if chi else None,
        }
        print(
            f"  drive m3: mean {100 * e.mean():.3g} %, p95 {100 * numbers['m3_p95']:.3g} %, max {100 * e.max():.3g} %, "
            f"over 3 %: {numbers['over_3pct']}; 95 % interval covers {100 * numbers['coverage_95']:.3g} % "
            f"({len(err)} unsplit drives)"
        )
        print(
            f"  median time to ±5 %: {numbers['median_t_to_5pct_s']:.3g} s, to ±2 %: {numbers['median_t_to_2pct_s']:.3g} s "
            f"(±2 % reached in {100 * numbers['reached_2pct']:.3g} % of drives)"
        )
    split_rate = float(np.mean(splits)) if splits else float("nan")
    if right:
        numbers |= {
            "split_right": float(np.mean(right)),
            "segment_m3_mean": float(np.mean(seg_err)) if seg_err else None,
        }
        numbers["segment_coverage_95"] = float(np.mean(cover)) if cover else None
        print(
            f"  occupant change: split at the right window (±1, one boundary) in {100 * np.mean(right):.3g} % of "
            f"{len(right)} drives; per segment m3 mean {100 * np.mean(seg_err or [np.nan]):.3g} %"
        )
    else:
        numbers["no_split"] = 1.0 - split_rate
        print(f"  no occupant change: not split in {100 * (1 - split_rate):.3g} % of drives")
    if args.json:
        Path(args.json).write_text(json.dumps(numbers, indent=1))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    mk = sub.add_parser("make", help="write foreign recordings (.h5, or .csv for one drive)")
    mk.add_argument("--out", required=True)
    mk.add_argument("--n", type=int, default=300)
    mk.add_argument("--steps", type=int, default=512)
    mk.add_argument("--h", type=float, default=0.01)
    mk.add_argument("--sub", type=int, default=10, help="fine steps per logger step")
    mk.add_argument("--speed-kmh", type=float, default=30.0)
    mk.add_argument("--classes", nargs="+", default=["A", "B", "C"])
    mk.add_argument("--warmup", type=float, nargs=2, default=[2.0, 20.0])
    mk.add_argument("--noise", type=float, default=0.0, help="additive white noise, fraction of channel RMS")
    mk.add_argument("--noise-abs", type=float, default=0.0, help="additive white noise floor [m/s²], every channel")
    mk.add_argument("--bias", type=float, default=0.0, help="constant offset, fraction of channel RMS")
    mk.add_argument("--seat-rel", type=float, default=0.0, help="relative spread of the seat's C3, K3")
    mk.add_argument("--c1-max", type=float, default=0.0, help="tyre damper C1 ~ U(0, this) [Ns/m]")
    mk.add_argument("--seed", type=int, default=0)
    mk.add_argument("--occupant", choices=(*OCCUPANTS, "mixed"), default="rigid", help="rigid mass or seated person")
    mk.add_argument("--body-f-hz", type=float, nargs=2, metavar=("LO", "HI"), help="body1's mode [Hz] (default 4 6)")
    mk.add_argument("--body-zeta", type=float, nargs=2, metavar=("LO", "HI"), help="its damping ratio (0.3 0.5)")
    mk.add_argument(
        "--body-rigid-share", type=float, nargs=2, metavar=("LO", "HI"), help="the rigid part of M (0.2 0.4)"
    )
    mk.add_argument("--delay-ms", type=float, default=0.0, help="a3's logger this many ms behind a2's")
    mk.add_argument("--delay-ms-range", type=float, nargs=2, metavar=("A", "B"), help="a3 late by U(A, B) ms each")
    mk.add_argument("--seat-law", choices=("linear", "power"), default="linear", help="K3, C3 over the static load")
    mk.add_argument("--seat-exponent", type=float, default=0.5, help="power law: K3, C3 ∝ (load / 80 kg)^this")
    mk.add_argument("--pan-mass", type=float, default=None, help="a rigid seat pan on the spring [kg]")
    mk.add_argument("--known-loads", type=float, nargs="+", help="ballast [kg], cycled over the recordings")
    sc = sub.add_parser("score", help="score a qcm-estimate run folder against the file's truth")
    sc.add_argument("run")
    sc.add_argument("--data")
    sc.add_argument("--tol", type=float, default=0.05)
    sc.add_argument("--json", help="write the m3 numbers to this JSON file")
    dr = sub.add_parser("drives", help="write drives (minutes to hours) for qcm-import and aggregate=drive")
    dr.add_argument("--out", required=True, help="a new folder: drives.csv or *_seat.csv/*_floor.csv, truth.json")
    dr.add_argument("--n", type=int, default=100)
    dr.add_argument("--duration", type=float, default=60.0, help="driving time [s] (a stop comes on top)")
    dr.add_argument("--h", type=float, default=0.01, help="one clock: the logger's step [s]")
    dr.add_argument("--sub", type=int, default=10, help="one clock: fine steps per logger step")
    dr.add_argument("--speed-kmh", type=float, default=30.0)
    dr.add_argument("--classes", nargs="+", default=["A", "B", "C"])
    dr.add_argument("--warmup-s", type=float, default=5.0, help="driven from rest before the loggers start")
    dr.add_argument("--noise", type=float, default=0.05, help="additive white noise, fraction of the driving RMS")
    dr.add_argument("--stop-s", type=float, default=0.0, help="a stop of this length half-way")
    dr.add_argument("--change", action="store_true", help="another occupant after the stop")
    dr.add_argument("--min-change", type=float, default=0.1, help="the new occupant differs by at least this")
    dr.add_argument("--two-files", action="store_true", help="a seat and a floor logger, each its own CSV and clock")
    dr.add_argument("--rates", type=float, nargs="+", default=[100.0, 200.0], help="two files: the loggers' rates")
    dr.add_argument("--jitter", type=float, default=0.01, help="two files: step-to-step timing jitter (fraction)")
    dr.add_argument("--tilt-max-deg", type=float, default=20.0)
    dr.add_argument("--drift-ppm", type=float, default=100.0, help="two files: largest relative clock drift")
    dr.add_argument("--start-spread-s", type=float, default=30.0, help="two files: loggers start this far apart")
    dr.add_argument("--horizontal", type=float, default=0.2, help="two files: horizontal acceleration RMS [m/s²]")
    dr.add_argument("--m3-range", type=float, nargs=2, default=[30.0, 150.0], help="occupant mass U(A, B) [kg]")
    dr.add_argument("--occupant", choices=(*OCCUPANTS, "mixed"), default="rigid", help="rigid mass or seated person")
    dr.add_argument("--whole", action="store_true", help="also whole.h5: each drive clean, for occupant_crb.py")
    dr.add_argument("--seed", type=int, default=0)
    sd = sub.add_parser("score-drives", help="score a qcm-estimate aggregate=drive run folder")
    sd.add_argument("run")
    sd.add_argument("--truth", required=True, help="the drives' truth.json")
    sd.add_argument("--window-s", type=float, default=5.12, help="window length: the split's tolerance (±1)")
    sd.add_argument("--json")
    args = ap.parse_args(argv)
    commands = {"make": make, "score": score, "drives": make_drives, "score-drives": score_drives}
    commands[args.cmd](args)


if __name__ == "__main__":
    main()
