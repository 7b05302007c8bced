"""The accelerometer model: statistics of each kind, per-sample reproducibility, NaN channels,
bad input, and its use by the datamodules (fixed evaluation noise, fresh training noise)."""

from __future__ import annotations

import math

import pytest
import torch

from hybridqcm.data.datamodules import HDF5DataModule, StreamingDataModule
from hybridqcm.data.sensor import SensorModel, additive_augmentation, apply_to_channels, build_sensor
from test_datamodules import make_tiny_dataset


def _signal(b=4, t=20000, seed=0):
    g = torch.Generator().manual_seed(seed)
    time = torch.linspace(0, 50, t, dtype=torch.float64)
    amp = torch.tensor([0.3, 1.0, 4.0], dtype=torch.float64) * (
        1 + torch.rand(b, 1, 3, generator=g, dtype=torch.float64)
    )
    return amp * torch.sin(3.0 * time[None, :, None] + torch.rand(b, 1, 3, generator=g, dtype=torch.float64))


def test_additive_relative_std_is_a_fraction_of_each_channels_rms():
    a = _signal()
    out = SensorModel("additive", sigma=[0.01, 0.05, 0.1]).validate().apply(a, torch.arange(4))
    rms = a.pow(2).mean(1).sqrt()
    ratio = (out - a).std(1) / (rms * torch.tensor([0.01, 0.05, 0.1], dtype=torch.float64))
    assert float((ratio - 1).abs().max()) < 0.05  # 20 000 points: std known to ~1 %
    assert float((out - a).mean(1).abs().max() / rms.max()) < 0.01


def test_additive_absolute_bias_and_quantisation():
    a = _signal(b=2)
    sensor = SensorModel("additive", sigma=0.02, relative=False, bias=[0.1, 0.0, 0.2]).validate()
    out = sensor.apply(a, torch.tensor([7, 9]))
    assert float(((out - a).std(1) / 0.02 - 1).abs().max()) < 0.05
    mean = (out - a).mean(1)
    assert torch.allclose(mean, torch.tensor([0.1, 0.0, 0.2], dtype=torch.float64).expand(2, 3), atol=1e-3)
    q = SensorModel("additive", sigma=0.0, quantisation=0.05).validate().apply(a, torch.tensor([0, 1]))
    assert torch.allclose(q / 0.05, torch.round(q / 0.05), atol=1e-9)
    assert float((q - a).abs().max()) <= 0.025 + 1e-12
    assert torch.allclose(
        SensorModel("additive", quantisation=0.05).validate().noise_std(a),
        torch.full((2, 3), 0.05 / math.sqrt(12), dtype=torch.float64),
    )


def test_multiplicative_is_the_source_model():
    a = _signal(b=2) + 5.0  # keep away from zero
    out = SensorModel("multiplicative", sigma=0.05).validate().apply(a, torch.tensor([0, 1]))
    eta = (out / a - 1) / 0.05
    assert abs(float(eta.std()) - 1) < 0.02 and abs(float(eta.mean())) < 0.02


def test_noise_depends_only_on_seed_and_sample_id():
    a = _signal(b=5, t=300)
    sensor = SensorModel("additive", sigma=0.05, seed=3).validate()
    index = torch.tensor([10, 11, 12, 13, 14])
    whole = sensor.apply(a, index)
    pieces = torch.cat([sensor.apply(a[[3, 1]], index[[3, 1]]), sensor.apply(a[[0, 2, 4]], index[[0, 2, 4]])])
    torch.testing.assert_close(pieces, whole[[3, 1, 0, 2, 4]], rtol=0, atol=0)
    assert not torch.equal(SensorModel("additive", sigma=0.05, seed=4).validate().apply(a, index), whole)
    assert not torch.equal(sensor.apply(a, index, salt=1), whole)


def test_nan_channels_stay_nan_and_do_not_leak():
    a = _signal(b=2, t=100)
    a[..., 2] = float("nan")
    out = SensorModel("additive", sigma=0.1).validate().apply(a, torch.tensor([0, 1]))
    assert torch.isnan(out[..., 2]).all() and torch.isfinite(out[..., :2]).all()
    x = torch.stack([a[..., 0], torch.ones_like(a[..., 0])], 1).float()  # channels (a3, pu_u)
    y = apply_to_channels(SensorModel("additive", sigma=0.1).validate(), x, ["a3", "pu_u"], torch.tensor([0, 1]))
    assert torch.equal(y[:, 1], x[:, 1]) and not torch.equal(y[:, 0], x[:, 0])


