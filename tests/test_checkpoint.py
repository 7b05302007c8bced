"""The split of models/modules.py (issues 8, 29): old checkpoints, and the epoch statistics.

Facts checked: a checkpoint written before the split loads through the safe loader with every
tensor unchanged; a checkpoint records the class name only (no module path that a move could
break), and the loader resolves it by that name alone; validation/test statistics logged through metrics.ErrorDistribution equal a numpy
computation on the same predictions, under the keys the training app and tracking read.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from conftest import tiny_datamodule
from hybridqcm.errors import CheckpointError
from hybridqcm.metrics import ErrorDistribution
from hybridqcm.models.checkpoint import MODULES, load_checkpoint, stored_class
from hybridqcm.models.estimators import LabelledEstimator, PhysicsResidualEstimator

# Written by the pre-split code (class then in hybridqcm.models.modules); present on the dev box only.
PRE_SPLIT_CKPT = Path("/work/main/outputs/dev/train_exp2_cont2/checkpoints/last.ckpt")
SMALL_CNN = {
    "_target_": "hybridqcm.models.networks.ParameterCNN",
    "channels": [4, 4],
    "kernels": [10, 5],
    "hidden": [8, 4],
}


def test_checkpoints_name_their_class_only_and_load_by_that_name(tmp_path):
    """What a pre-split file holds (the class name, hparams, tensors) loads whatever module the class lives in
    now; a module path (the old home hybridqcm.models.modules is gone) is not a name the loader knows."""
    assert importlib.util.find_spec("hybridqcm.models.modules") is None
    assert set(MODULES) == {
        "LabelledEstimator",
        "GaussianEstimator",
        "PhysicsResidualEstimator",
        "DenoisingAutoencoder",
        "CompletionUNet",
    }
    torch.manual_seed(1)
    written = PhysicsResidualEstimator(net=SMALL_CNN, plot_every_n_epochs=0)
    raw = {"hybridqcm_class": "PhysicsResidualEstimator", "hyper_parameters": dict(written.hparams)}
    raw["state_dict"] = {k: v.clone() for k, v in written.state_dict().items()}
    path = tmp_path / "old.ckpt"
    torch.save(raw, path)
    assert stored_class(path) == "PhysicsResidualEstimator"
    module = load_checkpoint(path, "cnn")
    assert type(module) is PhysicsResidualEstimator and not module.training
    assert all(torch.equal(module.state_dict()[k], v) for k, v in raw["state_dict"].items())

    moved = tmp_path / "path.ckpt"
    torch.save({**raw, "hybridqcm_class": "hybridqcm.models.modules.PhysicsResidualEstimator"}, moved)
    assert stored_class(moved) == "hybridqcm.models.modules.PhysicsResidualEstimator"
    with pytest.raises(CheckpointError, match="holds a hybridqcm.models.modules.PhysicsResidualEstimator checkpoint"):
        load_checkpoint(moved, "cnn")


@pytest.mark.skipif(not PRE_SPLIT_CKPT.is_file(), reason="pre-split checkpoint of the dev box not present")
def test_checkpoint_written_before_the_split_loads_through_the_safe_loader():
    raw = torch.load(PRE_SPLIT_CKPT, map_location="cpu", weights_only=True)
    assert raw["hybridqcm_class"] == "PhysicsResidualEstimator"
    module = load_checkpoint(PRE_SPLIT_CKPT, "cnn")
    assert type(module) is PhysicsResidualEstimator and not module.training
    state = module.state_dict()
    assert set(state) == set(raw["state_dict"])
    assert all(torch.equal(state[k], v) for k, v in raw["state_dict"].items())
    assert dict(module.hparams) == raw["hyper_parameters"]


def _strings(value):
    if isinstance(value, str):
        yield value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from _strings(k)
            yield from _strings(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _strings(v)


def _trainer(**kwargs):
    return L.Trainer(
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
        **kwargs,
    )


def _numpy_statistics(pred: np.ndarray, true: np.ndarray, stage: str) -> dict[str, float]:
    e = np.abs(pred - true) / np.abs(true)
    out = {f"{stage}/mean_rel_err": e.mean()}
    for j, name in enumerate(("p1", "p2")):
        out[f"{stage}/{name}/mean_rel_err"] = e[:, j].mean()
        out[f"{stage}/{name}/max_rel_err"] = e[:, j].max()
        out[f"{stage}/{name}/over_25pct"] = (e[:, j] > 0.25).mean()
    return out


def test_error_distribution_over_several_batches_equals_numpy():
    rng = np.random.default_rng(3)
    true = rng.uniform(0.5, 2.0, (13, 2))
    pred = true * (1 + rng.normal(0, 0.3, (13, 2)))
    metric = ErrorDistribution(["p1", "p2"])
    for rows in (slice(0, 5), slice(5, 6), slice(6, 13)):  # uneven batches
        metric.update(torch.from_numpy(pred[rows]), torch.from_numpy(true[rows]))
    expected = _numpy_statistics(pred, true, "s")
    rows = metric.compute()
    assert [r["param"] for r in rows] == ["p1", "p2"] and all(r["n"] == 13 for r in rows)
    for row in rows:
        assert row["mean_err"] == pytest.approx(expected[f"s/{row['param']}/mean_rel_err"], rel=1e-14)
        assert row["max_err"] == pytest.approx(expected[f"s/{row['param']}/max_rel_err"], rel=1e-14)
        assert row["over_25pct"] == expected[f"s/{row['param']}/over_25pct"]
    assert metric.mean_error() == pytest.approx(expected["s/mean_rel_err"], rel=1e-14)
    metric.reset()
    assert metric.update_count == 0 and metric.errors == []


def test_logged_statistics_keys_and_values_and_new_checkpoint(tiny_dataset, tmp_path):
    torch.manual_seed(0)
    module = LabelledEstimator(net=SMALL_CNN, plot_every_n_epochs=0)
    dm = tiny_datamodule(tiny_dataset, module, num_workers=0)  # the 40 test samples arrive in 3 batches (16, 16, 8)
    trainer = _trainer(max_epochs=1, limit_train_batches=2, limit_val_batches=2)
    trainer.fit(module, dm)
    stats = ("mean_rel_err", "max_rel_err", "over_25pct")
    keys = {f"{s}/{p}/{k}" for s in ("val", "test") for p in ("p1", "p2") for k in stats}
    keys |= {"val/loss", "val/mean_rel_err", "test/loss", "test/mean_rel_err"}
    assert {k for k in trainer.callback_metrics if k.startswith("val/")} == {k for k in keys if k.startswith("val/")}

    (logged,) = trainer.test(module, dm, verbose=False)
    assert set(logged) == {k for k in keys if k.startswith("test/")}
    results = module.test_results
    assert results["pred"].shape == (40, 2) and sorted(results["index"].tolist()) == list(range(40))
    expected = _numpy_statistics(results["pred"].numpy(), results["true"].numpy(), "test")
    for key, value in expected.items():  # Lightning stores logged floats as float32
        assert logged[key] == pytest.approx(value, rel=1e-6), key

    # A second test run starts from nothing (the metric was reset after logging).
    (again,) = trainer.test(module, dm, verbose=False)
    assert again == logged

    path = tmp_path / "new.ckpt"
    trainer.save_checkpoint(path)
    raw = torch.load(path, map_location="cpu", weights_only=True)
    assert raw["hybridqcm_class"] == "LabelledEstimator"
    paths = [s for s in _strings({k: v for k, v in raw.items() if k != "state_dict"}) if "hybridqcm." in s]
    assert paths == ["hybridqcm.models.networks.ParameterCNN"]  # the net target only, no module path
    assert type(load_checkpoint(path, "cnn")) is LabelledEstimator
