"""Physical-unit inference graphs of the trained networks, for TorchScript / ONNX export.

Each LightningModule normalises its inputs itself (modules.py), so the exported graph is the
module's own inference path with nothing left to the caller: raw accelerations in m/s² in,
physical parameters or signals out, the same numbers as

    estimator   .estimate(a3, a2)      input [batch, 2, window] (a3, a2)   -> [batch, P] float64 (p1, p2)
    denoiser    .denoise(x)            input [batch, 2, time]   (â3, â2)   -> [batch, 2, time] (a3, a2)
    completion  .complete(a3, pu_u)    input [batch, 2, time]   (a3, pu_u) -> [batch, 2, time] (a2, a1)

One input tensor `[batch, channels, time]` float32 for every kind. The batch axis is dynamic;
the time axis is fixed at export (the convolution padding is computed from it), `window`
steps for the estimators (they read exactly the first `window` steps) and `time_steps`
(default: the training window) for the signal networks.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from hybridqcm.models.base import QCMModule
from hybridqcm.models.estimators import ParameterEstimator
from hybridqcm.models.signal_models import CompletionUNet, DenoisingAutoencoder

CONTRACT_SCHEMA = "hybridqcm.export/1"


class PhysicalGraph(nn.Module):
    """The module's physical-unit inference as one forward(x [batch, C, time]) -> output (see module docstring).

    A plain nn.Module holding the module's network and normalisation buffers (a LightningModule
    itself cannot be traced: its trainer-bound properties raise outside a Trainer). The steps
    are those of QCMModule._scale / _standardise_in and ParameterEstimator.decode_outputs /
    _SignalModule._physical; the parity check against estimate / denoise / complete pins them."""

    def __init__(self, module: QCMModule) -> None:
        super().__init__()
        if getattr(module, "denoiser", None) is not None:
            raise ValueError("export: detach the denoiser first (export it as its own network)")
        module = module.eval()
        self.net = module.net
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            self.register_buffer(name, getattr(module, name).detach().clone())
        self.estimator = isinstance(module, ParameterEstimator)
        self.window = int(module.hparams.window)
        self.log_targets = self.estimator and module.hparams.target_transform == "log"
        channel = module.hparams.get("scale_channel")
        self.scale_channel = -1 if channel is None else int(channel)

    def _scale(self, x: Tensor) -> Tensor:
        """Per-sample scale [batch, 1, 1]: RMS of the reference channel (ones without one)."""
        if self.scale_channel < 0:
            return torch.ones_like(x[:, :1, :1])
        return x[:, self.scale_channel].pow(2).mean(-1).sqrt().clamp_min(1e-12)[:, None, None]

    def forward(self, x: Tensor) -> Tensor:
        x = x.float()
        if self.estimator:
            x = x[..., : self.window]
        scale = self._scale(x)
        z = self.net((x / scale - self.in_mean[:, None]) / self.in_std[:, None])
        if self.estimator:
            y = z.double() * self.out_std.double() + self.out_mean.double()  # [batch, P] float64
            return y.exp() if self.log_targets else y
        return (z * self.out_std[:, None] + self.out_mean[:, None]) * scale  # [batch, C', time] m/s^2


def io_names(module: QCMModule) -> tuple[list[str], list[str]]:
    """(input channel names, output names) in the order of the channels axis."""
    hp = module.hparams
    if isinstance(module, ParameterEstimator):
        return list(hp.input_channels), list(hp.target_channels)
    if isinstance(module, DenoisingAutoencoder):
        return list(hp.channels), list(hp.channels)
    return list(hp.input_channels), list(hp.target_channels)


def export_time_steps(module: QCMModule, time_steps: int | None = None) -> int:
    """Length of the exported time axis: the window for estimators, `time_steps` or the window otherwise."""
    window = int(module.hparams.window)
    if isinstance(module, ParameterEstimator):
        if time_steps not in (None, window):
            raise ValueError(f"export: an estimator reads exactly window = {window} steps; time_steps = {time_steps}")
        return window
    if time_steps is not None and int(time_steps) < 1:
        raise ValueError(f"export: time_steps must be >= 1, got {time_steps}")
    return int(time_steps or window)


def reference_output(module: QCMModule, x: Tensor) -> Tensor:
    """The checkpoint's own inference API on x [batch, C, time] (raw units): what an export must reproduce."""
    if isinstance(module, ParameterEstimator):
        return module.estimate(x[:, 0], x[:, 1])
    if isinstance(module, DenoisingAutoencoder):
        return module.denoise(x)
    if isinstance(module, CompletionUNet):
        return module.complete(x[:, 0], x[:, 1])
    raise TypeError(f"export: no inference API known for {type(module).__name__}")


def parity_error(module: QCMModule, reference: Tensor, other: Tensor) -> float:
    """Largest deviation of `other` from `reference`, relative to the output's scale.

    Estimators: elementwise max |Δp| / |p| (parameters span decades, so each is its own scale).
    Signal networks: max |Δ| / RMS of the reference channel, over channels and samples (a
    signal crosses zero, so pointwise relative errors would be meaningless there)."""
    ref, other = reference.detach().double(), torch.as_tensor(other).detach().double()
    if ref.shape != other.shape:
        raise ValueError(f"parity: shapes differ, {tuple(ref.shape)} vs {tuple(other.shape)}")
    if isinstance(module, ParameterEstimator):
        return float(((other - ref).abs() / ref.abs().clamp_min(1e-300)).max())
    scale = ref.pow(2).mean(-1, keepdim=True).sqrt().clamp_min(1e-300)  # [batch, C, 1]
    return float(((other - ref).abs() / scale).max())


def contract(module: QCMModule, time_steps: int, h: float | None = None) -> dict[str, Any]:
    """The input/output contract written beside the exports (JSON sidecar)."""
    inputs, outputs = io_names(module)
    window = int(module.hparams.window)
    if isinstance(module, ParameterEstimator):
        output = {
            "name": "params",
            "shape": ["batch", len(outputs)],
            "dtype": "float64",
            "names": outputs,
            "units": "model parameters p_i as in SPEC §2 (physical units)",
        }
        api = "estimate(a3, a2)"
    else:
        output = {
            "name": "signals",
            "shape": ["batch", len(outputs), time_steps],
            "dtype": "float32",
            "channels": outputs,
            "units": "m/s^2",
        }
        api = "denoise(x)" if isinstance(module, DenoisingAutoencoder) else "complete(a3, pu_u)"
    return {
        "schema": CONTRACT_SCHEMA,
        "model_class": type(module).__name__,
        "kind": module.kind,
        "api": api,
        "input": {
            "name": "accel",
            "shape": ["batch", len(inputs), time_steps],
            "dtype": "float32",
            "channels": inputs,
            "units": "m/s^2 (raw, unnormalised" + ("; pu_u = p_u * road height u)" if "pu_u" in inputs else ")"),
            "layout": "[batch, channels, time]",
        },
        "output": output,
        "dynamic_axes": ["batch"],
        "window": window,
        "time_steps": time_steps,
        "h": h,
        "target_names": outputs,
    }


__all__ = [
    "PhysicalGraph",
    "io_names",
    "export_time_steps",
    "reference_output",
    "parity_error",
    "contract",
    "CONTRACT_SCHEMA",
]