@pytest.mark.parametrize(
    "spec,message",
    [
        ({"kind": "gaussian"}, "sensor.kind = 'gaussian' is not known"),
        ({"kind": "additive", "sigma": -0.1}, "sensor.sigma must be finite and >= 0, got -0.1"),
        ({"kind": "additive", "bias": [0, -1, 0]}, "sensor.bias must be finite and >= 0"),
        ({"kind": "additive", "sigma": [0.1, 0.2]}, "sensor.sigma must be a number or 3 numbers"),
        ({"kind": "additive", "quantisation": -1}, "sensor.quantisation must be finite and >= 0"),
        ({"kind": "none", "sigma": 0.05}, "sensor.kind = 'none' takes no sigma"),
        ({"kind": "additive", "sgma": 0.05}, "sensor: unknown option(s) ['sgma']"),
    ],
)
def test_bad_sensor_is_one_line(spec, message):
    with pytest.raises(ValueError) as error:
        build_sensor(spec)
    assert message in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize(
    "spec, words",
    [
        ({"kind": "none"}, "none"),
        ({"kind": "additive", "sigma": 0.05}, "additive noise 5 % of channel RMS"),
        ({"kind": "multiplicative", "sigma": 0.05}, "multiplicative noise 5 %"),
        (
            {"kind": "additive", "sigma": [0.02, 0.02, 0.05], "relative": False, "bias": 0.01},
            "additive noise (a3, a2, a1) = 0.02 m/s², 0.02 m/s², 0.05 m/s², bias 0.01 m/s²",
        ),
        (
            {"kind": "additive", "sigma_range": [0.01, 0.1], "quantisation": 0.002},
            "additive noise 1 % to 10 % of channel RMS (log-uniform per sample), quantisation 0.002 m/s²",
        ),
    ],
)
def test_describe_names_kind_level_and_unit(spec, words):
    """The words a report title carries: a relative 5 % is of the RMS, absolute levels are m/s²."""
    assert build_sensor(spec).describe() == words


def test_augmentation_level_is_drawn_per_sample():
    x = torch.ones(64, 2, 400)
    y = additive_augmentation(x, ["a3", "pu_u"], 0.1, torch.Generator().manual_seed(0))
    level = (y[:, 0] - 1).std(-1)
    assert float(level.max()) < 0.11 and float(level.min()) < 0.02 and float(level.max()) > 0.08
    assert torch.equal(y[:, 1], x[:, 1])


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("sensor") / "tiny.h5", n_steps=64)


def test_hdf5_datamodule_fixed_test_noise_fresh_training_noise(small):
    kw = dict(window=64, inputs=("a3", "a2"), targets=("p1", "p2"), sensor={"kind": "additive", "sigma": 0.05}, seed=1)
    one, two = HDF5DataModule(small, batch_size=4, **kw), HDF5DataModule(small, batch_size=7, eval_batch_size=5, **kw)
    clean = HDF5DataModule(small, window=64, inputs=("a3", "a2"), targets=("p1", "p2"), seed=1)
    for dm in (one, two, clean):
        dm.setup()
    x1 = torch.cat([b["x"] for b in one.test_dataloader()])
    x2 = torch.cat([b["x"] for b in two.test_dataloader()])
    x0 = torch.cat([b["x"] for b in clean.test_dataloader()])
    torch.testing.assert_close(x1, x2, rtol=0, atol=0)  # same noise whatever the batching
    noise = (x1 - x0).double()
    ratio = noise.std(-1) / (x0.double().pow(2).mean(-1).sqrt() * 0.05)
    assert 0.7 < float(ratio.mean()) < 1.3
    rows = list(range(6))
    first, second = one.data_train.__getitems__(rows)["x"], one.data_train.__getitems__(rows)["x"]
    assert not torch.equal(first, second)  # fresh training noise each time
    with pytest.raises(ValueError, match="noise_sigma = 0.05 and sensor.kind = 'additive' both add noise"):
        HDF5DataModule(small, noise_sigma=0.05, **kw)


def test_streaming_continuous_mid_drive_with_sensor_and_augmentation():
    dm = StreamingDataModule(
        window=64,
        inputs=("a3", "a2"),
        targets=("p1", "p2"),
        physics="continuous",
        warmup_s=[2, 5],
        sensor={"kind": "additive", "sigma": 0.01},
        train_additive_max=0.1,
        samples_per_epoch=32,
        batch_size=16,
        val_samples=8,
        test_samples=8,
        stats_samples=16,
    )
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    assert batch["x"].shape == (16, 2, 64) and torch.isfinite(batch["x"]).all()
    assert torch.isfinite(next(iter(dm.test_dataloader()))["x"]).all()
    with pytest.raises(ValueError, match="physics = 'rk45' is not known"):
        StreamingDataModule(window=64, physics="rk45")
    with pytest.raises(ValueError, match=r"data.warmup_s must be a range 0 <= low <= high"):
        StreamingDataModule(window=64, physics="continuous", warmup_s=[5, 2])


def test_hdf5_datamodule_refuses_only_the_unrecorded_channels_it_reads(tmp_path):
    import h5py
    import numpy as np

    path = make_tiny_dataset(tmp_path / "t.h5", n_steps=64)
    with h5py.File(path, "r+") as f:
        for split in ("train", "test"):
            accel = f[split]["accel"][()]
            accel[..., 2] = np.nan  # no wheel accelerometer
            f[split]["accel"][...] = accel
    dm = HDF5DataModule(path, window=64, inputs=("a3", "a2"), targets=("p1", "p2"), batch_size=8)
    dm.setup()  # a3, a2 suffice
    assert torch.isfinite(next(iter(dm.test_dataloader()))["x"]).all()
    bad = HDF5DataModule(path, window=64, inputs=("a3", "a1"), targets=("p1", "p2"))
    with pytest.raises(
        Exception, match=r"channel\(s\) \['a1'\] are not recorded \(all NaN\) but this task reads them as inputs"
    ):
        bad.setup()
