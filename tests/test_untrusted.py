"""Untrusted checkpoints are read as data: nothing in them runs, nothing outside the allow-list is built.

Every hostile file here is refused with one-line CheckpointError and the marker file its payload
would create (or truncate) is checked afterwards: it must not appear / must keep its content.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hybridqcm.errors import CheckpointError, ConfigError, DatasetError, HybridQCMError
from hybridqcm.models.checkpoint import load_checkpoint, load_module, read_checkpoint

SRC = str(Path(__file__).resolve().parents[1] / "src")


class _Payload:
    """Pickles as a call of os.system: loading it with weights_only=False would run the command."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


@pytest.fixture(scope="module")
def tiny_cnn(tmp_path_factory) -> Path:
    """A real checkpoint of our PhysicsResidualEstimator (tiny net, untrained), saved the way Lightning saves."""
    from hybridqcm.models import PhysicsResidualEstimator

    torch.manual_seed(0)
    module = PhysicsResidualEstimator(
        net={"channels": [4, 4], "kernels": [16, 8], "strides": [4, 2], "hidden": [8, 4]}, window=128
    )
    path = tmp_path_factory.mktemp("ckpt") / "cnn.ckpt"
    checkpoint = {
        "state_dict": module.state_dict(),
        "hyper_parameters": dict(module.hparams),
        "hybridqcm_class": "PhysicsResidualEstimator",
        "pytorch-lightning_version": "2.6.6",
    }
    torch.save(checkpoint, path)
    return path


def _tampered(source: Path, target: Path, edit) -> Path:
    raw = torch.load(source, weights_only=True)
    edit(raw)
    torch.save(raw, target)
    return target


def test_error_hierarchy():
    for cls in (ConfigError, DatasetError, CheckpointError):
        assert issubclass(cls, HybridQCMError) and issubclass(cls, ValueError)


def test_real_checkpoint_round_trips(tiny_cnn):
    module = load_checkpoint(tiny_cnn, "cnn", "cnn_ckpt")
    assert type(module).__name__ == "PhysicsResidualEstimator" and not module.training
    stored = torch.load(tiny_cnn, weights_only=True)["state_dict"]
    for key, value in module.state_dict().items():
        assert torch.equal(value, stored[key]), key
    # what it predicts is recorded: targets, inputs, window, rate, physics
    hp = module.hparams
    assert (list(hp.target_channels), list(hp.input_channels), hp.window, hp.h, hp.physics) == (
        ["p1", "p2"],
        ["a3", "a2"],
        128,
        0.01,
        "euler",
    )


def test_pickle_payload_is_refused_and_never_runs(tiny_cnn, tmp_path):
    marker = tmp_path / "pwned"
    evil = _tampered(tiny_cnn, tmp_path / "evil.ckpt", lambda raw: raw.update(extra=_Payload(f"touch {marker}")))
    with pytest.raises(CheckpointError, match=r"evil.ckpt: refused, .*GLOBAL (posix|os)\.system") as info:
        load_checkpoint(evil, "cnn", "cnn_ckpt")
    assert "\n" not in str(info.value)
    assert not marker.exists()
    # The class-checked entry point (qcm-train's ckpt_path, denoiser_ckpt) goes through the same loader.
    from hybridqcm.models import PhysicsResidualEstimator

    with pytest.raises(CheckpointError, match="refused"):
        load_module(str(evil), PhysicsResidualEstimator)
    assert not marker.exists()


def test_pickle_payload_in_the_estimate_app_never_runs(tiny_cnn, tiny_dataset, tmp_path):
    """End to end: qcm-estimate with a hostile cnn_ckpt exits 2 with one line, nothing executed."""
    marker = tmp_path / "pwned-app"
    evil = _tampered(tiny_cnn, tmp_path / "evil.ckpt", lambda raw: raw.update(extra=_Payload(f"touch {marker}")))
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            "from hybridqcm.apps.estimate import main; main()",
            "experiment=exp6_cnn_init",
            f"data.path={tiny_dataset}",
            f"cnn_ckpt={evil}",
            f"hydra.run.dir={tmp_path / 'run'}",
            "n_samples=2",
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": SRC},
    )
    assert result.returncode == 2, result.stderr[-2000:]
    assert "refused" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not marker.exists()


@pytest.mark.parametrize(
    "net",
    [
        {"_target_": "builtins.open", "_args_": ["VICTIM", "w"]},
        {
            "_target_": "hybridqcm.models.networks.ParameterCNN",
            "activation_name": {"_target_": "builtins.open", "_args_": ["VICTIM", "w"]},
        },
        {"_target_": "os.system", "command": "touch VICTIM"},
    ],
)
def test_hyperparameter_injection_is_refused(tiny_cnn, tmp_path, net):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")

    def inject(raw):
        text = repr(net).replace("VICTIM", str(victim))
        raw["hyper_parameters"]["net"] = eval(text)  # noqa: S307 - our own literal

    evil = _tampered(tiny_cnn, tmp_path / "inject.ckpt", inject)
    with pytest.raises(CheckpointError, match=r"inject.ckpt: hyper_parameters\.net.* refused"):
        load_checkpoint(evil, "cnn")
    assert victim.read_text() == "precious"
    assert not (Path.cwd() / "VICTIM").exists()


