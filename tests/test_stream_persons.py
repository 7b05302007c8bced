"""Streamed training data with seated persons (issue 28 item 5): data.occupant for the CNN start."""

from __future__ import annotations

import pytest
import torch

from hybridqcm.data.datamodules import StreamingDataModule
from hybridqcm.data.simulate import simulate_samples
from hybridqcm.data.stream import StreamSimulator

KW = dict(n_steps=300, physics="continuous", warmup_s=(2.0, 5.0))


def _rigid_residual(arrays) -> torch.Tensor:
    """[n] RMS of a3 + p1 (v3 - v2) + p2 (q3 - q2) over RMS of a3: the rigid occupant's equation."""
    p, a, v, q = arrays["params"], arrays["accel"], arrays["vel"], arrays["disp"]
    r = a[..., 0] + p[:, :1] * (v[..., 0] - v[..., 1]) + p[:, 1:2] * (q[..., 0] - q[..., 1])
    return r.square().mean(1).sqrt() / a[..., 0].square().mean(1).sqrt()


def test_the_rigid_stream_is_unchanged():
    """occupant=rigid (the default) draws exactly what the stream drew before persons existed."""
    sim = StreamSimulator(**KW)
    ours = sim(6, torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(4)
    pick = torch.multinomial(sim.class_weights, 6, replacement=True, generator=g)
    before = simulate_samples(
        sim.prior, sim.road, sim.class_index[pick], 300, 0.01, sim.speed_mps, g, 1, sim.integrator, "continuous",
        sim.warmup_s, basis=sim.basis(),
    )  # fmt: skip
    for key in ("accel", "params", "road", "state0"):
        assert torch.equal(ours[key], before[key])


def test_mixed_streams_persons_labelled_by_their_static_mass():
    """A third of each occupant per sample; the rigid ones obey the rigid equation (residual at round-off),
    the persons do not (their pan carries a body mode: why the physics-residual loss is refused), and every
    label is p2 = K3/M with M the static mass in the prior's range."""
    arrays = StreamSimulator(**KW, occupant="mixed")(300, torch.Generator().manual_seed(1))
    kind = arrays["occupant"]
    counts = torch.bincount(kind, minlength=3)
    assert counts.sum() == 300 and (counts > 70).all()
    residual = _rigid_residual(arrays)
    assert float(residual[kind == 0].max()) < 1e-6
    assert float(residual[kind > 0].min()) > 0.02
    mass = 98935.0 / arrays["params"][:, 1]
    assert float(mass.min()) >= 30.0 - 1e-9 and float(mass.max()) <= 150.0 + 1e-9
    assert "occupant_params" not in arrays


def test_a_body1_stream_carries_its_body_parameters():
    arrays = StreamSimulator(**KW, occupant="body1")(5, torch.Generator().manual_seed(2))
    body = arrays["occupant_params"]
    assert body.shape == (5, 3) and (body > 0).all()
    assert (_rigid_residual(arrays) > 0.02).all()


def test_persons_refuse_the_physics_residual_and_the_euler_stream():
    with pytest.raises(ValueError, match="assumes a rigid occupant"):
        StreamingDataModule(window=64, aux=["a3", "v3", "v2", "q3", "q2"], physics="continuous", occupant="body1")
    with pytest.raises(ValueError, match="needs physics=continuous"):
        StreamingDataModule(window=64, occupant="mixed")
    with pytest.raises(ValueError, match="data.occupant = 'giant'"):
        StreamingDataModule(window=64, physics="continuous", occupant="giant")


def test_a_persons_file_refuses_the_physics_residual_but_trains_the_labelled_cnn(tmp_path):
    """qcm-simulate occupant=body1's file: the labels (params p1, p2) are the static mass's, the physics
    residual's training split is refused in one line."""
    from conftest import write_tiny_dataset
    from hybridqcm.data.datamodules import HDF5DataModule
    from hybridqcm.data.hdf5 import read_split
    from hybridqcm.errors import DatasetError

    path = tmp_path / "persons.h5"
    write_tiny_dataset(path, physics="continuous", warmup_s=(2.0, 5.0), occupant="body1")
    physics = dict(window=64, aux=["a3", "v3", "v2", "q3", "q2"], batch_size=8, val_fraction=0.25)
    with pytest.raises(DatasetError, match="holds seated persons"):
        HDF5DataModule(path, **physics).setup("fit")
    HDF5DataModule(path, **physics).setup("test")  # evaluating on persons is allowed
    labelled = HDF5DataModule(path, window=64, batch_size=8, val_fraction=0.25)
    labelled.setup("fit")
    arrays = read_split(path, "train", ["params", "occupant_params"])
    assert arrays["occupant_params"].shape[1] == 3 and (arrays["occupant_params"][:, 0] > 0).all()
    y = torch.cat([labelled.data_train.tensors["y"], labelled.data_val.tensors["y"]])
    assert torch.equal(y.sort(0).values, torch.as_tensor(arrays["params"][:, :2]).double().sort(0).values)
