"""qcm-simulate end to end, run as a subprocess (Hydra), including its bad-input behaviour."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import app_in_process
from hybridqcm.data.hdf5 import LAYOUT, SCHEMA, dataset_info, read_split


def _command(tmp_path: Path, overrides, output: Path | None, run_name: str) -> list[str]:
    script = Path(sys.executable).parent / "qcm-simulate"
    command = [str(script)] if script.exists() else [sys.executable, "-m", "hybridqcm.apps.simulate"]
    output = output if output is not None else tmp_path / "data" / "out.h5"
    return command + ["preset=tiny", f"output={output}", f"hydra.run.dir={tmp_path / run_name}", *overrides]


ENV = {**os.environ, "COLUMNS": "160", "PYTHONWARNINGS": "ignore"}


def qcm_simulate(
    tmp_path: Path, *overrides: str, output: Path | None = None, run_name: str = "run", timeout: float = 120
) -> subprocess.CompletedProcess:
    return subprocess.run(
        _command(tmp_path, overrides, output, run_name),
        capture_output=True,
        text=True,
        timeout=timeout,
        env=ENV,
        cwd=tmp_path,
    )


def test_tiny_preset_writes_a_valid_dataset(tmp_path):
    result = qcm_simulate(tmp_path)
    assert result.returncode == 0, result.stderr
    out = tmp_path / "data" / "out.h5"
    info = dataset_info(out)
    assert info["attrs"]["schema"] == SCHEMA and info["attrs"]["prior"] == "thesis"
    assert info["attrs"]["h"] == 0.01 and info["attrs"]["n_steps"] == 512
    assert info["attrs"]["speed_mps"] == pytest.approx(30 / 3.6)
    assert info["splits"]["train"]["n_samples"] == 48 and info["splits"]["test"]["n_samples"] == 32
    for split in ("train", "test"):
        assert info["splits"][split]["keys"] == sorted(LAYOUT)
        data = read_split(out, split, tuple(LAYOUT))
        for key, (dtype, _) in LAYOUT.items():
            assert data[key].dtype == dtype, key
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["train"]["per_class"] == {"A": 24, "B": 16, "C": 8}
    assert 0.4 < summary["train"]["prior_acceptance_rate"] < 0.9
    assert "prior acceptance" in result.stdout and "parameter ranges" in result.stdout
    assert [p.name for p in (tmp_path / "data").iterdir()] == ["out.h5"]


def test_same_seed_gives_byte_identical_arrays(tmp_path, monkeypatch):
    """The seed fixes every draw; the arithmetic is byte-identical at one BLAS thread count (a threaded GEMM's
    sums are split by its threads, and MKL may change their number under load: 1 ulp of float32 in a3
    between two runs of the full suite). One thread here, as the README says for byte-exact data."""
    a, b, c = tmp_path / "a.h5", tmp_path / "b.h5", tmp_path / "c.h5"
    monkeypatch.setitem(ENV, "OMP_NUM_THREADS", "1")
    monkeypatch.setitem(ENV, "MKL_NUM_THREADS", "1")
    for path, seed, run in ((a, 7, "ra"), (b, 7, "rb"), (c, 8, "rc")):
        result = qcm_simulate(tmp_path, f"seed={seed}", "n_steps=128", output=path, run_name=run)
        assert result.returncode == 0, result.stderr
    with h5py.File(a) as fa, h5py.File(b) as fb, h5py.File(c) as fc:
        for split in ("train", "test"):
            for key in LAYOUT:
                xa, xb = fa[split][key][()], fb[split][key][()]
                assert xa.dtype == xb.dtype and xa.tobytes() == xb.tobytes(), (split, key)
            assert not np.array_equal(fa[split]["params"][()], fc[split]["params"][()])
        assert fa.attrs["seed"] == 7 and fc.attrs["seed"] == 8


BAD_INPUTS = [
    ("+splits.train.profiles.Z=3", "unknown road class 'Z'"),
    ("splits.test.profiles.B=-2", "splits.test.profiles.B must be a non-negative integer, got -2"),
    ("samples_per_profile=-1", "samples_per_profile must be >= 1, got -1"),
    ("n_steps=0", "n_steps must be >= 1, got 0"),
    ("h=0", "h must be > 0, got 0"),
    ("h=-0.01", "h must be > 0, got -0.01"),
    ("speed_kmh=-30", "speed_kmh must be > 0"),
    ("prior=nope", "unknown prior 'nope'"),
    ("profiles_per_chunk=0", "profiles_per_chunk must be >= 1, got 0"),
    ("integrator=euler", "unknown integrator 'euler'"),
    ("prior_options.sigma=-0.5", "prior sigma must be >= 0"),
    ("physics=exact", "physics = 'exact' is not known; choose one of ['continuous', 'euler']"),
    ("window.warmup_s=[-1,2]", "window.warmup_s must be a range 0 <= low <= high"),
    ("window.warmup_s=[5,2]", "window.warmup_s must be a range 0 <= low <= high"),
    ("window.warmup_s=-3", "window.warmup_s must be a range 0 <= low <= high"),
]


# run on the console (Hydra, fail(): the whole stderr of a real process); the others go through the same
# run_simulation in-process and raise one of the errors qcm-simulate turns into its one-line `error:`
CONSOLE_BAD = ("+splits.train.profiles.Z=3", "prior=nope", "physics=exact", "window.warmup_s=[5,2]")


@pytest.fixture(scope="module")
def bad_runs(tmp_path_factory) -> dict[str, tuple[Path, int, str]]:
    """The console's bad-input runs, two at a time (they are independent and mostly interpreter start-up)."""
    from concurrent.futures import ThreadPoolExecutor

    def one(item):
        i, override = item
        folder = tmp_path_factory.mktemp(f"bad{i}")
        result = qcm_simulate(folder, override)
        return override, (folder, result.returncode, result.stderr)

    with ThreadPoolExecutor(max_workers=2) as pool:
        return dict(pool.map(one, enumerate(CONSOLE_BAD)))


