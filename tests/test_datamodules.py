"""Datamodules and channel selection: HDF5 (splits, window, noise, statistics, errors) and streaming (sharding)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from hybridqcm.data.batches import apply_noise
from hybridqcm.data.channels import ChannelError, required_keys, select_channels, select_params
from hybridqcm.data.datamodules import HDF5DataModule, StreamingDataModule
from hybridqcm.data.dataset_writer import DatasetWriter
from hybridqcm.data.simulate import simulate_samples, write_dataset
from hybridqcm.data.stream import SimulatedStream
from hybridqcm.errors import DatasetError
from hybridqcm.physics import RoadProfile, build_prior


def make_tiny_dataset(path, n_steps: int = 512, seed: int = 0):
    """48 train samples (6 profiles x 8) and 32 test samples (4 x 8)."""
    write_dataset(
        path,
        {"train": {"profiles": {"A": 3, "B": 2, "C": 1}}, "test": {"profiles": {"A": 2, "B": 1, "C": 1}}},
        build_prior("thesis", h=0.01),
        RoadProfile(n_waves=200),
        n_steps=n_steps,
        h=0.01,
        speed_mps=30 / 3.6,
        samples_per_profile=8,
        seed=seed,
        progress=False,
        compression=None,
    )
    return path


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("data") / "tiny.h5")


def test_channels_select_and_pu_u():
    generator = torch.Generator().manual_seed(0)
    arrays = simulate_samples(
        build_prior("thesis"), RoadProfile(n_waves=100), torch.tensor([0, 1]), 50, 0.01, 8.3, generator
    )
    x = select_channels(arrays, ["a3", "v2", "q1", "pu_u", "u"])
    assert x.shape == (2, 5, 50)
    assert torch.equal(x[:, 0], arrays["accel"][..., 0]) and torch.equal(x[:, 1], arrays["vel"][..., 1])
    assert torch.equal(x[:, 2], arrays["disp"][..., 2])
    gain = arrays["params"][:, 9] - arrays["params"][:, 8]
    assert torch.allclose(x[:, 3], gain[:, None] * arrays["road"])
    assert select_params(arrays, ["p2", "p1"]).shape == (2, 2)
    numpy_arrays = {k: v.numpy() for k, v in arrays.items() if isinstance(v, torch.Tensor)}
    assert isinstance(select_channels(numpy_arrays, ["a2"]), np.ndarray)
    assert required_keys(["pu_u", "a1"]) == {"road", "params", "accel"}
    with pytest.raises(ChannelError, match="a4"):
        select_channels(arrays, ["a3", "a4"])
    with pytest.raises(ChannelError, match="mixes"):
        required_keys(["a3", "p1"])


def test_hdf5_datamodule_splits_window_stats(tiny):
    dm = HDF5DataModule(
        tiny, inputs=["a3", "a2"], targets=["p1", "p2"], aux=["v3"], window=100, val_fraction=0.34, batch_size=8, seed=3
    )
    dm.setup()
    train, val = dm.data_train.tensors, dm.data_val.tensors
    assert train["x"].shape[1:] == (2, 100) and train["aux"].dtype == torch.float32
    assert len(dm.data_train) + len(dm.data_val) == 48 and len(dm.data_test) == 32
    # Validation takes whole road profiles: no profile on both sides.
    assert not set(train["profile_id"].tolist()) & set(val["profile_id"].tolist())
    again = HDF5DataModule(tiny, inputs=["a3", "a2"], targets=["p1", "p2"], window=100, val_fraction=0.34, seed=3)
    again.setup("fit")
    assert torch.equal(again.data_val.tensors["index"], val["index"])  # deterministic carve
    assert torch.allclose(dm.stats["input_mean"], train["x"].double().mean((0, 2)))
    assert torch.allclose(dm.stats["target_log_mean"], train["y"].log().mean(0))
    batch = next(iter(dm.train_dataloader()))
    assert batch["x"].shape == (8, 2, 100) and batch["y"].shape == (8, 2) and batch["params"].shape == (8, 10)
    assert dm.state_dict()["stats"]["input_std"].shape == (2,)


def test_hdf5_noise_fresh_for_train_fixed_for_eval(tiny):
    dm = HDF5DataModule(tiny, window=64, noise_sigma=0.1, batch_size=4, seed=1)
    dm.setup()
    clean = dm.data_train.tensors["x"][:4]
    first, second = dm.data_train.__getitems__([0, 1, 2, 3])["x"], dm.data_train.__getitems__([0, 1, 2, 3])["x"]
    assert not torch.equal(first, second)  # fresh noise every batch
    ratio = (first / clean - 1)[..., 5:]  # a = 0 at rest
    assert 0.05 < ratio.std() < 0.2  # multiplicative, sigma ~ 0.1
    v1, v2 = dm.data_test.__getitems__([0, 1])["x"], dm.data_test.__getitems__([0, 1])["x"]
    assert torch.equal(v1, v2)  # evaluation noise is fixed
    assert torch.equal(apply_noise(clean, 0.0), clean)


def test_hdf5_errors_name_file_key_value(tiny, tmp_path):
    with pytest.raises(ValueError, match="noise_sigma.*-0.1"):
        HDF5DataModule(tiny, noise_sigma=-0.1)
    with pytest.raises(ChannelError, match="bogus"):
        HDF5DataModule(tiny, inputs=["a3", "bogus"])
    with pytest.raises(DatasetError, match="window = 600.*512"):
        HDF5DataModule(tiny, window=600).setup("fit")
    with pytest.raises(DatasetError, match="does not exist"):
        HDF5DataModule(tmp_path / "nope.h5").setup("fit")
    # A file with only accel/road/params: channels needing vel/disp are refused, naming the file and keys.
    partial = tmp_path / "partial.h5"
    with DatasetWriter(partial) as writer:
        writer.create_split("train", 4, 50, keys=("accel", "road", "params"))
        writer.write(
            "train",
            0,
            accel=np.ones((4, 50, 3), np.float32),
            road=np.zeros((4, 50), np.float32),
            params=np.ones((4, 10)),
        )
    with pytest.raises(DatasetError, match=r"partial\.h5.*lacks.*'disp'.*'vel'"):
        HDF5DataModule(partial, aux=["a3", "v3", "v2", "q3", "q2"], window=50, val_fraction=0.25).setup("fit")
    dm = HDF5DataModule(partial, window=50, val_fraction=0.25)
    dm.setup("fit")  # what the task needs is there
    with pytest.raises(DatasetError, match="split 'test' not found"):
        dm.setup("test")


def _stream_params(dm: StreamingDataModule, loader: DataLoader) -> torch.Tensor:
    return torch.cat([batch["params"] for batch in loader])


def test_streaming_distinct_samples_per_worker_and_epoch():
    dm = StreamingDataModule(
        window=20, batch_size=8, samples_per_epoch=32, val_samples=8, test_samples=8, num_workers=2, seed=5
    )
    dm.setup("fit")
    loader = dm.train_dataloader()
    epoch1 = _stream_params(dm, loader)
    epoch2 = _stream_params(dm, loader)
    assert epoch1.shape == (32, 10)  # 4 batches split over 2 workers
    both = torch.cat([epoch1, epoch2])
    assert torch.unique(both, dim=0).shape[0] == 64  # no repeats across workers or epochs
    # Without workers the per-pass counter gives fresh samples too.
    dm0 = StreamingDataModule(window=20, batch_size=8, samples_per_epoch=16, val_samples=8, num_workers=0, seed=5)
    dm0.setup("fit")
    a, b = _stream_params(dm0, dm0.train_dataloader()), _stream_params(dm0, dm0.train_dataloader())
    assert torch.unique(torch.cat([a, b]), dim=0).shape[0] == 32


def test_streaming_replay_reuses_the_previous_fresh_half_with_new_noise():
    """replay=0.5: the simulator makes half a batch per step; the other half are the previous step's
    fresh samples (same parameters, same clean signals) under fresh augmentation noise."""
    kwargs = dict(window=40, batch_size=8, samples_per_epoch=32, val_samples=4, seed=3, train_additive_max=0.1)
    dm = StreamingDataModule(replay=0.5, **kwargs)
    dm.setup("fit")
    calls = []
    simulator = dm.data_train.simulator
    dm.data_train.simulator = lambda n, g: calls.append(n) or simulator(n, g)
    batches = list(dm.data_train)
    assert calls == [8, 4, 4, 4] and all(b["params"].shape[0] == 8 for b in batches)
    for prev, cur in zip(batches, batches[1:]):
        fresh_prev = prev["params"] if prev is batches[0] else prev["params"][:4]
        for row in range(4, 8):  # each replayed sample is one of the previous step's fresh ones
            match = (fresh_prev == cur["params"][row]).all(1).nonzero()
            assert match.numel() == 1
            first_use = prev["x"][int(match[0])]  # fresh rows come first in a batch
            assert not torch.allclose(cur["x"][row], first_use)  # new noise on the same clean signal
            assert torch.allclose(cur["x"][row], first_use, atol=0.5 * float(first_use.abs().max()))
    assert torch.unique(torch.cat([b["params"] for b in batches]), dim=0).shape[0] == 8 + 3 * 4
    for bad in (0.75, -0.1, "half"):  # above 0.5 the replayed part would outgrow the previous fresh part
        with pytest.raises(ValueError, match=r"data.replay must be a number in \[0, 0.5\], got"):
            StreamingDataModule(replay=bad, **kwargs)


def test_streaming_ranks_shard(monkeypatch):
    dm = StreamingDataModule(window=20, batch_size=4, samples_per_epoch=16, val_samples=4, seed=2)
    dm.setup("fit")
    seen = []
    for rank in (0, 1):
        monkeypatch.setattr(SimulatedStream, "_rank", staticmethod(lambda rank=rank: (rank, 2)))
        dm.data_train._passes = 0
        batches = list(dm.data_train)
        assert len(batches) == 2  # half of the 4 batches per rank
        seen.append(torch.cat([b["params"] for b in batches]))
    assert torch.unique(torch.cat(seen), dim=0).shape[0] == 16


def test_streaming_fixed_validation_and_test(tiny):
    kwargs = dict(window=30, batch_size=4, samples_per_epoch=8, val_samples=6, test_samples=5, seed=1)
    a, b = StreamingDataModule(**kwargs), StreamingDataModule(**kwargs)
    a.setup(), b.setup()
    assert torch.equal(a.data_val.tensors["x"], b.data_val.tensors["x"]) and len(a.data_test) == 5
    assert not torch.equal(a.data_val.tensors["x"][:5], a.data_test.tensors["x"])
    assert "input_mean" in a.stats
    # data.path: test on the file's test split.
    c = StreamingDataModule(path=str(tiny), **kwargs)
    c.setup("test")
    assert len(c.data_test) == 32
    with pytest.raises(DatasetError, match="h = 0.01 differs"):
        StreamingDataModule(path=str(tiny), h=0.005, **{k: v for k, v in kwargs.items()}).setup("test")
    with pytest.raises(ValueError, match="must differ"):
        StreamingDataModule(seed=7, val_seed=7)
