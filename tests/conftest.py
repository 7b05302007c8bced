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


def read_estimates(path):
    """estimates.csv -> (labels, values [n, k], stds [n, k]): labels per row are the status and any text column
    (the chosen occupant model); values are the estimate columns (parameters, m3, x0, not the intervals);
    stds are each one's standard deviation column (std_X or X_std), NaN where it has none."""
    import csv

    import numpy as np

    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    first = rows[0]
    text = [c for c in first if not _numeric(first[c])]
    keep = [
        c for c in first if c not in text and not c.startswith("std_") and not c.endswith(("_std", "_low", "_high"))
    ]
    labels = [tuple(r[c] for c in text) for r in rows]
    values = np.array([[float(r[c]) for c in keep] for r in rows])
    std_of = [f"std_{c}" if f"std_{c}" in first else f"{c}_std" if f"{c}_std" in first else None for c in keep]
    stds = np.array([[float(r[s]) if s else np.nan for s in std_of] for r in rows])
    return labels, values, stds


def _numeric(value: str) -> bool:
    try:
        float(value)
    except ValueError:
        return False
    return True


def assert_same_answer(path, reference, *, rtol=1e-7, std_fraction=None):
    """Two runs' estimates.csv give one answer: the same statuses (and chosen models), and each estimate within
    ``rtol`` of the reference's or, with ``std_fraction``, within the larger of that and this fraction of its own
    standard deviation (a fit stopped by a tolerance ends where the arithmetic's path takes it; the device or
    kernel must move it by far less than the data's uncertainty). NaN matches NaN only, inf the same inf."""
    import numpy as np

    labels, values, _ = read_estimates(path)
    ref_labels, ref_values, ref_stds = read_estimates(reference)
    assert labels == ref_labels
    tol = 1e-9 + rtol * np.abs(ref_values)
    if std_fraction is not None:
        tol = np.where(np.isfinite(ref_stds), np.maximum(tol, std_fraction * ref_stds), tol)
    with np.errstate(invalid="ignore"):
        close = (
            (values == ref_values) | (np.abs(values - ref_values) <= tol) | (np.isnan(values) & np.isnan(ref_values))
        )
    bad = ~close
    assert not bad.any(), (
        f"{int(bad.sum())} estimates apart, the largest by {np.abs(values - ref_values)[bad].max():.3g}"
    )


def app_in_process(app: str, run_dir: Path, *overrides: str) -> dict:
    """What `qcm-<app> overrides` runs (app: simulate or estimate), in this process: the configuration composed
    as the app composes it, run_dir the run folder; returns the run's summary. A console start (torch,
    Lightning, Hydra: 5-7 s of CPU) costs more than the tiny runs of the tests; each app keeps its console
    tests (test_app_simulate, test_app_estimate, ...)."""
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR

    paths = [f"paths.root_dir={run_dir}", f"paths.output_dir={run_dir}"]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(app, overrides=[*overrides, *paths])
    run_dir.mkdir(parents=True, exist_ok=True)
    if app == "simulate":
        from hybridqcm.data.simulate_run import run_simulation

        return run_simulation(cfg)
    if app == "estimate":
        from hybridqcm.apps.estimate import run

        return run(cfg, run_dir)
    raise ValueError(f"app_in_process: no in-process run for qcm-{app}")


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


# -- the training tests' files and short runs (test_app_train, test_export_files, test_tracking) -----------------
# Small nets and data so a run takes seconds.
TRAIN_SMALL = ["debug=short", "data.samples_per_epoch=64", "data.val_samples=32", "data.batch_size=32", "seed=1"]
TRAIN_SMALL_NET = {
    "exp1_labelled": ["model.net.channels=[8,8]", "model.net.hidden=[16,8]"],
    "exp2_physics": ["model.net.channels=[8,8]", "model.net.hidden=[16,8]"],
    "exp4_denoiser": ["model.net.channels=[4,8]", "model.net.kernel_size=9"],
    "exp9_unet": ["model.net.filters=[2,4]"],
}


def train_config(overrides, out_dir):
    """qcm-train's configuration composed in-process, writing under out_dir."""
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=[*overrides, f"paths.root_dir={out_dir}", f"paths.output_dir={out_dir}"])


def _train_tiny(path, seed=0):
    from test_datamodules import make_tiny_dataset  # the tests' tiny dataset, one definition

    return make_tiny_dataset(path, seed=seed)


@pytest.fixture(scope="session")
def train_files(tmp_path_factory) -> dict:
    """tiny.h5 and other.h5 (seeds 0, 1: 48 train / 32 test samples, 512 steps), partial.h5 (no disp/vel)
    and the root folder they lie in; written once per session, never modified."""
    import numpy as np

    from hybridqcm.data.dataset_writer import DatasetWriter

    root = tmp_path_factory.mktemp("app")
    partial = root / "partial.h5"
    with DatasetWriter(partial) as writer:
        for split in ("train", "test"):
            writer.create_split(split, 8, 512, keys=("accel", "road", "params"))
            writer.write(
                split,
                0,
                accel=np.random.rand(8, 512, 3).astype(np.float32),
                road=np.zeros((8, 512), np.float32),
                params=np.ones((8, 10)),
            )
    return {
        "tiny": _train_tiny(root / "tiny.h5"),
        "other": _train_tiny(root / "other.h5", seed=1),
        "partial": partial,
        "root": root,
    }


@pytest.fixture(scope="session")
def train_runs(train_files) -> dict:
    """Short in-process runs of exp2 (physics CNN) and exp4 (CAE); returns their run folders."""
    from hybridqcm.training import train

    runs = {}
    for exp in ("exp2_physics", "exp4_denoiser"):
        out = train_files["root"] / exp
        overrides = [f"experiment={exp}", f"data.path={train_files['tiny']}", *TRAIN_SMALL, *TRAIN_SMALL_NET[exp]]
        assert train(train_config(overrides, out))
        runs[exp] = out
    return runs
