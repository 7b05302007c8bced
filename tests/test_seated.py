"""qcm-simulate occupant=rigid|body1|body2: the quarter car with a seated person (physics/seated.py)."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
import tarfile
from concurrent.futures import ThreadPoolExecutor
from io import BytesIO
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from hybridqcm.data.hdf5 import LAYOUT, dataset_info, read_split
from hybridqcm.physics.occupant import transmissibility
from hybridqcm.physics.parameters import PhysicalConstants, system_matrix
from hybridqcm.physics.seated import BODY_RANGES, draw_body, physical_matrices, seated_system_matrix

REPO = Path(__file__).resolve().parents[1]
# the last commit before occupant=: its generator is "today's" for the rigid occupant
BEFORE = "935b0a8"
# one BLAS thread in every run whose files are compared byte for byte, as the README says for byte-exact data:
# a threaded GEMM splits its sums by its threads, and MKL may change their number under load (two body1 runs
# of one seed once differed under a loaded full suite; test_app_simulate saw 1 ulp of float32 in a3)
ENV_COLUMNS = {"COLUMNS": "160", "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

# one small dataset, written by the code before and after the change
SMALL = dict(
    splits={"train": {"profiles": {"A": 2, "C": 1}}, "test": {"profiles": {"B": 1}}},
    n_steps=64,
    h=0.01,
    speed_mps=30 / 3.6,
    samples_per_profile=3,
    seed=5,
    profiles_per_chunk=2,
    progress=False,
)
WRITE_SMALL = """
import sys
from hybridqcm.data.simulate import write_dataset
from hybridqcm.physics.prior import build_prior
from hybridqcm.physics.road import RoadProfile
kw = {kw!r}
for physics, warmup, out in (("continuous", (2.0, 20.0), sys.argv[1]), ("euler", (0.0, 0.0), sys.argv[2])):
    prior = build_prior("thesis", h=None if physics == "continuous" else kw["h"])
    write_dataset(out, prior=prior, road_profile=RoadProfile(), physics=physics, warmup_s=warmup, **kw{extra})
if len(sys.argv) > 3:
    prior = build_prior("thesis", h=None)
    write_dataset(sys.argv[3], prior=prior, road_profile=RoadProfile(), physics="continuous", warmup_s=(2.0, 20.0), occupant="body2", **kw)
