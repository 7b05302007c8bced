"""The split of models/modules.py (issue 8): old checkpoints and import paths, and the epoch statistics.

Facts checked: a checkpoint written before the split loads through the safe loader with every
tensor unchanged; a checkpoint records the class name only (no module path that a move could
break); validation/test statistics logged through metrics.ErrorDistribution equal a numpy
computation on the same predictions, under the keys the training app and tracking read.
"""

from __future__ import annotations

from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

import hybridqcm.models as models
import hybridqcm.models.modules as old_home
from conftest import tiny_datamodule
from hybridqcm.metrics import ErrorDistribution
from hybridqcm.models.checkpoint import MODULES, load_checkpoint
from hybridqcm.models.estimators import LabelledEstimator, PhysicsResidualEstimator
from hybridqcm.models.signal_models import CompletionUNet, DenoisingAutoencoder

# Written by the pre-split code (class then in hybridqcm.models.modules); present on the dev box only.
PRE_SPLIT_CKPT = Path("/work/main/outputs/dev/train_exp2_cont2/checkpoints/last.ckpt")
SMALL_CNN = {
    "_target_": "hybridqcm.models.networks.ParameterCNN",
    "channels": [4, 4],
    "kernels": [10, 5],
    "hidden": [8, 4],
}


def test_old_import_path_names_the_same_classes():
    for name in ("LabelledEstimator", "GaussianEstimator", "PhysicsResidualEstimator"):
        assert getattr(old_home, name) is getattr(models, name) is MODULES[name]
    assert old_home.DenoisingAutoencoder is DenoisingAutoencoder and old_home.CompletionUNet is CompletionUNet
    assert old_home.CheckpointMismatch is models.CheckpointMismatch and old_home.MODULES is MODULES
    assert {cls.__module__ for cls in MODULES.values()} == {
        "hybridqcm.models.estimators",
        "hybridqcm.models.signal_models",
    }


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
