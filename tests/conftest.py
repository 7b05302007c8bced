"""Shared fixtures.

`tiny_dataset` is a session-scoped HDF5 file in the SPEC §5 layout written once with
`write_dataset` (train: 48 samples, test: 40 samples, 512 steps, thesis prior, seed 0);
any test may read it, none may modify it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

TINY_SPLITS = {
    "train": {"profiles": {"A": 3, "B": 2, "C": 1}},  # 6 profiles x 8 draws = 48 samples
    "test": {"profiles": {"A": 2, "B": 2, "C": 1}},  # 5 profiles x 8 draws = 40 samples
}
TINY_SAMPLES_PER_PROFILE = 8
TINY_N_STEPS = 512
TINY_H = 0.01
TINY_SPEED_MPS = 30.0 / 3.6
TINY_SEED = 0


def write_tiny_dataset(path: Path, seed: int = TINY_SEED, **overrides) -> dict:
    """Write the tiny dataset to `path`; returns write_dataset's per-split summaries."""
    from hybridqcm.data.simulate import write_dataset
    from hybridqcm.physics.prior import build_prior
    from hybridqcm.physics.road import RoadProfile

    kwargs = dict(
        splits=TINY_SPLITS,
        prior=build_prior("thesis", h=TINY_H),
        road_profile=RoadProfile(),
        n_steps=TINY_N_STEPS,
        h=TINY_H,
        speed_mps=TINY_SPEED_MPS,
        samples_per_profile=TINY_SAMPLES_PER_PROFILE,
        seed=seed,
        progress=False,
        profiles_per_chunk=2,
    )
    kwargs.update(overrides)
    return write_dataset(path, **kwargs)


def tiny_datamodule(path, module, **kwargs):
    """The HDF5 datamodule a module asks for (its data_requirements) on a tiny file: batches of 8,
    evaluation batches of 16, a quarter of the training split for validation."""
    from hybridqcm.data.datamodules import HDF5DataModule

    req = module.data_requirements()
    return HDF5DataModule(
        path,
        inputs=req["inputs"],
        targets=req["targets"],
        aux=req["aux"],
        window=req["window"],
        batch_size=8,
        eval_batch_size=16,
        val_fraction=0.25,
        **kwargs,
    )


def make_foreign(path, n: int = 6, **options):
    """A file of the second simulator (bench/foreign_sim.py make, 512 steps; options as its flags, e.g.
    occupant="body1", delay_ms=5) -> its /test/truth_m3 [n]."""
    import importlib.util

    import h5py

    spec = importlib.util.spec_from_file_location("foreign_sim", REPO_ROOT / "bench" / "foreign_sim.py")
    fs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fs)
    args = ["make", "--out", str(path), "--n", str(n), "--steps", "512"]
    for key, value in options.items():  # a list or tuple: a flag of several values (known_loads=[0, 40])
        values = value if isinstance(value, (list, tuple)) else [value]
        args += [f"--{key.replace('_', '-')}", *map(str, values)]
    fs.main(args)
    with h5py.File(path, "r") as f:
        return f["test/truth_m3"][()]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """Path of a small read-only dataset: /train (48 samples) and /test (40 samples), n_steps = 512."""
    path = tmp_path_factory.mktemp("tiny_dataset") / "tiny.h5"
    write_tiny_dataset(path)
    path.chmod(0o444)
    return path