def _bad_in_process(folder: Path, override: str) -> str:
    """run_simulation on tiny + override, composed as qcm-simulate composes it -> the error's message."""
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.data.simulate_run import run_simulation
    from hybridqcm.errors import ConfigError

    paths = [f"paths.root_dir={folder}", f"paths.output_dir={folder / 'run'}", f"output={folder / 'data' / 'out.h5'}"]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("simulate", overrides=["preset=tiny", *paths, override])
    with pytest.raises((ValueError, FileExistsError, OSError, ConfigError)) as error:  # the ones the app catches
        run_simulation(cfg)
    return str(error.value)


@pytest.mark.parametrize("override,message", BAD_INPUTS)
def test_bad_input_fails_cleanly(bad_runs, tmp_path, override, message):
    if override in bad_runs:
        folder, returncode, stderr = bad_runs[override]
        assert returncode != 0
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert lines and lines[-1].startswith("error:"), stderr
        assert message in lines[-1], lines[-1]
        assert "Traceback" not in stderr
    else:
        folder = tmp_path
        error = _bad_in_process(folder, override)
        assert message in error and "\n" not in error, error
    data_dir = folder / "data"
    assert not data_dir.exists() or list(data_dir.iterdir()) == [], "no output or temporary file may be left"


def test_refuses_to_overwrite_existing_output(tmp_path):
    out = tmp_path / "data" / "out.h5"
    out.parent.mkdir()
    out.write_bytes(b"keep me")
    result = qcm_simulate(tmp_path)
    assert result.returncode != 0
    assert "exists; pass overwrite=true" in result.stderr and "Traceback" not in result.stderr
    assert out.read_bytes() == b"keep me"
    result = qcm_simulate(tmp_path, "overwrite=true", "n_steps=32")
    assert result.returncode == 0, result.stderr
    assert dataset_info(out)["splits"]["test"]["n_steps"] == 32


@pytest.mark.parametrize("h", [0.005, 0.002, 0.001])
def test_logger_rates_continuous_mid_drive(tmp_path, h):
    n_steps = int(round(0.64 / h))  # the same 0.64 s window at every rate
    out = tmp_path / "data" / "out.h5"
    # qcm-simulate's run in-process (the console: the other tests of this file)
    app_in_process("simulate", tmp_path / "run", "preset=tiny", f"output={out}", f"h={h}", f"n_steps={n_steps}",
                   "samples_per_profile=2", "progress=false")  # fmt: skip
    info = dataset_info(out)
    assert info["physics"] == "continuous" and info["initial_state"] == "mid-drive"
    assert info["attrs"]["h"] == h and info["attrs"]["warmup_s"] == [2.0, 20.0]
    data = read_split(out, "test", ("accel", "vel", "disp", "state0"))
    assert data["accel"].shape[1] == n_steps
    np.testing.assert_allclose(
        data["state0"], np.concatenate([data["vel"][:, 0], data["disp"][:, 0]], -1), rtol=1e-6, atol=1e-9
    )
    assert np.abs(data["state0"]).min(0).max() > 0  # windows start while moving
    # the signal is the same physical process at every rate: accel RMS within a factor 2 of 100 Hz
    assert 0.02 < float(np.sqrt((data["accel"][..., 0] ** 2).mean())) < 1.0


def test_euler_from_rest_keeps_the_source_protocol(tmp_path):
    out = tmp_path / "data" / "out.h5"
    app_in_process("simulate", tmp_path / "run", "preset=tiny", f"output={out}", "physics=euler", "n_steps=64",
                   "progress=false")  # fmt: skip
    info = dataset_info(tmp_path / "data" / "out.h5")
    assert info["physics"] == "euler" and info["initial_state"] == "rest"
    assert info["attrs"]["integrator"] == "semi_explicit_euler" and info["attrs"]["warmup_s"] == [0.0, 0.0]
    data = read_split(tmp_path / "data" / "out.h5", "train", ("accel", "state0"))
    assert not data["state0"].any() and np.abs(data["accel"][:, 0, :2]).max() == 0
