"""Batches as the models read them: channel selection, measurement noise, statistics and the tensor dataset.

ChannelSpec(inputs, targets, aux).build(arrays, index) -> {x [B, C_in, N], y, aux, params [B, 10], index [B]}
apply_noise(x, sigma)   multiplicative noise x (1 + eta)
channel_stats(tensors)  per-channel mean/std of x, y, aux (the models' normalisation buffers)
TensorBatches           a split held in memory, served a batch at a time (with seeded val/test noise)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from hybridqcm.data.channels import (
    ChannelError,
    is_param,
    required_keys,
    select_channels,
    select_params,
    validate_channels,
)
from hybridqcm.data.sensor import SensorModel, additive_augmentation, apply_to_channels


def apply_noise(x: torch.Tensor, sigma: float | torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """Multiplicative measurement noise x (1 + eta), eta ~ N(0, sigma^2) per point.

    sigma: a float or a per-sample tensor [B] (broadcast over channels and time).
    """
    if isinstance(sigma, (int, float)) and sigma == 0:
        return x
    eta = (
        torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        if generator is not None
        else torch.randn_like(x)
    )
    if isinstance(sigma, torch.Tensor):
        sigma = sigma.to(x).reshape(-1, *([1] * (x.ndim - 1)))
    return x * (1 + sigma * eta)


class ChannelSpec:
    """Which channels a task reads: inputs (time), targets (time or parameters), clean auxiliaries."""

    def __init__(
        self,
        inputs: Sequence[str],
        targets: Sequence[str] | None = None,
        aux: Sequence[str] | None = None,
        targets_optional: bool = False,
    ) -> None:
        self.inputs = validate_channels(inputs, "inputs")
        if not self.inputs or is_param(self.inputs[0]):
            raise ChannelError(f"inputs: need at least one time channel, got {self.inputs}")
        self.targets = validate_channels(targets, "targets")
        self.aux = validate_channels(aux, "aux")
        if self.aux and is_param(self.aux[0]):
            raise ChannelError(f"aux: must be time channels, got {self.aux}")
        self.targets_optional = bool(targets_optional)

    @property
    def targets_are_params(self) -> bool:
        return bool(self.targets) and is_param(self.targets[0])

    def keys(self, available: Sequence[str] | None = None) -> tuple[set[str], set[str]]:
        """(needed keys, optional keys to read if present)."""
        needed = required_keys(self.inputs) | required_keys(self.aux)
        target_keys = required_keys(self.targets)
        optional = {"params", "profile_id"}
        if self.targets_optional:
            optional |= target_keys
        else:
            needed |= target_keys
        return needed, optional - needed

    def build(self, arrays: Mapping, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """Tensors for a sample set (no noise): x [M,C,N] f32, y, aux [M,A,N] (source dtype), params, index."""
        out = {"x": torch.as_tensor(select_channels(arrays, self.inputs)).float(), "index": index}
        if self.targets and all(k in arrays for k in required_keys(self.targets)):
            if self.targets_are_params:
                out["y"] = torch.as_tensor(select_params(arrays, self.targets)).double()
            else:
                out["y"] = torch.as_tensor(select_channels(arrays, self.targets)).float()
        if self.aux:
            # Kept in the source's precision: float32 from HDF5 (as stored; halves memory), float64 from the simulator.
            out["aux"] = torch.as_tensor(select_channels(arrays, self.aux))
        if "params" in arrays:
            out["params"] = torch.as_tensor(
                np.asarray(arrays["params"]) if not isinstance(arrays["params"], torch.Tensor) else arrays["params"]
            ).double()
        return out


def channel_stats(tensors: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Per-channel mean/std of x (and y) over samples and time; of log-parameters for parameter targets."""
    stats = {}
    x = tensors["x"].double()
    stats["input_mean"] = x.mean((0, 2))
    stats["input_std"] = x.std((0, 2)).clamp_min(1e-12)
    if "y" in tensors:
        y = tensors["y"].double()
        if y.ndim == 2:  # parameters: statistics of log p (all p > 0)
            stats["target_log_mean"] = y.log().mean(0)
            stats["target_log_std"] = y.log().std(0).clamp_min(1e-12)
        else:
            stats["target_mean"] = y.mean((0, 2))
            stats["target_std"] = y.std((0, 2)).clamp_min(1e-12)
    return stats


class TensorBatches(Dataset):
    """In-memory samples; fetched a batch at a time (`__getitems__`), noise applied per batch."""

    def __init__(
        self,
        tensors: Mapping[str, torch.Tensor],
        noise_sigma: float = 0.0,
        fixed_noise_seed: int | None = None,
        sensor: SensorModel | None = None,
        names: Sequence[str] = (),
        augment_max: float = 0.0,
    ) -> None:
        self.tensors = dict(tensors)
        self.noise_sigma = float(noise_sigma)
        self.sensor = sensor if sensor is not None and sensor.active else None
        self.names, self.augment_max = tuple(names), float(augment_max)
        self.n = int(self.tensors["x"].shape[0])
        self.noisy_x = None
        if self.noise_sigma > 0 and fixed_noise_seed is not None:
            generator = torch.Generator().manual_seed(int(fixed_noise_seed))
            self.noisy_x = apply_noise(self.tensors["x"], self.noise_sigma, generator)
        if self.sensor is not None and fixed_noise_seed is not None:
            self.noisy_x = apply_to_channels(
                self.sensor, self.tensors["x"], self.names, self.tensors["index"], salt=int(fixed_noise_seed)
            )

    def __len__(self) -> int:
        return self.n

    def __getitems__(self, indices: Sequence[int]) -> dict[str, torch.Tensor]:
        idx = torch.as_tensor(indices, dtype=torch.long)
        batch = {k: v[idx] for k, v in self.tensors.items()}
        if self.noisy_x is not None:
            batch["x"] = self.noisy_x[idx]
        elif self.noise_sigma > 0:
            batch["x"] = apply_noise(batch["x"], self.noise_sigma)
        elif self.sensor is not None:  # training: fresh noise per batch (the salt comes from the seeded global RNG)
            salt = int(torch.randint(1, 2**62, ()))
            batch["x"] = apply_to_channels(self.sensor, batch["x"], self.names, batch["index"], salt)
        if self.augment_max > 0:
            batch["x"] = additive_augmentation(batch["x"], self.names, self.augment_max)
        return batch

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[0] for k, v in self.__getitems__([i]).items()}
