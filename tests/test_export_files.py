"""qcm-export: TorchScript and ONNX exports reproduce the checkpoints' own inference; contract; CLI errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from hybridqcm.models.export import contract, parity_error, reference_output
from hybridqcm.models.export_files import ParityError, export, parity_inputs
from hybridqcm.training import train
from test_app_train import SMALL, SMALL_NET, _cfg, data, trained  # noqa: F401 - fixtures shared with the train tests

onnxruntime = pytest.importorskip("onnxruntime")


@pytest.fixture(scope="module")
def checkpoints(data, trained):
    """last.ckpt of a physics CNN, a CAE and a U-Net trained for a few steps on the tiny dataset."""
    out = data["root"] / "exp9_unet"
    train(_cfg(["experiment=exp9_unet", f"data.path={data['tiny']}", *SMALL, *SMALL_NET["exp9_unet"]], out))
    runs = {**trained, "exp9_unet": out}
    return {name: run / "checkpoints" / "last.ckpt" for name, run in runs.items()}


@pytest.mark.parametrize(
    "experiment, model_class, n_out",
    [
        ("exp2_physics", "PhysicsResidualEstimator", 2),
        ("exp4_denoiser", "DenoisingAutoencoder", 2),
        ("exp9_unet", "CompletionUNet", 2),
    ],
)
def test_exports_match_checkpoint_on_held_out_recordings(checkpoints, data, tmp_path, experiment, model_class, n_out):
    sidecar = export(str(checkpoints[experiment]), tmp_path, "net", data=str(data["tiny"]), split="test", n_check=32)
    assert sidecar["model_class"] == model_class
    assert set(sidecar["parity"]) == {"torchscript", "onnx"}
    assert all(0 <= err <= 1e-5 for err in sidecar["parity"].values()), sidecar["parity"]
    assert json.loads((tmp_path / "net.json").read_text()) == sidecar
    assert sidecar["h"] == 0.01 and sidecar["h_source"].startswith("attrs of")

    # Independently of export(): reload both files and compare with the checkpoint's own API on a
    # different batch size than the one traced (the batch axis is dynamic).
    from hybridqcm.models.export_files import load_for_export

    model = load_for_export(str(checkpoints[experiment]))
    steps = sidecar["time_steps"]
    x, _ = parity_inputs(model, steps, str(data["tiny"]), "test", 5)
    reference = reference_output(model, x)
    scripted = torch.jit.load(str(tmp_path / "net.pt"))
    session = onnxruntime.InferenceSession(str(tmp_path / "net.onnx"), providers=["CPUExecutionProvider"])
    (onnx_out,) = session.run(None, {"accel": x.numpy()})
    assert parity_error(model, reference, scripted(x)) <= 1e-5
    assert parity_error(model, reference, torch.from_numpy(onnx_out)) <= 1e-5
    batch_dim = session.get_inputs()[0].shape[0]
    assert isinstance(batch_dim, str), f"batch axis is fixed at {batch_dim}"
    assert session.get_inputs()[0].shape[1:] == [2, steps] == sidecar["input"]["shape"][1:]
    expected_out = ["batch", n_out] if model.kind == "estimator" else ["batch", n_out, steps]
    assert sidecar["output"]["shape"] == expected_out and list(onnx_out.shape[1:]) == expected_out[1:]
    if model.kind == "estimator":
        assert sidecar["target_names"] == ["p1", "p2"] and onnx_out.dtype == np.float64
        assert (reference > 0).all()  # physical parameters, not normalised log-values


def test_parity_measure_detects_a_deviation(checkpoints, data):
    from hybridqcm.models.export_files import load_for_export

    for name in ("exp2_physics", "exp4_denoiser"):
        model = load_for_export(str(checkpoints[name]))
        x, _ = parity_inputs(model, int(model.hparams.window), str(data["tiny"]), "test", 4)
        reference = reference_output(model, x)
        assert parity_error(model, reference, reference) == 0.0
        off = reference.double() + 3e-5 * reference.double().abs().max()
        assert parity_error(model, reference, off) > 1e-5


def test_parity_failure_is_an_error(checkpoints, tmp_path):
    with pytest.raises(ParityError, match="deviates"):
        export(str(checkpoints["exp4_denoiser"]), tmp_path, formats=["torchscript"], n_check=4, tol=-1.0)


def test_contract_names_units_and_window(checkpoints):
    from hybridqcm.models.export_files import load_for_export

    unet = contract(load_for_export(str(checkpoints["exp9_unet"])), 256, 0.01)
    assert unet["input"]["channels"] == ["a3", "pu_u"] and unet["output"]["channels"] == ["a2", "a1"]
    assert unet["input"]["shape"] == ["batch", 2, 256] and unet["window"] == 512 and unet["output"]["units"] == "m/s^2"


@pytest.mark.slow  # a faster check of the same behaviour stays in the default suite
def test_cli_synthetic_signals_and_time_steps(checkpoints, tmp_path):
    command = [
        sys.executable,
        "-m",
        "hybridqcm.apps.export",
        str(checkpoints["exp4_denoiser"]),
        "--out",
        str(tmp_path),
        "--format",
        "torchscript",
        "--time-steps",
        "300",
        "--n-check",
        "8",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    sidecar = json.loads((tmp_path / "last.json").read_text())
    assert (
        sidecar["time_steps"] == 300
        and sidecar["parity"]["torchscript"] <= 1e-5
        and "synthetic" in sidecar["parity_inputs"]
    )
    assert not (tmp_path / "last.onnx").exists()
    scripted = torch.jit.load(str(tmp_path / "last.pt"))
    assert scripted(torch.randn(3, 2, 300)).shape == (3, 2, 300)
    # an existing export is not replaced unasked (before: replaced without a word)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    again = subprocess.run(command[:-4] + ["--time-steps", "200"], capture_output=True, text=True, timeout=300)
    assert again.returncode == 2
    assert again.stderr.strip().splitlines() == [
        f"error: {tmp_path / 'last.pt'} exists; pass --overwrite to replace the export (or --out/--name)"
    ]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_overwrite_replaces_an_export_and_only_then(checkpoints, tmp_path):
    from hybridqcm.errors import ConfigError
    from hybridqcm.models.export_files import export

    ckpt = checkpoints["exp4_denoiser"]
    export(ckpt, tmp_path, "cae", ["torchscript"], 300, n_check=4)
    (tmp_path / "cae.onnx").write_text("the user's own file of that name")
    with pytest.raises(ConfigError, match=r"cae.onnx exists; pass --overwrite"):
        export(ckpt, tmp_path, "cae", ["onnx"], 300, n_check=4)
    assert (tmp_path / "cae.onnx").read_text() == "the user's own file of that name"
    export(ckpt, tmp_path, "cae", ["torchscript"], 200, n_check=4, overwrite=True)
    assert json.loads((tmp_path / "cae.json").read_text())["time_steps"] == 200
    assert torch.jit.load(str(tmp_path / "cae.pt"))(torch.randn(2, 2, 200)).shape == (2, 2, 200)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cae.json", "cae.onnx", "cae.pt"]  # no temporary left


def test_cli_bad_input_is_one_line_exit_2(tmp_path):
    """On the console (a real process: its whole stderr, imports' chatter included) a bad input is one line,
    exit 2; the other bad inputs go through the same main() and fail() in-process below."""
    result = subprocess.run(
        [sys.executable, "-m", "hybridqcm.apps.export", "/nonexistent/x.ckpt", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2, result.stderr[-2000:]
    assert "does not exist" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["{bad}"], "not a readable torch checkpoint"),
        (["{ckpt}", "--time-steps", "100"], "reads exactly window"),
        (["{ckpt}", "--data", "/nonexistent.h5"], "nonexistent.h5"),
    ],
)
def test_main_bad_input_is_one_line_exit_2(checkpoints, tmp_path, capsys, args, message):
    from hybridqcm.apps.export import main

    bad = tmp_path / "bad.ckpt"
    bad.write_text("not a checkpoint")
    args = [a.format(bad=bad, ckpt=checkpoints["exp2_physics"]) for a in args]
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--out", str(tmp_path)])
    stderr = capsys.readouterr().err
    assert exit_info.value.code == 2, stderr[-2000:]
    assert message in stderr and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1, stderr


def test_help_documents_contract():
    result = subprocess.run(
        [sys.executable, "-m", "hybridqcm.apps.export", "--help"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0 and "[batch, channels, time]" in result.stdout and "--time-steps" in result.stdout