"""


def _env(pythonpath: Path | None = None) -> dict:
    import os

    env = {**os.environ, **ENV_COLUMNS}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return env


def _write_small(folder: Path, src: Path | None, extra: str = "") -> tuple[Path, ...]:
    """The rigid SMALL dataset (continuous, euler) by the code under `src` (None: this tree); with
    `extra` also a body2 file of the same seed."""
    folder.mkdir(parents=True, exist_ok=True)
    outputs = (folder / "continuous.h5", folder / "euler.h5") + ((folder / "body2.h5",) if extra else ())
    script = WRITE_SMALL.format(kw=SMALL, extra=extra)
    result = subprocess.run(
        [sys.executable, "-c", script, *map(str, outputs)],
        capture_output=True,
        text=True,
        timeout=120,
        env=_env(src),
        cwd=folder,
    )
    assert result.returncode == 0, result.stderr
    return outputs


def _old_source(tmp: Path) -> Path | None:
    """src/ of the commit BEFORE, extracted under tmp; None without git or that commit."""
    if shutil.which("git") is None:
        return None
    result = subprocess.run(["git", "archive", BEFORE, "src"], cwd=REPO, capture_output=True, timeout=60)
    if result.returncode != 0:
        return None
    with tarfile.open(fileobj=BytesIO(result.stdout)) as archive:
        archive.extractall(tmp, filter="data")
    return tmp / "src"


def _simulate(tmp: Path, *overrides: str, output: Path, run: str) -> subprocess.CompletedProcess:
    script = Path(sys.executable).parent / "qcm-simulate"
    command = [str(script)] if script.exists() else [sys.executable, "-m", "hybridqcm.apps.simulate"]
    command += ["preset=tiny", "n_steps=64", f"output={output}", f"hydra.run.dir={tmp / run}", *overrides]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, env=_env(), cwd=tmp)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict:
    """Every subprocess of this file, two at a time (mostly interpreter start-up)."""
    tmp = tmp_path_factory.mktemp("persons")
    old_src = _old_source(tmp / "before")
    jobs = {
        "body1_a": lambda: _simulate(tmp, "occupant=body1", "seed=3", output=tmp / "a.h5", run="ra"),
        "body1_b": lambda: _simulate(tmp, "occupant=body1", "seed=3", output=tmp / "b.h5", run="rb"),
        "bad": lambda: _simulate(tmp, "occupant=body3", output=tmp / "bad.h5", run="rbad"),
        "euler": lambda: _simulate(tmp, "occupant=body1", "physics=euler", output=tmp / "eu.h5", run="reu"),
        "now": lambda: _write_small(tmp / "now", None, ', occupant="rigid"'),  # + a body2 file
    }
    if old_src is not None:
        jobs["before"] = lambda: _write_small(tmp / "before_out", old_src)
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = {name: pool.submit(job) for name, job in jobs.items()}
        out = {name: future.result() for name, future in futures.items()}
    return {"tmp": tmp, **out}


def test_rigid_is_bit_identical_to_before(runs):
    if "before" not in runs:
        pytest.skip(f"git or commit {BEFORE} not available")
    for before, now in zip(runs["before"], runs["now"][:2]):
        with h5py.File(before) as fb, h5py.File(now) as fn:
            assert sorted(fb) == sorted(fn)
            for split in fb:
                assert sorted(fn[split]) == sorted(LAYOUT) and fn[split].attrs["occupant"] == "rigid"
                for key in LAYOUT:
                    xb, xn = fb[split][key][()], fn[split][key][()]
                    assert xb.dtype == xn.dtype and xb.tobytes() == xn.tobytes(), (before.name, split, key)


def _random_persons(n: int, occupant: str, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    from hybridqcm.physics.prior import build_prior

    generator = torch.Generator().manual_seed(seed)
    p = build_prior("thesis", h=None).sample(n, generator).params
    return p, draw_body(occupant, n, generator)


@pytest.mark.parametrize("occupant", ["body1", "body2"])
def test_pan_over_chassis_transfer_is_the_closed_form(occupant):
    """a3/a2 of the road-driven model, (i w I - A)^-1 B, equals occupant.transmissibility."""
    p, body = _random_persons(64, occupant)
    A = seated_system_matrix(p, body)
    n = A.shape[-1]
    omega = 2 * math.pi * torch.linspace(0.2, 30.0, 150, dtype=torch.float64)
    lhs = 1j * omega[None, :, None, None] * torch.eye(n) - A[:, None].to(torch.complex128)
    rhs = torch.zeros(p.shape[0], omega.shape[0], n, 1, dtype=torch.complex128)
    rhs[..., 2, 0] = 1.0  # the road enters at v1
    G = torch.linalg.solve(lhs, rhs)[..., 0]  # velocities' gains; accelerations are i w times them
    model = G[..., 0] / G[..., 1]
    closed = transmissibility(torch.cat([p[:, :2], body], -1), omega)
    torch.testing.assert_close(model, closed, rtol=1e-9, atol=1e-12)
    rigid = transmissibility(p[:, :2], omega)
    assert (model - rigid).abs().amax() > 0.1  # the person matters


@pytest.mark.parametrize("n_modes", [0, 1, 2])
def test_state_equation_is_newton_per_body(n_modes):
    """A of the parametrised model is Newton's law per body (pan, chassis, wheel, body masses)
    written in absolute coordinates, moved to (v, q, y', y) with y_i = q_i - q3."""
    M, m_s = 90.0, 25.0
    masses = [40.0, 25.0][:n_modes] if n_modes == 2 else [M - m_s] * n_modes
    if n_modes == 0:
        m_s = M
    k_body, c_body = [4.0e4, 1.2e5][:n_modes], [900.0, 700.0][:n_modes]
    car = PhysicalConstants(C1=30.0, m3=M)
    p = car.to_params()[None]
    body = torch.tensor(
        [[v for i in range(n_modes) for v in (masses[i] / m_s, k_body[i] / masses[i], c_body[i] / masses[i])]],
        dtype=torch.float64,
    )
    Mm, Cm, Km = physical_matrices(
        m_s, masses, k_body, c_body, car.m2, car.m1, car.C3, car.K3, car.C2, car.K2, car.C1, car.K1
    )
    N = 3 + n_modes
    Minv = torch.linalg.inv(Mm)
    A_abs = torch.cat([torch.cat([-Minv @ Cm, -Minv @ Km], 1), torch.cat([torch.eye(N), torch.zeros(N, N)], 1)], 0)
    # absolute (v3 v2 v1 vb.., q3 q2 q1 qb..) -> (v3 v2 v1 q3 q2 q1 y'.. y..)
    T = torch.zeros(2 * N, 2 * N, dtype=torch.float64)
    for j in range(3):
        T[j, j] = 1.0
        T[3 + j, N + j] = 1.0
    for i in range(n_modes):
        T[6 + i, 3 + i], T[6 + i, 0] = 1.0, -1.0
        T[6 + n_modes + i, N + 3 + i], T[6 + n_modes + i, N] = 1.0, -1.0
    expected = T @ A_abs @ torch.linalg.inv(T)
    A = seated_system_matrix(p, body)[0]
    torch.testing.assert_close(A, expected, rtol=1e-10, atol=1e-9)
    if n_modes == 0:
        assert torch.equal(A, system_matrix(p)[0])


def test_simulated_accelerations_obey_the_state_equation():
    """The exact response with body modes: a = dv/dt (central differences on a fine grid), the seat's
    apparent mass loads the chassis, the window starts mid-drive."""
    from hybridqcm.physics.continuous import simulate_continuous
    from hybridqcm.physics.road import RoadProfile, road_class_index

    p, body = _random_persons(6, "body2", seed=1)
    road = RoadProfile(n_waves=200)
    amplitude, phase = road.draw(torch.full((6,), road_class_index("B")), torch.Generator().manual_seed(2))
    h = 0.0005
    response = simulate_continuous(p, amplitude, phase, road.omega * 30 / 3.6, 400, h, 3.0, body=body)
    dv = (response.vel[:, 2:] - response.vel[:, :-2]) / (2 * h)
    scale = response.accel.abs().amax((0, 1))
    assert ((dv - response.accel[:, 1:-1]).abs().amax((0, 1)) / scale).max() < 2e-3
    assert response.body_state0.shape == (6, 4) and response.body_state0.abs().min() > 0
    rigid = simulate_continuous(p, amplitude, phase, road.omega * 30 / 3.6, 400, h, 3.0)
    assert (response.accel[..., 0] - rigid.accel[..., 0]).abs().max() > 0.05 * scale[0]


@pytest.mark.parametrize("occupant", ["body1", "body2"])
def test_drawn_bodies_lie_in_the_literature_ranges(occupant):
    body = draw_body(occupant, 4000, torch.Generator().manual_seed(0))
    _check_ranges(body.numpy(), occupant)
    assert draw_body("rigid", 5, torch.Generator()).shape == (5, 0)


def _check_ranges(body: np.ndarray, occupant: str) -> None:
    n_modes = body.shape[1] // 3
    assert n_modes == {"body1": 1, "body2": 2}[occupant]
    r, k, c = body[:, 0::3], body[:, 1::3], body[:, 2::3]
    rigid_fraction = 1 / (1 + r.sum(1))
    fraction = r * rigid_fraction[:, None]  # m_i / M
    omega = np.sqrt(k)
    for i in range(n_modes):
        ranges = BODY_RANGES[i]
        f, zeta = omega[:, i] / (2 * math.pi), c[:, i] / (2 * omega[:, i])
        for value, (low, high) in ((f, ranges["f_hz"]), (zeta, ranges["zeta"])):
            assert low <= value.min() and value.max() <= high
            if len(value) > 1000:
                assert value.min() < low + 0.05 * (high - low) and value.max() > high - 0.05 * (high - low)
    low, high = BODY_RANGES[0]["fraction"]
    assert (low - 1e-12 <= 1 - rigid_fraction).all() and (1 - rigid_fraction <= high + 1e-12).all()
    if n_modes == 2:
        low, high = BODY_RANGES[1]["fraction"]
        assert (low - 1e-12 <= fraction[:, 1]).all() and (fraction[:, 1] <= high + 1e-12).all()


def test_qcm_simulate_body1_writes_reproducible_persons(runs):
    tmp = runs["tmp"]
    for name in ("body1_a", "body1_b"):
        assert runs[name].returncode == 0, runs[name].stderr
    a, b = tmp / "a.h5", tmp / "b.h5"
    info = dataset_info(a)
    for split in ("train", "test"):
        assert info["splits"][split]["occupant"] == "body1"
        assert info["splits"][split]["keys"] == sorted([*LAYOUT, "occupant_params"])
        data = read_split(a, split, ("occupant_params", "params", "accel", "road"))
        assert data["occupant_params"].shape == (data["params"].shape[0], 3)
        _check_ranges(data["occupant_params"], "body1")
        again = read_split(b, split, ("occupant_params", "params", "accel"))
        for key in again:
            if key != "h":
                assert data[key].tobytes() == again[key].tobytes(), (split, key)
    assert "occupant: body1" in runs["body1_a"].stdout


def test_persons_ride_the_rigid_files_vehicles(runs):
    """Same seed: the vehicles (p, static mass), roads and warm-ups of the rigid file; a3 differs."""
    rigid, persons = runs["now"][0], runs["now"][2]
    info = dataset_info(persons)
    for split in info["splits"]:
        assert info["splits"][split]["occupant"] == "body2"
        data = read_split(persons, split, ("params", "road", "accel", "occupant_params"))
        same = read_split(rigid, split, ("params", "road", "accel"))
        assert np.array_equal(data["params"], same["params"]) and np.array_equal(data["road"], same["road"])
        assert not np.allclose(data["accel"][..., 0], same["accel"][..., 0], rtol=0.05, atol=1e-3)
        _check_ranges(data["occupant_params"], "body2")


@pytest.mark.parametrize(
    "name,message",
    [
        ("bad", "occupant = 'body3' is not known; choose one of ['rigid', 'body1', 'body2']"),
        ("euler", "occupant = 'body1' needs physics=continuous"),
    ],
)
def test_bad_occupant_is_one_line(runs, name, message):
    result = runs[name]
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], result.stderr
    assert not (runs["tmp"] / f"{'bad' if name == 'bad' else 'eu'}.h5").exists()
