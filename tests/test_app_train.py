"""qcm-train: configs compose, runs write their artefacts, evaluation/denoiser/multirun contracts, bad input fails early."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from conftest import TRAIN_SMALL as SMALL
from conftest import TRAIN_SMALL_NET as SMALL_NET
from conftest import train_config as _cfg
from hybridqcm.config import CONFIG_DIR, app_experiments, check_experiment_overrides
from hybridqcm.data.dataset_writer import DatasetWriter
from hybridqcm.errors import ConfigError
from hybridqcm.training import build_datamodule, prepare, train

BIN = Path(sys.executable).parent
TRAIN_EXPERIMENTS = app_experiments("train")


@pytest.fixture(scope="module")
def data(train_files):
    """The tiny training files (conftest.train_files: one per session, shared with the export and tracking tests)."""
    return train_files


@pytest.fixture(scope="module")
def trained(train_runs):
    """Short in-process runs of exp2 (physics CNN) and exp4 (CAE) (conftest.train_runs: one per session)."""
    return train_runs


# -- configs ---------------------------------------------------------------------------------------------------
def test_training_experiments_are_the_expected_ones():
    for name in ("exp1_labelled", "exp2_physics", "exp4_denoiser", "exp9_unet"):
        assert name in TRAIN_EXPERIMENTS and f"{name}_reference" in TRAIN_EXPERIMENTS


@pytest.mark.parametrize("experiment", TRAIN_EXPERIMENTS)
def test_every_experiment_composes_and_instantiates(experiment, tmp_path):
    cfg = _cfg([f"experiment={experiment}", "data.path=/nonexistent.h5"], tmp_path)
    assert cfg.task_name == experiment and cfg.trainer.accelerator == "auto"
    model = instantiate(cfg.model)
    datamodule = build_datamodule(cfg.data, model.data_requirements(), train=True)
    assert datamodule.window == model.data_requirements()["window"]
    assert cfg.optimized_metric.startswith("val/")


def test_search_launcher_and_debug_configs_compose(tmp_path):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=["experiment=exp1_labelled", "hparams_search=exp1_optuna", "launcher=joblib", "debug=fdr"],
            return_hydra_config=True,
        )
    assert "optuna" in cfg.hydra.sweeper._target_ and "joblib" in cfg.hydra.launcher._target_
    assert cfg.optimized_metric == "val/mean_rel_err" and cfg.trainer.fast_dev_run is True
    assert "model.lr_schedule.max_lr" in cfg.hydra.sweeper.params


# -- runs --------------------------------------------------------------------------------------------------
def test_physics_run_artefacts(trained):
    out = trained["exp2_physics"]
    assert (out / "checkpoints" / "last.ckpt").exists()
    with open(out / "predictions.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 32 and set(rows[0]) == {"index", "p1_true", "p1_pred", "p2_true", "p2_pred"}
    for name in ("error_distribution.csv", "error_distribution.md", "sorted_predictions_p1.png", "test_metrics.json"):
        assert (out / name).exists(), name
    summary = json.loads((out / "test_metrics.json").read_text())
    assert summary["n_test"] == 32 and summary["train_seconds"] > 0 and "test/p1/mean_rel_err" in summary["metrics"]
    assert summary["device"] == ("cuda:0" if torch.cuda.is_available() else "cpu")  # trainer.accelerator=auto
    assert list((out / "tensorboard").glob("events.out.tfevents.*"))


def test_denoiser_run_artefacts(trained):
    out = trained["exp4_denoiser"]
    for name in ("checkpoints/last.ckpt", "per_sample_mse.csv", "mse_summary.csv", "mse_hist_a3.png", "examples.png"):
        assert (out / name).exists(), name


def test_unet_run(data, tmp_path):
    metrics = train(
        _cfg(["experiment=exp9_unet", f"data.path={data['tiny']}", *SMALL, *SMALL_NET["exp9_unet"]], tmp_path)
    )
    assert "test/rel_mse" in metrics and (tmp_path / "checkpoints" / "last.ckpt").exists()
    with open(tmp_path / "mse_summary.csv") as handle:
        assert [r["channel"] for r in csv.DictReader(handle)] == ["a2", "a1"]


def test_cli_evaluates_checkpoint_on_other_file_with_noise_and_denoiser(data, trained, tmp_path):
    run_dir = tmp_path / "eval"
    command = [
        str(BIN / "qcm-train"),
        "experiment=exp2_physics",
        "train=false",
        f"ckpt_path={trained['exp2_physics']}/checkpoints/last.ckpt",
        f"data.path={data['other']}",
        "data.noise_sigma=0.05",
        f"denoiser_ckpt={trained['exp4_denoiser']}/checkpoints/last.ckpt",
        f"hydra.run.dir={run_dir}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((run_dir / "test_metrics.json").read_text())
    assert summary["noise_sigma"] == 0.05 and summary["denoiser_ckpt"].endswith("last.ckpt")
    assert summary["data_path"] == str(data["other"]) and summary["train"] is False
    assert (run_dir / "error_distribution.csv").exists()


def test_physics_cnn_is_tested_on_a_file_without_velocities_and_displacements(data, trained, tmp_path, caplog):
    """A logger's or another simulator's file stores accelerations and labels only. The same recordings
    with and without /vel, /disp (written here by a second writer) give the same predictions and errors;
    the run says the training loss's channels are missing."""
    import h5py

    bare = tmp_path / "bare.h5"
    with h5py.File(data["other"], "r") as src, DatasetWriter(bare) as writer:
        n, n_steps = src["test/accel"].shape[:2]
        writer.create_split("test", n, n_steps, keys=("accel", "road", "params"))
        writer.write("test", 0, **{k: src[f"test/{k}"][()] for k in ("accel", "road", "params")})
    ckpt = f"ckpt_path={trained['exp2_physics']}/checkpoints/last.ckpt"
    runs = {}
    for name, path in (("full", data["other"]), ("bare", bare)):
        with caplog.at_level("WARNING", logger="qcm-train"):
            caplog.clear()
            metrics = train(
                _cfg(["experiment=exp2_physics", "train=false", ckpt, f"data.path={path}"], tmp_path / name)
            )
        runs[name] = (metrics, caplog.text)
        with open(tmp_path / name / "predictions.csv") as handle:
            runs[name] += ([(r["p1_pred"], r["p2_pred"]) for r in csv.DictReader(handle)],)
    (full, full_log, full_pred), (bare_metrics, bare_log, bare_pred) = runs["full"], runs["bare"]
    assert "test/loss" in full and "test/loss" not in bare_metrics  # the residual loss needs the aux channels
    assert full_pred == bare_pred and len(bare_pred) == n
    for key in ("test/p1/mean_rel_err", "test/p2/max_rel_err"):
        assert bare_metrics[key] == pytest.approx(full[key], rel=1e-12)
    assert "testing without that loss" in bare_log and "testing without" not in full_log


