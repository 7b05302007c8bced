"""qcm-estimate at scale: streamed blocks, 2 processes (gloo), shards, restart, refusal, atomic merge."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from hybridqcm.apps.estimate import run
from hybridqcm.config import CONFIG_DIR
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.blocks import RankBlocks, block_rows, build_inputs
from hybridqcm.estimation.draws import NormalStream
from hybridqcm.estimation.plan import validate
from hybridqcm.estimation.shards import ShardStore
from hybridqcm.physics.parameters import PhysicalConstants

BIN = Path(sys.executable).parent
# the rigid occupant on one clock: these tests are about blocks, shards and processes, not the occupant models
ROADFREE = [
    "experiment=occupant_roadfree",
    "occupant.models=[rigid]",
    "delay=null",
    "progress=false",
    "plots=false",
    "tensorboard=false",
]


def _cfg(overrides):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("estimate", overrides=list(overrides))


def _estimates(path: Path) -> tuple[list[str], np.ndarray, list[str]]:
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    header, body = rows[0], rows[1:]
    status_col = header.index("status")
    numbers = np.array([[float(x) for j, x in enumerate(r) if j != status_col] for r in body])
    return header, numbers, [r[status_col] for r in body]


@pytest.mark.parametrize("total", [5, 16, 40, 333, 4096 * 3 + 7])
def test_normal_stream_slices_are_torch_randn_bit_for_bit(total):
    reference = torch.randn(total, generator=torch.Generator().manual_seed(11), dtype=torch.float64).numpy()
    stream = NormalStream(11, total)
    rng = np.random.default_rng(total)
    cuts = sorted({0, total, *rng.integers(0, total, 6).tolist()})
    pieces = [stream.take(a, b) for a, b in zip(cuts, cuts[1:])]
    assert np.array_equal(np.concatenate(pieces), reference)
    assert np.array_equal(stream.take(1, min(total, 4)), reference[1:4])  # a step back rewinds


@pytest.mark.parametrize(
    "n, size", [(17000, 4096), (170000, 4096), (24, 8), (16, 8), (5, 8), (4097, 4096), (3, 1), (1, 1)]
)
def test_blocks_cover_every_row_once_and_split_equally_over_power_of_two_processes(n, size):
    blocks = block_rows(n, size)
    rows = [r for a, b in blocks for r in range(a, b)]
    assert rows == list(range(n))  # contiguous, in order, each row once
    sizes = [b - a for a, b in blocks]
    assert max(sizes) <= size and max(sizes) - min(sizes) <= 1
    for world in (1, 2, 4, 8):  # rank r takes blocks r, r + world, ... (Lightning's predict sampler)
        if len(blocks) % world == 0:
            shares = [sum(sizes[r::world]) for r in range(world)]
            assert max(shares) - min(shares) <= len(blocks) // world
    if n == 17000:
        assert [sum(sizes[r::2]) for r in range(2)] == [8500, 8500]  # was 8 808 / 8 192 in blocks of 4 096


def test_blocks_read_the_same_inputs_as_one_in_memory_draw(tiny_dataset):
    cfg = _cfg(
        ["experiment=exp5_random_init", f"data.path={tiny_dataset}", "n_samples=37", "noise_sigma=0.05", "seed=3"]
    )
    plan = validate(cfg)
    blocks = [build_inputs(cfg, plan, slice(a, min(a + 8, 37))) for a in range(0, 37, 8)]
    # The draws of the in-memory reading (one randn over the whole prefix), written out here.
    p_ref = PhysicalConstants(**{k: float(v) for k, v in cfg.vehicle.items()}).to_params()
    delta = 0.1 * torch.randn(37, 10, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    init = torch.where(p_ref * (1 + delta) > 0, p_ref * (1 + delta), p_ref.expand(37, 10))
    from hybridqcm.data.hdf5 import read_split

    raw = torch.from_numpy(read_split(tiny_dataset, "test", ["accel"], n_steps=plan["n_read_steps"])["accel"][:37])
    eta = torch.randn(raw.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    assert torch.equal(torch.cat([b["init"] for b in blocks]), init)
    assert torch.equal(torch.cat([b["accel"] for b in blocks]), raw.double() * (1 + 0.05 * eta))
    assert torch.equal(torch.cat([b["index"] for b in blocks]), torch.arange(37))


def _one_and_two_processes(overrides: list[str], tmp_path: Path) -> dict[str, Path]:
    """Run folders of qcm-estimate with ``overrides`` in one process ("one") and in two ("two", gloo)."""
    runs = {}
    for name, extra in {"one": [], "two": ["trainer=ddp", "trainer.devices=2"]}.items():
        command = [str(BIN / "qcm-estimate"), *overrides, *extra, f"hydra.run.dir={tmp_path / name}"]
        result = subprocess.run(command, capture_output=True, text=True, timeout=300)
        assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
        runs[name] = tmp_path / name
    return runs


def test_two_processes_give_the_single_process_estimates(tiny_dataset, tmp_path):
    """24 recordings in 4 blocks of 6: rank 0 solves blocks 0 and 2, rank 1 blocks 1 and 3 (gloo)."""
    common = [*ROADFREE, f"data.path={tiny_dataset}", "n_samples=24", "batch_size=8"]
    runs = _one_and_two_processes(common, tmp_path)
    assert json.loads((runs["two"] / "summary.json").read_text())["processes"] == 2
    header1, one, status1 = _estimates(runs["one"] / "estimates.csv")
    header2, two, status2 = _estimates(runs["two"] / "estimates.csv")
    assert header1 == header2 and status1 == status2
    assert one[:, 0].tolist() == list(range(24))  # every input row once, in input order
    np.testing.assert_allclose(two, one, rtol=1e-12, atol=0)
    assert not (runs["two"] / "shards").exists()  # merged, then removed


@pytest.mark.slow
def test_more_processes_than_blocks_leaves_a_rank_idle_not_failing(tiny_dataset, tmp_path):
    """One block on two ranks (a small file, or a resumed run with one block left): rank 1 has nothing
    to do. Lightning's own predict sampler asserted there; the run must give the single-process rows."""
    common = [*ROADFREE, f"data.path={tiny_dataset}", "n_samples=5", "batch_size=8"]
    runs = _one_and_two_processes(common, tmp_path)
    summary = json.loads((runs["two"] / "summary.json").read_text())
    assert summary["processes"] == 2 and summary["blocks"] == 1
    _, one, _ = _estimates(runs["one"] / "estimates.csv")
    _, two, _ = _estimates(runs["two"] / "estimates.csv")
    assert two[:, 0].tolist() == list(range(5))
    np.testing.assert_allclose(two, one, rtol=1e-12, atol=0)


