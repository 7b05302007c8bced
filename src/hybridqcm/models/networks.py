"""Plain nn.Modules of SPEC §6 (input as channels x time, [B, C, N]); sizes configurable.

Strided convolutions use TensorFlow-style "same" padding (output length ceil(N / stride)), which
is what reproduces the source's weight counts: ParameterCNN 1 361 332 (flatten 100 x 125 at
N = 500) and DenoisingCAE 1 010 302 with output length N.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

ACTIVATIONS = {
    "relu": nn.ReLU,
    "gelu": nn.GELU,
    "elu": nn.ELU,
    "tanh": nn.Tanh,
    "silu": nn.SiLU,
    "leaky_relu": nn.LeakyReLU,
}


def activation(name: str) -> nn.Module:
    if name not in ACTIVATIONS:
        raise ValueError(f"unknown activation {name!r}; choose one of {sorted(ACTIVATIONS)}")
    return ACTIVATIONS[name]()


def same_length(n: int, stride: int) -> int:
    return math.ceil(n / stride)


class SameConv1d(nn.Conv1d):
    """Conv1d with "same" padding for any stride: [B, C, N] -> [B, C', ceil(N / stride)]."""

    def forward(self, x: Tensor) -> Tensor:
        n, k, s = x.shape[-1], self.kernel_size[0], self.stride[0]
        total = max((same_length(n, s) - 1) * s + k - n, 0)
        return super().forward(F.pad(x, (total // 2, total - total // 2)))


class SameConvTranspose1d(nn.ConvTranspose1d):
    """Transposed conv, output cropped to N * stride ("same"): [B, C, N] -> [B, C', N * stride]."""

    def forward(self, x: Tensor) -> Tensor:
        n, s = x.shape[-1], self.stride[0]
        y = super().forward(x)  # length (n - 1) s + k
        excess = y.shape[-1] - n * s
        left = excess // 2
        return y[..., left : left + n * s] if excess > 0 else F.pad(y, (0, -excess))


def _mlp(width: int, hidden: Sequence[int], out_features: int, activation_name: str, dropout: float) -> list[nn.Module]:
    """The dense head's layers: Linear -> activation (-> Dropout) per hidden width, then Linear to the outputs."""
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(width, h), activation(activation_name)] + ([nn.Dropout(dropout)] if dropout > 0 else [])
        width = h
    return [*layers, nn.Linear(width, out_features)]


class ParameterCNN(nn.Module):
    """(a3, a2) [B, 2, window] -> 2 outputs (normalised parameters).

    Reference: Conv1d(2->100, k50, s2) -> Conv1d(100->100, k10, s2) -> flatten -> 100 -> 10 -> 2.
    """

    def __init__(
        self,
        in_channels: int = 2,
        window: int = 500,
        channels: Sequence[int] = (100, 100),
        kernels: Sequence[int] = (50, 10),
        strides: Sequence[int] = (2, 2),
        hidden: Sequence[int] = (100, 10),
        out_features: int = 2,
        activation_name: str = "relu",
        dropout: float = 0.0,
    ) -> None:
        super().__init__()
        if not len(channels) == len(kernels) == len(strides):
            raise ValueError(
                f"ParameterCNN: channels {channels}, kernels {kernels}, strides {strides} must have equal lengths"
            )
        layers: list[nn.Module] = []
        c, n = in_channels, int(window)
        for c_out, k, s in zip(channels, kernels, strides):
            layers += [SameConv1d(c, c_out, k, stride=s), activation(activation_name)]
            c, n = c_out, same_length(n, s)
        self.features = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Flatten(), *_mlp(c * n, hidden, out_features, activation_name, dropout))
        self.window, self.in_channels, self.flat_features = int(window), in_channels, c * n

    def forward(self, x: Tensor) -> Tensor:
        if x.shape[1:] != (self.in_channels, self.window):
            raise ValueError(f"ParameterCNN expects [B, {self.in_channels}, {self.window}], got {tuple(x.shape)}")
        return self.head(self.features(x))


class SpectralCNN(nn.Module):
    """(a3, a2) [B, C, window] -> outputs: a filter bank, its log band energies, an MLP.

    The windows of a drive are stationary and the vehicle is linear, so what identifies its
    parameters is second-order: the spectra of the channels and their cross-spectrum, i.e. the
    transfer function between them. The last convolution is linear (a bank of `channels[-1]` FIR
    filters, each mixing all input channels, so cross-spectra are reachable); the mean square of
    each filter output over the window [B, F] is a band energy, and its log turns the ratios a
    transfer function is made of into differences the MLP reads linearly. Earlier convolutions
    (with activations) are optional. Pooling over time makes the output shift-invariant, so a
    window cut anywhere in a drive is one case, not many; stride 1 keeps every sample's phase.
    With `remove_mean` each channel's mean over the window is subtracted first, so a constant
    accelerometer bias changes nothing (the mean of a stationary acceleration is ~0 anyway).
    """

    def __init__(
        self,
        in_channels: int = 2,
        window: int = 500,
        channels: Sequence[int] = (64,),
        kernels: Sequence[int] = (25,),
        hidden: Sequence[int] = (128, 64),
        out_features: int = 2,
        activation_name: str = "gelu",
        dropout: float = 0.0,
        remove_mean: bool = True,
    ) -> None:
        super().__init__()
        if not channels or len(channels) != len(kernels):
            raise ValueError(f"SpectralCNN: channels {channels} and kernels {kernels} must be non-empty, equal lengths")
        if int(window) < max(kernels):
            raise ValueError(f"SpectralCNN: window {window} is shorter than the longest kernel {max(kernels)}")
        layers: list[nn.Module] = []
        c = in_channels
        for i, (c_out, k) in enumerate(zip(channels, kernels)):
            layers.append(nn.Conv1d(c, c_out, k))  # "valid": no padded edges in the energies
            if i < len(channels) - 1:
                layers.append(activation(activation_name))
            c = c_out
        self.features = nn.Sequential(*layers)
        self.head = nn.Sequential(*_mlp(c, hidden, out_features, activation_name, dropout))
        self.window, self.in_channels, self.remove_mean = int(window), in_channels, bool(remove_mean)

    def band_energies(self, x: Tensor) -> Tensor:
        """Log mean-square of each filter's output over the window: [B, C, window] -> [B, F]."""
        y = self.features(x - x.mean(-1, keepdim=True) if self.remove_mean else x)
        return torch.log(y.square().mean(-1) + 1e-6)  # the floor keeps a silent filter finite

    def forward(self, x: Tensor) -> Tensor:
        if x.shape[1:] != (self.in_channels, self.window):
            raise ValueError(f"SpectralCNN expects [B, {self.in_channels}, {self.window}], got {tuple(x.shape)}")
        return self.head(self.band_energies(x))


class DenoisingCAE(nn.Module):
    """Convolutional autoencoder [B, C, N] -> [B, C, N] (any N).

    Reference: Conv(2->50, k50, s2) -> Conv(50->100, k50, s2) -> ConvT(100->100, k50, s2) ->
    ConvT(100->50, k50, s2) -> ConvT(50->2, k50, s1), linear output.
    """

    def __init__(
        self,
        in_channels: int = 2,
        channels: Sequence[int] = (50, 100),
        kernel_size: int = 50,
        activation_name: str = "relu",
        residual: bool = False,
    ) -> None:
        super().__init__()
        enc: list[nn.Module] = []
        c = in_channels
        for c_out in channels:
            enc += [SameConv1d(c, c_out, kernel_size, stride=2), activation(activation_name)]
            c = c_out
        dec: list[nn.Module] = []
        for c_out in list(channels[::-1][:1]) + list(channels[::-1][1:]):
            dec += [SameConvTranspose1d(c, c_out, kernel_size, stride=2), activation(activation_name)]
            c = c_out
        dec.append(SameConvTranspose1d(c, in_channels, kernel_size, stride=1))
        self.encoder, self.decoder = nn.Sequential(*enc), nn.Sequential(*dec)
        self.depth, self.residual = len(channels), residual

    def forward(self, x: Tensor) -> Tensor:
        n = x.shape[-1]
        multiple = 2**self.depth
        pad = (-n) % multiple
        z = F.pad(x, (0, pad)) if pad else x
        y = self.decoder(self.encoder(z))[..., :n]
        return x + y if self.residual else y


class _DoubleConv(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, k: int, batchnorm: bool, act: str) -> None:
        layers: list[nn.Module] = []
        for a, b in ((c_in, c_out), (c_out, c_out)):
            layers += [nn.Conv1d(a, b, k, padding=k // 2, bias=not batchnorm)]
            layers += [nn.BatchNorm1d(b)] if batchnorm else []
            layers += [activation(act)]
        super().__init__(*layers)


class UNet1d(nn.Module):
    """1-D U-Net [B, C_in, N] -> [B, C_out, N] (any N; padded to a multiple of 2^(levels-1)).

    Filters 4-8-16-32 with 2x max-pooling along time, batch-norm, transposed-conv upsampling
    and skip concatenations; 29 166 weights with kernel 9 (SPEC: 30 653 for the 2-D original).
    """

    def __init__(
        self,
        in_channels: int = 2,
        out_channels: int = 2,
        filters: Sequence[int] = (4, 8, 16, 32),
        kernel_size: int = 9,
        batchnorm: bool = True,
        activation_name: str = "relu",
    ) -> None:
        super().__init__()
        if kernel_size % 2 == 0:
            raise ValueError(f"UNet1d: kernel_size must be odd (symmetric padding), got {kernel_size}")
        self.down = nn.ModuleList()
        c = in_channels
        for f in filters:
            self.down.append(_DoubleConv(c, f, kernel_size, batchnorm, activation_name))
            c = f
        self.up = nn.ModuleList()
        self.merge = nn.ModuleList()
        for f in reversed(filters[:-1]):
            self.up.append(nn.ConvTranspose1d(c, f, 2, stride=2))
            self.merge.append(_DoubleConv(2 * f, f, kernel_size, batchnorm, activation_name))
            c = f
        self.out = nn.Conv1d(c, out_channels, 1)
        self.levels = len(filters)

    def forward(self, x: Tensor) -> Tensor:
        n = x.shape[-1]
        pad = (-n) % (2 ** (self.levels - 1))
        z = F.pad(x, (0, pad), mode="replicate") if pad else x
        skips = []
        for i, block in enumerate(self.down):
            z = block(z)
            if i < self.levels - 1:
                skips.append(z)
                z = F.max_pool1d(z, 2)
        for up, merge in zip(self.up, self.merge):
            z = merge(torch.cat([up(z), skips.pop()], 1))
        return self.out(z)[..., :n]


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# The allow-list of networks a module (or a checkpoint's hyper-parameters) may build, by `_target_`.
NETWORKS = {
    f"hybridqcm.models.networks.{cls.__name__}": cls for cls in (ParameterCNN, SpectralCNN, DenoisingCAE, UNet1d)
}

__all__ = [
    "ParameterCNN",
    "SpectralCNN",
    "DenoisingCAE",
    "UNet1d",
    "SameConv1d",
    "SameConvTranspose1d",
    "count_parameters",
]