def test_optimizer_target_outside_torch_optim_is_refused(tiny_cnn, tmp_path):
    evil = _tampered(
        tiny_cnn,
        tmp_path / "opt.ckpt",
        lambda raw: raw["hyper_parameters"].update(optimizer={"_target_": "subprocess.run", "args": ["true"]}),
    )
    with pytest.raises(CheckpointError, match=r"hyper_parameters\.optimizer\._target_ = 'subprocess.run'"):
        read_checkpoint(evil, "cnn")
    fine = _tampered(
        tiny_cnn,
        tmp_path / "adam.ckpt",
        lambda raw: raw["hyper_parameters"].update(
            optimizer={"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-3}
        ),
    )
    assert read_checkpoint(fine, "cnn").hparams["optimizer"]["_target_"] == "torch.optim.Adam"


def test_unknown_hyperparameter_and_foreign_class_are_refused(tiny_cnn, tmp_path):
    extra = _tampered(tiny_cnn, tmp_path / "extra.ckpt", lambda raw: raw["hyper_parameters"].update(evil=1))
    with pytest.raises(CheckpointError, match=r"\['evil'\] are not arguments of PhysicsResidualEstimator"):
        read_checkpoint(extra, "cnn")
    foreign = _tampered(tiny_cnn, tmp_path / "foreign.ckpt", lambda raw: raw.update(hybridqcm_class="os.system"))
    with pytest.raises(CheckpointError, match="holds a os.system checkpoint, but cnn needs"):
        read_checkpoint(foreign, "cnn")
    with pytest.raises(CheckpointError, match="holds a PhysicsResidualEstimator checkpoint, but unet needs"):
        read_checkpoint(tiny_cnn, "unet")


def test_state_dict_missing_unexpected_or_misshaped_key_is_one_line(tiny_cnn, tmp_path):
    def drop(raw):
        raw["state_dict"].pop(next(k for k in raw["state_dict"] if k.startswith("net.")))

    cases = {
        "missing keys": drop,
        "unexpected keys": lambda raw: raw["state_dict"].update(bogus=torch.zeros(1)),
        "shapes do not match": lambda raw: raw["state_dict"].update(in_mean=torch.zeros(5)),
    }
    for i, (message, edit) in enumerate(cases.items()):
        bad = _tampered(tiny_cnn, tmp_path / f"bad{i}.ckpt", edit)
        with pytest.raises(CheckpointError, match=message) as info:
            load_checkpoint(bad, "cnn")
        assert "\n" not in str(info.value)


def test_estimator_refuses_cnn_for_other_targets_or_channels(tiny_cnn, tmp_path):
    from hybridqcm.estimation.front import HybridEstimator

    labelled = tmp_path / "labelled.ckpt"
    from hybridqcm.models import LabelledEstimator

    module = LabelledEstimator(
        net={"channels": [4], "kernels": [8], "strides": [4], "hidden": [4]}, window=64, target_channels=["p3", "p4"]
    )
    torch.save(
        {
            "state_dict": module.state_dict(),
            "hyper_parameters": dict(module.hparams),
            "hybridqcm_class": "LabelledEstimator",
        },
        labelled,
    )
    with pytest.raises(CheckpointError, match=r"targets \['p3', 'p4'\], but the initialiser needs \['p1', 'p2'\]"):
        HybridEstimator(cnn_ckpt=str(labelled))
    other_h = _tampered(tiny_cnn, tmp_path / "h.ckpt", lambda raw: raw["hyper_parameters"].update(h=0.005))
    with pytest.raises(CheckpointError, match=r"trained at h = 0.005 s, but the data have h = 0.01 s"):
        HybridEstimator(cnn_ckpt=str(other_h), h=0.01)
    continuous = _tampered(
        tiny_cnn, tmp_path / "c.ckpt", lambda raw: raw["hyper_parameters"].update(physics="continuous")
    )
    with pytest.raises(CheckpointError, match="physics = 'continuous'"):
        HybridEstimator(cnn_ckpt=str(continuous))


def test_old_checkpoint_without_h_or_physics_loads_as_euler(tiny_cnn, tmp_path):
    def strip(raw):
        raw["hyper_parameters"].pop("h")
        raw["hyper_parameters"].pop("physics")

    old = _tampered(tiny_cnn, tmp_path / "old.ckpt", strip)
    module = load_checkpoint(old, "cnn")
    assert module.hparams.physics == "euler" and module.hparams.h == 0.01


def test_no_unsafe_load_or_checkpoint_instantiate_in_src():
    """grep proof: no weights_only=False, and Hydra instantiate only on app configs / allow-listed optimizers."""
    root = Path(SRC) / "hybridqcm"
    offenders = []
    for path in root.rglob("*.py"):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if "weights_only=False" in line.replace(" ", ""):
                offenders.append(f"{path}:{number}")
    assert offenders == []
    # Lightning's load_from_checkpoint unpickles the file: every reader goes through models/checkpoint.py
    readers = [
        f"{path}:{number}"
        for path in root.rglob("*.py")
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if ".load_from_checkpoint(" in line and not line.lstrip().startswith(("#", '"'))
    ]
    assert readers == [], readers
    text = (root / "models" / "base.py").read_text()
    assert "from hydra.utils import instantiate" in text  # optimizers only, after check_config_tree
    assert "instantiate(net_cfg" not in text and "build_network(net_cfg" in text
