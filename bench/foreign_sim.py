"""Recordings from a simulator that is not ours: the estimator's check against physics, not our generator.

    .venv/bin/python bench/foreign_sim.py make --out data/foreign.h5 --n 300 [--noise 0.05 --bias 0.2]
    .venv/bin/python bench/foreign_sim.py make --out data/foreign.csv --n 1 --steps 6000   (one drive, qcm-import)
    .venv/bin/python bench/foreign_sim.py score RUN_DIR [--data data/foreign.h5]

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
  fraction of each channel's RMS and a constant bias per channel, any rate h.

`make` writes what another producer would: `/test/accel` float64 [M, steps, 3] (a3, a2, a1), `/test/road`
(sampled at the logger's instants), `/test/params` (p1..p10 from the constants, for scoring), attrs
`schema` and `h` only (no `physics`: a foreign file is continuous with an unknown initial state), plus
`/test/truth_m3`, `/test/truth_K3` for scoring. With a `.csv` output it writes one long drive of the
first vehicle in the layout `qcm-import` reads (t, a3, a2, a1 in m/s²), its truth in a `.json` beside.
`score` reads a qcm-estimate run folder and prints the occupant mass error and status counts, and how
many answers more than a tolerance off are still called `converged`.
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


def _state_space(v, i: int):
    """x = (q3, q2, q1, v3, v2, v1), input w = (u, du/dt): dx/dt = A x + B w, from Newton's law per body."""
    m = np.array([v["m3"][i], v["m2"][i], v["m1"][i]])
    C3, C2, C1, K3, K2, K1 = (v[k][i] for k in ("C3", "C2", "C1", "K3", "K2", "K1"))
    # Forces on (seat, chassis, wheel) per unit of (q, v): the seat spring/damper between 3 and 2,
    # the suspension between 2 and 1, the tyre between 1 and the road.
    Kq = np.array([[-K3, K3, 0.0], [K3, -K3 - K2, K2], [0.0, K2, -K2 - K1]])
    Cv = np.array([[-C3, C3, 0.0], [C3, -C3 - C2, C2], [0.0, C2, -C2 - C1]])
    Fu = np.array([[0.0, 0.0], [0.0, 0.0], [K1, C1]])  # tyre force from (u, du/dt)
    A = np.zeros((6, 6))
    A[:3, 3:] = np.eye(3)
    A[3:, :3] = Kq / m[:, None]
    A[3:, 3:] = Cv / m[:, None]
    B = np.zeros((6, 2))
    B[3:] = Fu / m[:, None]
    return A, B


