"""qcm-estimate with the networks on a GPU: the same estimates as on the CPU. Skipped without CUDA
(CI has none); run on a GPU machine (docs/measurements/scaling.md, "On a GPU")."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from hybridqcm.apps.estimate import run
from hybridqcm.config import CONFIG_DIR
from hybridqcm.estimation.front import HybridEstimator, equation_error_params
from hybridqcm.testing import synthetic_samples, train_tiny_checkpoints

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _cfg(overrides):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("estimate", overrides=list(overrides))


def _estimates(path):
    """(statuses, the estimate columns): parameters, m3, x0; not the intervals, which on these
    noise-free recordings sit at the rounding floor and follow GN's path, not only its end point."""
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    status = [r.pop("status") for r in rows]
    keep = [c for c in rows[0] if not c.startswith("std_") and c not in ("m3_std", "m3_low", "m3_high")]
    text = [c for c in keep if not _numeric(rows[0][c])]  # the chosen occupant model: compared as the status
    status = [(s, *(r[c] for c in text)) for s, r in zip(status, rows)] if text else status
    return status, np.array([[float(r[c]) for c in keep if c not in text] for r in rows])


def _numeric(value: str) -> bool:
    try:
        float(value)
    except ValueError:
        return False
    return True


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
    results = {}
    for accelerator in ("cpu", "gpu"):
        (tmp_path / accelerator).mkdir()
        monkeypatch.chdir(tmp_path / accelerator)  # the run's folder when Hydra is not running
        summary = run(_cfg([*common, f"trainer.accelerator={accelerator}"]))
        assert summary["predict_devices"] == (["cuda:0"] if accelerator == "gpu" else ["cpu"])
        results[accelerator] = _estimates(tmp_path / accelerator / "estimates.csv")
    assert devices == [("cpu", "cpu")] * 2 + [("cuda", "cuda")] * 2  # 2 blocks each; networks where the batch is
    (status_cpu, cpu), (status_gpu, gpu) = results["cpu"], results["gpu"]
    assert status_gpu == status_cpu
    np.testing.assert_allclose(gpu, cpu, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(
    "experiment",
    [
        ["experiment=exp5_random_init", "n_samples=8"],  # the exact model, x0 unknown, restarts
        [
            "experiment=exp8_occupant_only",
            "n_samples=8",
            "noise_sigma=0.05",
            "init.cnn=false",
        ],  # noise model, intervals
    ],
    ids=["exp5", "exp8_noise"],
)
def test_gauss_newton_on_the_gpu_gives_the_cpu_estimates(experiment, tmp_path, monkeypatch):
    from conftest import make_foreign

    data = tmp_path / "foreign.h5"
    make_foreign(data, n=8, seed=3)
    common = [*experiment, f"data.path={data}", "batch_size=4", "progress=false", "plots=false", "tensorboard=false"]
    results = {}
    for where in ("cpu", "gpu"):
        (tmp_path / where).mkdir()
        monkeypatch.chdir(tmp_path / where)
        extra = ["trainer.accelerator=gpu", "gn_device=accelerator"] if where == "gpu" else []
        summary = run(_cfg([*common, *extra]))
        if where == "gpu":
            assert summary["gn_device"] == "accelerator" and summary["device_memory_mib"] > 0  # GN ran on the GPU
        results[where] = _estimates(tmp_path / where / "estimates.csv")
    (status_cpu, cpu), (status_gpu, gpu) = results["cpu"], results["gpu"]
    assert status_gpu == status_cpu
    np.testing.assert_allclose(gpu, cpu, rtol=1e-7, atol=1e-9)