def test_rank_blocks_deal_every_block_once():
    """Without a process group one process takes every block; under W ranks, rank r takes r, r + W, ..."""
    assert list(RankBlocks(5)) == [0, 1, 2, 3, 4] and len(RankBlocks(0)) == 0
    ranks = {}
    for rank in range(3):
        with (
            mock.patch.object(torch.distributed, "is_initialized", return_value=True),
            mock.patch.object(torch.distributed, "get_rank", return_value=rank),
            mock.patch.object(torch.distributed, "get_world_size", return_value=3),
        ):
            ranks[rank] = list(RankBlocks(4))
    assert ranks == {0: [0, 3], 1: [1], 2: [2]}
    assert sorted(sum(ranks.values(), [])) == [0, 1, 2, 3]


def test_restart_skips_finished_blocks_and_refuses_foreign_shards(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    overrides = [*ROADFREE, f"data.path={tiny_dataset}", "n_samples=20", "batch_size=8", "keep_shards=true"]
    first = run(_cfg(overrides))
    assert first["blocks"] == 4 and first["blocks_resumed"] == 0  # 4 blocks of 5
    assert first["predict_devices"] == ["cpu"]  # the default trainer=cpu
    reference = (tmp_path / "estimates.csv").read_bytes()
    shards = tmp_path / "shards"
    kept = (shards / "block-000000.csv").stat().st_mtime_ns

    def interrupt():  # what a run killed after blocks 0, 2 and 3 leaves: shards, no merged outputs
        for name in ("estimates.csv", "status.csv", "summary.json", "calibration.csv", "error_distribution.csv"):
            (tmp_path / name).unlink(missing_ok=True)
        (tmp_path / "error_distribution.md").unlink(missing_ok=True)
        (tmp_path / ".hybridqcm-done.json").unlink(missing_ok=True)

    interrupt()
    (shards / "block-000001.done.json").unlink()
    second = run(_cfg(overrides))
    assert second["blocks_resumed"] == 3
    assert (shards / "block-000000.csv").stat().st_mtime_ns == kept  # not solved again
    assert (tmp_path / "estimates.csv").read_bytes() == reference

    interrupt()
    with pytest.raises(ConfigError, match=r"block-000000\.done\.json: shard written by a different .*seed"):
        run(_cfg([*overrides, "seed=5"]))
    assert not (tmp_path / "estimates.csv").exists()


def test_merge_never_leaves_a_half_written_table(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    overrides = [*ROADFREE, f"data.path={tiny_dataset}", "n_samples=16", "batch_size=8", "keep_shards=true"]
    run(_cfg(overrides))
    store = ShardStore(
        tmp_path, json.loads((tmp_path / "shards" / "block-000000.done.json").read_text())["fingerprint"]
    )
    (tmp_path / "estimates.csv").unlink()
    with open(tmp_path / "shards" / "block-000001.csv", newline="") as handle:  # lose one row of block 1
        rows = list(csv.reader(handle))
    with open(tmp_path / "shards" / "block-000001.csv", "w", newline="") as handle:
        csv.writer(handle).writerows(rows[:3] + rows[4:])
    with pytest.raises(DatasetError, match=r"block-000001\.csv: sample 10 is missing"):
        store.merge([(0, 8), (8, 16)], 16)
    assert not (tmp_path / "estimates.csv").exists()
    assert not list(tmp_path.glob(".estimates.csv*"))  # the temporary file is gone too
    (tmp_path / "shards" / "block-000001.done.json").unlink()
    with pytest.raises(DatasetError, match=r"block 1 \(rows 8\.\.15\) was not estimated"):
        store.merge([(0, 8), (8, 16)], 16)


def test_cpu_ranks_are_forked_at_one_thread_and_other_accelerators_keep_their_strategy(tmp_path, monkeypatch):
    """trainer=ddp on CPU: the configured spawn becomes a fork (no fresh interpreter per rank) whose
    ranks run torch at one thread (GNU OpenMP is not fork-safe above that); on a GPU the configured
    strategy is kept (CUDA cannot be forked)."""
    from hybridqcm.estimation.runner import ForkedCPUDDP, build_trainer

    cpu = build_trainer(_cfg(["trainer=ddp", "trainer.devices=2"]), [], tmp_path)
    assert isinstance(cpu.strategy, ForkedCPUDDP) and cpu.strategy._start_method == "fork"
    assert cpu.strategy.process_group_backend == "gloo"
    from lightning.pytorch.strategies import DDPStrategy

    monkeypatch.setattr(DDPStrategy, "setup_environment", lambda self: None)  # no process group here
    threads = torch.get_num_threads()
    try:
        cpu.strategy.setup_environment()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
    cfg = _cfg(["trainer=ddp", "trainer.devices=2", "trainer.accelerator=gpu"])
    from hybridqcm.estimation import runner

    strategy = runner.instantiate(cfg.trainer.strategy)
    assert not isinstance(strategy, ForkedCPUDDP) and strategy._start_method == "spawn"
    assert not runner._resolves_to_cpu("gpu") and runner._resolves_to_cpu("cpu")


def test_gn_device_is_cpu_or_the_accelerator_and_named_when_wrong(tiny_dataset, tmp_path, monkeypatch):
    from hybridqcm.estimation.runner import gn_on_device

    build = object()
    assert gn_on_device(_cfg([*ROADFREE]), lambda: build) is None  # the default: GN on the CPU
    assert gn_on_device(_cfg([*ROADFREE, "gn_device=accelerator"]), lambda: build)() is build
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"^gn_device='gpu': choose one of \['cpu', 'accelerator'\]$"):
        run(_cfg([*ROADFREE, f"data.path={tiny_dataset}", "n_samples=2", "gn_device=gpu"]))
    assert not (tmp_path / "estimates.csv").exists()
    # the road-free occupant fit is not validated on a GPU: refused before any work, wherever it would run
    with pytest.raises(ConfigError, match=r"^gn_device=accelerator: only the road-driven quarter car's"):
        run(_cfg([*ROADFREE, f"data.path={tiny_dataset}", "n_samples=2", "gn_device=accelerator"]))
    assert not (tmp_path / "estimates.csv").exists()
