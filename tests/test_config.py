"""Bad inputs of issue 9: each is refused before any work with one line (exit code 2 in the apps)."""

from __future__ import annotations

import math
import os
import stat
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from hybridqcm import config
from hybridqcm.config import CONFIG_DIR, check_task_name
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.plan import validate
from hybridqcm.metrics import coverage_95
from hybridqcm.testing import synthetic_samples, write_dataset

SRC = str(Path(__file__).resolve().parents[1] / "src")


def _cfg(app, overrides):
    """As the app composes: the one-line refusals of its schema (estimation/settings.py) first."""
    config.check_schema_overrides(overrides, app)
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(app, overrides=list(overrides))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("validation")
    samples = synthetic_samples(6, n_steps=120, seed=3)
    good = write_dataset(root / "good.h5", samples)
    out = {"good": good}
    with h5py.File(root / "empty.h5", "w") as f:
        f.create_dataset("test/accel", shape=(0, 120, 3), dtype=np.float32)
        f.create_dataset("test/road", shape=(0, 120), dtype=np.float32)
    out["empty"] = root / "empty.h5"
    with h5py.File(root / "group.h5", "w") as f:
        f.create_group("test/accel").create_dataset("a3", data=np.zeros((6, 120), np.float32))
        f.create_dataset("test/road", data=samples["road"].numpy().astype(np.float32))
    out["group"] = root / "group.h5"
    params = samples["params"].numpy().copy()
    params[2, 4] = -params[2, 4]
    with h5py.File(root / "negative.h5", "w") as f:
        f.attrs["h"] = 0.01
        f.create_dataset("test/accel", data=samples["accel"].numpy().astype(np.float32))
        f.create_dataset("test/road", data=samples["road"].numpy().astype(np.float32))
        f.create_dataset("test/params", data=params)
    out["negative"] = root / "negative.h5"
    return out


@pytest.mark.parametrize(
    "key, overrides, error, message",
    [
        ("empty", [], DatasetError, r"/test is empty \(0 samples\)"),
        ("group", [], DatasetError, r"/test/accel is a Group, not an array"),
        ("good", ["n_samples=7"], ConfigError, r"n_samples=7 but .*good.h5 /test holds 6 samples"),
        ("good", ["+data.pathh=x.h5"], ConfigError, r"unknown setting data.pathh='x.h5'"),
        ("good", ["+foo=1"], ConfigError, r"unknown setting foo=1"),
        ("negative", [], DatasetError, r"/test/params\[2, 4\] \(p5\) = -[0-9.]+; parameters must be finite and > 0"),
        # issue 29: before, a traceback each (int('abc'), Lightning's MisconfigurationException)
        ("good", ["n_samples=abc"], ConfigError, r"^n_samples='abc': give a whole number or null$"),
        ("good", ["batch_size=2.5"], ConfigError, r"^batch_size=2.5: give a whole number$"),
        ("good", ["noise_sigma=x"], ConfigError, r"^noise_sigma='x': give a number$"),
        ("good", ["plots=maybe"], ConfigError, r"^plots='maybe': give true or false$"),
        ("good", ["trainer.devices=0"], ConfigError, r"^trainer.devices=0: give a number of devices >= 1"),
        ("good", ["+trainer.num_nodes=0"], ConfigError, r"^trainer.num_nodes=0: give a number of nodes >= 1$"),
        ("good", ["skip_windows.min_std=-1"], ConfigError, r"^skip_windows: min_std must be a finite number >= 0"),
    ],
)
def test_estimate_refuses_before_any_work(files, key, overrides, error, message):
    with pytest.raises(error, match=message) as info:
        validate(_cfg("estimate", ["experiment=exp5_random_init", f"data.path={files[key]}", *overrides]))
    assert "\n" not in str(info.value)


def test_n_samples_equal_to_the_split_is_fine(files):
    assert (
        validate(_cfg("estimate", ["experiment=exp5_random_init", f"data.path={files['good']}", "n_samples=6"]))[
            "n_samples"
        ]
        == 6
    )