def test_multirun_sweep_gets_one_folder_per_job_and_a_summary(data, tmp_path):
    sweep = tmp_path / "sweep"
    command = [
        str(BIN / "qcm-train"),
        "-m",
        "experiment=exp2_physics",
        f"data.path={data['tiny']}",
        "data.noise_sigma=0,0.05",
        *SMALL,
        *SMALL_NET["exp2_physics"],
        "callbacks=none",
        "logger=none",
        f"hydra.sweep.dir={sweep}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=400)
    assert result.returncode == 0, result.stderr[-3000:]
    for job in ("0", "1"):
        assert (sweep / job / "error_distribution.csv").exists()
    with open(sweep / "summary.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 and {r["overrides"].split("data.noise_sigma=")[1].split()[0] for r in rows} == {"0", "0.05"}


# -- bad input ------------------------------------------------------------------------------------------------
def test_unknown_and_non_training_experiments(tmp_path):
    with pytest.raises(
        ConfigError, match=r"^unknown experiment 'exp99' \(no configs/apps/train/experiment/exp99.yaml\); "
    ):
        check_experiment_overrides(["experiment=exp99"], "train")
    for app, name in (("train", "exp1_mine"), ("estimate", "exp5_gn")):
        (tmp_path / "apps" / app / "experiment").mkdir(parents=True)
        (tmp_path / "apps" / app / "experiment" / f"{name}.yaml").write_text("# @package _global_\n")
    with pytest.raises(
        ConfigError,
        match=r"^experiment 'exp5_gn' is a qcm-estimate experiment .*: run it with "
        r"qcm-estimate; qcm-train experiments: exp1_mine$",
    ):
        check_experiment_overrides(["experiment=exp5_gn"], "train", tmp_path)
    check_experiment_overrides(["experiment=exp1_mine"], "train", tmp_path)
    check_experiment_overrides(["experiment=exp1_labelled,exp2_physics"], "train")  # multirun lists are fine
    result = subprocess.run([str(BIN / "qcm-train"), "experiment=nope"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "unknown experiment 'nope'" in result.stderr


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["train=false"], "needs ckpt_path"),
        (["ckpt_path=/nonexistent/x.ckpt"], "does not exist"),
        (["denoiser_ckpt=/x.ckpt"], "at evaluation"),
        (["data.noise_sigma=-0.1"], "noise_sigma"),
        (["data.inputs=[a3,a1]"], "data.inputs"),
        (["data.inputs=[a3,zz]"], "data.inputs"),
        # issue 29: before, Hydra's instantiation error about Trainer(devices=0), a TypeError mid-fit
        (["trainer.devices=0"], r"^trainer.devices=0: give a number of devices >= 1, -1 \(all\), auto"),
        (["model.optimizer.lr=abc"], r"^model.optimizer.lr='abc': give a number$"),
        (["model.optimizer.lr=-1"], r"^model.optimizer \(torch.optim.Adam\): Invalid learning rate: -1"),
    ],
)
def test_bad_settings_fail_before_training(overrides, message, data, tmp_path):
    cfg = _cfg(["experiment=exp1_labelled", f"data.path={data['tiny']}", *overrides], tmp_path)
    with pytest.raises(ConfigError, match=message):
        train(cfg)
    assert not (tmp_path / "checkpoints").exists()


def test_bad_data_and_checkpoints_fail_before_training(data, trained, tmp_path):
    cases = [
        (["experiment=exp2_physics_reference", f"data.path={data['partial']}"], r"partial\.h5.*lacks.*disp"),
        (["experiment=exp1_labelled_reference", f"data.path={data['tiny']}", "data.window=600"], "window = 600"),
        (["experiment=exp1_labelled_reference", f"data.path={tmp_path}/missing.h5"], "does not exist"),
        (
            ["experiment=exp1_labelled", "train=false", f"ckpt_path={trained['exp4_denoiser']}/checkpoints/last.ckpt"],
            "holds a DenoisingAutoencoder model, expected LabelledEstimator",
        ),
        (
            [
                "experiment=exp9_unet",
                "train=false",
                f"ckpt_path={trained['exp2_physics']}/checkpoints/last.ckpt",
                f"denoiser_ckpt={trained['exp4_denoiser']}/checkpoints/last.ckpt",
            ],
            "holds a PhysicsResidualEstimator",
        ),
    ]
    for overrides, message in cases:
        with pytest.raises(ConfigError, match=message):
            prepare(_cfg(overrides, tmp_path))
