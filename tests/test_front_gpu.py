"""qcm-estimate with the networks on a GPU: the same estimates as on the CPU. Skipped without CUDA
(CI has none); run on a GPU machine (docs/measurements/scaling.md, "On a GPU")."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir

from conftest import assert_same_answer
from hybridqcm.apps.estimate import run
from hybridqcm.config import CONFIG_DIR
from hybridqcm.estimation.front import HybridEstimator, equation_error_params
from hybridqcm.testing import synthetic_samples, train_tiny_checkpoints

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _cfg(overrides):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("estimate", overrides=list(overrides))


def test_equation_error_init_runs_on_the_inputs_device():
    s = synthetic_samples(4, n_steps=100, seed=1)
    fallback, known = s["params"] * 1.1, torch.zeros(10, dtype=torch.bool)
    cpu = equation_error_params(s["accel"], s["road"], 0.01, fallback, known)
    gpu = equation_error_params(s["accel"].cuda(), s["road"].cuda(), 0.01, fallback.cuda(), known.cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-9, atol=0)


def test_the_networks_start_on_the_gpu_is_the_cpu_start(tmp_path):
    ckpt = train_tiny_checkpoints(tmp_path, synthetic_samples(32, n_steps=160, seed=0), steps=3, window=128)
    s = synthetic_samples(64, n_steps=160, seed=5)
    batch = {"accel": s["accel"], "road": s["road"], "pu": s["params"][:, 9] - s["params"][:, 8]}
    batch.update(init=s["params"].clone(), index=torch.arange(64))
    module = HybridEstimator(cnn_ckpt=str(ckpt["cnn"]), unet_ckpt=str(ckpt["unet"]), observed=["a3"], n_steps=100)
    cpu = module.prepare(batch)
    gpu = module.cuda().prepare({k: v.cuda() for k, v in batch.items()})
    for key in ("init", "targets"):  # the CNN's p1, p2; the U-Net's a2, a1 (float32 rounding apart)
        torch.testing.assert_close(gpu[key].cpu(), cpu[key], rtol=1e-5, atol=1e-5 * float(cpu[key].abs().max()))


def test_exp10_on_the_gpu_gives_the_cpu_estimates(tiny_dataset, tmp_path, monkeypatch):
    ckpt = train_tiny_checkpoints(tmp_path / "ckpt", synthetic_samples(32, n_steps=160, seed=0), steps=3, window=128)
    devices = []
    prepare = HybridEstimator.prepare

    def recording(self, batch):
        devices.append((batch["accel"].device.type, next(self.cnn.parameters()).device.type))
        return prepare(self, batch)

    monkeypatch.setattr(HybridEstimator, "prepare", recording)
    common = [
        "experiment=exp10_hybrid",
        f"data.path={tiny_dataset}",
        f"cnn_ckpt={ckpt['cnn']}",
        f"unet_ckpt={ckpt['unet']}",
        "n_samples=16",
        "batch_size=8",
        "progress=false",
        "plots=false",
        "tensorboard=false",
    ]
    for accelerator in ("cpu", "gpu"):
        (tmp_path / accelerator).mkdir()
        monkeypatch.chdir(tmp_path / accelerator)  # the run's folder when Hydra is not running
        summary = run(_cfg([*common, f"trainer.accelerator={accelerator}"]))
        assert summary["predict_devices"] == (["cuda:0"] if accelerator == "gpu" else ["cpu"])
    assert devices == [("cpu", "cpu")] * 2 + [("cuda", "cuda")] * 2  # 2 blocks each; networks where the batch is
    assert_same_answer(tmp_path / "gpu" / "estimates.csv", tmp_path / "cpu" / "estimates.csv", rtol=1e-6)


@pytest.mark.parametrize(
    ("experiment", "within"),
    [
        # the exact model, x0 unknown, restarts; noise-free: every fit ends at the rounding floor
        (["experiment=exp5_random_init", "n_samples=8"], {"rtol": 1e-7}),
        # the noise model and intervals: fits end at the solver's tolerance, so the device may move them, by far
        # less than their uncertainty (CPU kernels against torch's: tests/test_app_estimate.py, 4e-5 of it)
        (
            ["experiment=exp8_occupant_only", "n_samples=8", "noise_sigma=0.05", "init.cnn=false"],
            {"std_fraction": 1e-3},
        ),
    ],
    ids=["exp5", "exp8_noise"],
)
def test_gauss_newton_on_the_gpu_gives_the_cpu_estimates(experiment, within, tmp_path, monkeypatch):
    from conftest import make_foreign

    data = tmp_path / "foreign.h5"
    make_foreign(data, n=8, seed=3)
    common = [*experiment, f"data.path={data}", "batch_size=4", "progress=false", "plots=false", "tensorboard=false"]
    for where in ("cpu", "gpu"):
        (tmp_path / where).mkdir()
        monkeypatch.chdir(tmp_path / where)
        extra = ["trainer.accelerator=gpu", "gn_device=accelerator"] if where == "gpu" else []
        summary = run(_cfg([*common, *extra]))
        if where == "gpu":
            assert summary["gn_device"] == "accelerator" and summary["device_memory_mib"] > 0  # GN ran on the GPU
    assert_same_answer(tmp_path / "gpu" / "estimates.csv", tmp_path / "cpu" / "estimates.csv", **within)