def test_read_only_run_folder_is_found_before_solving(files, tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    run = tmp_path / "ro"
    run.mkdir()
    run.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        result = subprocess.run(
            [
                sys.executable,
                "-c",
                "from hybridqcm.apps.estimate import main; main()",
                "experiment=exp5_random_init",
                f"data.path={files['good']}",
                f"hydra.run.dir={run}",
                "progress=false",
            ],
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": SRC},
        )
    finally:
        run.chmod(0o755)
    assert result.returncode == 2 and "not writable" in result.stderr


def test_read_only_run_folder_check(tmp_path, monkeypatch):
    """The writability probe itself (runs as root too: the probe's failure is simulated)."""

    def deny(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Path, "write_text", deny)
    with pytest.raises(ConfigError, match=r"hydra.run.dir=.*: run folder is not writable \(Permission denied\)"):
        config.check_writable_dir(tmp_path / "run")


@pytest.mark.parametrize("name", ["../../x", "a/b", "..", ""])
def test_task_name_must_be_a_plain_folder_name(name):
    with pytest.raises(ConfigError, match="task_name="):
        check_task_name(name)


def test_task_name_traversal_is_refused_by_the_app(tmp_path):
    result = subprocess.run(
        [sys.executable, "-c", "from hybridqcm.apps.estimate import main; main()", "task_name=../../escaped"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": SRC},
    )
    assert result.returncode == 2 and "task_name='../../escaped'" in result.stderr
    assert not (tmp_path.parent / "escaped").exists() and not (tmp_path / "outputs").exists()


def test_train_logger_none_with_lr_monitor_is_one_line(tmp_path):
    """logger=none switches the LR monitor off with it (configs/logger/none.yaml); a monitor put back
    by hand without a logger is one line before any work."""
    from omegaconf import OmegaConf

    from hybridqcm.training import check_logger_callbacks

    overrides = [
        "experiment=exp1_labelled",
        "logger=none",
        f"paths.output_dir={tmp_path}",
        f"paths.root_dir={tmp_path}",
    ]
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        fine = compose("train", overrides=overrides)
    check_logger_callbacks(fine)
    assert fine.callbacks.get("lr_monitor") is None
    forced = OmegaConf.merge(
        fine, {"callbacks": {"lr_monitor": {"_target_": "lightning.pytorch.callbacks.LearningRateMonitor"}}}
    )
    with pytest.raises(ConfigError, match=r"callbacks.lr_monitor \(LearningRateMonitor\) needs a logger"):
        check_logger_callbacks(forced)


def test_simulate_checks(tmp_path):
    from hybridqcm.data.simulate_run import check_splits, check_step

    check_step(0.01)
    with pytest.raises(ValueError, match=r"h=10.0: the Euler step is unstable"):
        check_step(10.0)
    with pytest.raises(ValueError, match=r"splits.test.profiles = .*every count is 0"):
        check_splits({"train": {"profiles": {"A": 1}}, "test": {"profiles": {"A": 0, "B": 0}}})


def test_coverage_counts_diverged_and_non_finite_as_not_covered():
    truth = torch.ones(4, dtype=torch.float64)
    estimate = torch.tensor([1.0, 1.0, math.nan, 1.0], dtype=torch.float64)
    std = torch.tensor([0.1, math.inf, 0.1, 0.1], dtype=torch.float64)
    failed = torch.tensor([False, False, False, True])
    # only sample 0 is covered: 1 has infinite std, 2 a NaN estimate, 3 diverged
    assert coverage_95(estimate, truth, std, failed) == 0.25
    assert (
        coverage_95(estimate, truth, torch.full((4,), math.inf, dtype=torch.float64), torch.ones(4, dtype=bool)) == 0.0
    )


def test_summary_reports_the_converged_answers_beside_all(tmp_path):
    """A flagged wrong basin (misfit, occupant 1 000x too heavy) dominates the mean over all recordings;
    the converged-only mean and max are those of the converged rows, computed here by hand from m3 = K3/p2."""
    from omegaconf import OmegaConf

    from hybridqcm.estimation.solver import SolverStatus
    from hybridqcm.physics import reference_params
    from hybridqcm.reports.estimate import write_metrics

    true = reference_params().repeat(4, 1).double()
    params = true.clone()
    params[:, 1] *= torch.tensor([1.01, 0.001, 0.98, 1.0], dtype=torch.float64)
    codes = [SolverStatus.CONVERGED, SolverStatus.MISFIT, SolverStatus.CONVERGED, SolverStatus.DIVERGED]
    columns = {
        "params": params,
        "std": 0.01 * true,
        "status": torch.tensor([int(c) for c in codes]),
        "iterations": torch.ones(4),
        "restarts": torch.zeros(4),
    }
    cfg = OmegaConf.create({"K3": 98935.0, "experiment_name": "t", "n_steps": 10, "plots": False, "tensorboard": False})
    summary, _ = write_metrics(cfg, columns, true, [], tmp_path)
    converged_err = [abs(1 / 1.01 - 1), abs(1 / 0.98 - 1)]  # m3 = K3 / p2
    assert summary["m3_mean_rel_err_converged"] == pytest.approx(np.mean(converged_err), rel=1e-12)
    assert summary["m3_max_rel_err_converged"] == pytest.approx(max(converged_err), rel=1e-12)
    # over all: the misfit's 999 dominates; the diverged row's last iterate counts with its error (0 here)
    assert summary["m3_mean_rel_err"] == pytest.approx(np.mean([*converged_err, 1 / 0.001 - 1, 0.0]), rel=1e-12)
    codes = torch.full((4,), int(SolverStatus.MISFIT))
    summary, _ = write_metrics(cfg, {**columns, "status": codes}, true, [], tmp_path)
    assert summary["m3_mean_rel_err_converged"] is None and summary["m3_max_rel_err_converged"] is None


def test_train_refuses_unknown_top_level_keys(tmp_path):
    from hybridqcm.training import check_top_level_keys

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        bad = compose("train", overrides=["experiment=exp1_labelled", "+ckpt_pth=x.ckpt"])
        good = compose("train", overrides=["experiment=exp1_labelled", "hparams_search=exp1_optuna", "debug=fdr"])
    with pytest.raises(ConfigError, match=r"unknown setting ckpt_pth='x.ckpt'"):
        check_top_level_keys(bad)
    check_top_level_keys(good)