def _foh(A: np.ndarray, B: np.ndarray, dt: float):
    """x_{j+1} = Ad x_j + G0 w_j + G1 w_{j+1} for w linear between steps (Van Loan block exponential)."""
    n, m = B.shape
    blk = np.zeros((n + 2 * m, n + 2 * m))
    blk[:n, :n] = A * dt
    blk[:n, n : n + m] = B * dt
    blk[n : n + m, n + m :] = np.eye(m)
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
):
    """Recordings [n, steps, 3] (a3, a2, a1), road [n, steps], window start times [n], road class [n].

    Each drive: from rest at t = 0 on its own road; states advanced by the first-order hold on the fine
    step h / sub (the road is linear between fine points); the window is `steps` samples from t0 on."""
    n_veh = len(v["m3"])
    dt = h / sub
    t0 = np.round(rng.uniform(*warmup, n_veh) / h) * h
    start = np.round(t0 / dt).astype(int)
    n_fine = int(start.max()) + (steps - 1) * sub + 1
    cls = rng.choice(np.asarray(classes), n_veh)
    # Road in time on the fine grid (x = speed t) and its slope, both linear in the state update.
    u = np.stack([iso_road(n_fine + 1, speed_mps * dt, int(c), rng) for c in cls])
    du = np.diff(u, axis=1) / dt  # slope on each fine interval; the hold uses it at both ends
    u = u[:, :n_fine]
    systems = [_state_space(v, i) for i in range(n_veh)]
    mats = [_foh(A, B, dt) for A, B in systems]
    Ad = np.stack([m[0] for m in mats])
    G0 = np.stack([m[1] for m in mats])
    G1 = np.stack([m[2] for m in mats])
    # w = (u, du/dt) with du/dt piecewise constant: hold u linearly and du/dt as a zero-order hold,
    # i.e. G0 @ (u_j, s_j) + G1 @ (u_{j+1}, s_j) with s_j the slope on interval j (exact).
    x = np.zeros((n_veh, 6))
    accel = np.empty((n_veh, steps, 3))
    road = np.empty((n_veh, steps))
    Ac = np.stack([A[3:] for A, _ in systems])  # [n, 3, 6] accelerations from the state
    Bc = np.stack([B[3:] for _, B in systems])  # [n, 3, 2] and from (u, du/dt)
    rows = np.arange(n_veh)
    for j in range(n_fine):
        k = (j - start) // sub
        rec = ((j - start) % sub == 0) & (k >= 0) & (k < steps)
        if rec.any():
            s_here = du[rows, j]  # the slope on the interval starting here (the tyre damper's view)
            w = np.stack([u[rows, j], s_here], axis=1)
            a = np.einsum("nij,nj->ni", Ac, x) + np.einsum("nij,nj->ni", Bc, w)
            accel[rec, k[rec]] = a[rec]  # rows of A, B below the identity: (a3, a2, a1)
            road[rec, k[rec]] = u[rec, j]
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
    ):
        if not ok:
            sys.exit(f"foreign_sim make: {key} = {value} is out of range")
    if any(c not in ISO_CLASSES for c in args.classes):
        sys.exit(f"foreign_sim make: --classes {args.classes}: each one of {list(ISO_CLASSES)}")
    out = Path(args.out)
    if out.exists():
        sys.exit(f"{out}: exists; choose another --out")
    rng = np.random.default_rng(args.seed)
    v = draw_vehicles(args.n, rng, seat_rel=args.seat_rel, c1_max=args.c1_max)
    accel, road, t0, cls = simulate(
        v,
        args.steps,
        args.h,
        rng,
        speed_mps=args.speed_kmh / 3.6,
        classes=[ISO_CLASSES.index(c) for c in args.classes],
        warmup=tuple(args.warmup),
        sub=args.sub,
    )
    accel = add_sensor(accel, rng, args.noise, args.bias, args.noise_abs)
    out.parent.mkdir(parents=True, exist_ok=True)
    params = parameters(v)
    tmp = out.with_name(out.name + ".partial")  # renamed into place complete: no half-written file looks valid
    if out.suffix == ".csv":
        t = np.arange(args.steps) * args.h
        table = np.column_stack([t, accel[0], road[0]])
        truth = {"params": params[0].tolist(), "m3": float(v["m3"][0]), "K3": float(v["K3"][0]), "h": args.h}
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
        tmp.rename(out)
    print(f"{out}: {args.n} recordings x {args.steps} steps at h = {args.h} s, noise {args.noise}, bias {args.bias}")


def score(args) -> None:
    import csv

    import h5py

    run = Path(args.run)
    with open(run / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    summary = json.loads((run / "summary.json").read_text())
    data = Path(args.data or summary.get("data", {}).get("path", ""))
    with h5py.File(data, "r") as f:
        truth = f["test/params"][()]
        # a file of ours has no truth_m3: its seat is the reference one (thesis prior, SPEC § 2)
        truth_m3 = f["test/truth_m3"][()] if "truth_m3" in f["test"] else REF["K3"] / truth[:, 1]
    idx = np.array([int(r["index"]) for r in rows])
    m3 = np.array([float(r["m3"]) for r in rows])
    status = np.array([r["status"] for r in rows])
    err = np.abs(m3 / truth_m3[idx] - 1)
    lo = np.array([float(r.get("m3_low", "nan")) for r in rows])
    hi = np.array([float(r.get("m3_high", "nan")) for r in rows])
    cover = np.mean((lo <= truth_m3[idx]) & (truth_m3[idx] <= hi))
    names = [k for k in rows[0] if k.startswith("p") and k[1:].isdigit()]
    perr = np.stack([np.abs(np.array([float(r[k]) for r in rows]) / truth[idx, int(k[1:]) - 1] - 1) for k in names], 1)
    conv = status == "converged"
    print(f"{run}: {len(rows)} recordings")
    print(f"  m3 mean {100 * err.mean():.3g} %, p95 {100 * np.percentile(err, 95):.3g} %, max {100 * err.max():.3g} %")
    within = ", ".join(f"{100 * np.mean(err <= t):.4g} %" for t in (0.005, 0.01, 0.05))
    print(f"  m3 within 0.5 / 1 / 5 %: {within}; 95 % interval covers {100 * cover:.3g} %")
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
    sc = sub.add_parser("score", help="score a qcm-estimate run folder against the file's truth")
    sc.add_argument("run")
    sc.add_argument("--data")
    sc.add_argument("--tol", type=float, default=0.05)
    args = ap.parse_args(argv)
    make(args) if args.cmd == "make" else score(args)


if __name__ == "__main__":
    main()
