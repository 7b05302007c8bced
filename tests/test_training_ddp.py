"""Training scales out by config: Lightning DDP with 2 CPU processes (spawn, gloo)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch

BIN = Path(sys.executable).parent


def test_two_process_ddp_training_on_cpu(tmp_path, tiny_dataset):
    run_dir = tmp_path / "ddp"
    command = [
        str(BIN / "qcm-train"),
        "experiment=exp2_physics",
        "trainer=ddp",
        "trainer.devices=2",
        "debug=short",
        f"data.path={tiny_dataset}",
        "data.samples_per_epoch=128",
        "data.val_samples=32",
        "data.batch_size=32",
        "model.net.channels=[8,8]",
        "model.net.hidden=[16,8]",
        "data.num_workers=0",
        f"hydra.run.dir={run_dir}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-4000:]
    assert (
        "distributed_backend=gloo" in log and "All distributed processes registered. Starting with 2 processes" in log
    )
    assert (run_dir / "checkpoints" / "last.ckpt").exists()
    checkpoint = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    # 2 epochs x 2 batches per rank (128 samples / 32 per batch / 2 ranks): each rank stepped on its own shard.
    assert checkpoint["global_step"] == 4
    metrics = json.loads((run_dir / "test_metrics.json").read_text())
    assert metrics["n_test"] > 0
