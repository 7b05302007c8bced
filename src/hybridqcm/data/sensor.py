"""The accelerometer model (SPEC §9), applied when data is read so one clean file serves every
noise level.

    additive:        a + sigma_c s_c eta + bias_c s_c    (eta ~ N(0, 1) per point)
    multiplicative:  a (1 + sigma_c eta) + bias_c s_c    (the source's model, SPEC §5)
    then, if quantisation > 0, rounding to multiples of the step.

s_c is the sample's RMS of channel c over the window when `relative` (sigma, bias are fractions
of the signal), else 1 (sigma, bias in m/s^2). Channels are (a3, a2, a1).

`sigma_range` = [low, high] instead of sigma: every sample draws its own level s_i, log-uniform on
[low, high], and uses sigma_c = s_i on every channel (a stream of recordings from loggers of many
noise floors; log-uniform so that each decade of noise is equally represented).

Reproducibility: the noise of sample i comes from its own generator seeded by (seed, salt, i),
so it is the same whatever the batching or order; evaluation uses a fixed salt, training a
fresh one per batch (fresh noise every epoch).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from hybridqcm.physics.parameters import CHANNELS

KINDS = ("none", "additive", "multiplicative")


def _per_channel(value, name: str) -> tuple[float, float, float]:
    values = [value] if isinstance(value, (int, float)) else list(value)
    if len(values) == 1:
        values = values * 3
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"sensor.{name} must be a number or one per channel (a3, a2, a1), got {value!r}") from None
    if len(out) != 3:
        raise ValueError(f"sensor.{name} must be a number or 3 numbers (a3, a2, a1), got {value!r}")
    if not all(math.isfinite(v) and v >= 0 for v in out):
        raise ValueError(f"sensor.{name} must be finite and >= 0, got {value!r}")
    return out


def keyed_normals(keys: Sequence[Sequence[int]], shape: tuple[int, ...]) -> Tensor:
    """[len(keys), *shape] float64 standard normals, row k from a generator of its own seeded by
    numpy's SeedSequence(keys[k]): a row depends on its key alone, never on the other rows of the
    batch (per-sample sensor noise, per-recording restart draws)."""
    # drawn on the CPU whatever the default device (GN on a GPU): the same numbers on every machine
    out = torch.empty(len(keys), *shape, dtype=torch.float64, device="cpu")
    generator = torch.Generator()
    for row, key in enumerate(keys):
        state = np.random.SeedSequence([int(k) for k in key]).generate_state(2, np.uint32)
        generator.manual_seed(int(state[0]) << 32 | int(state[1]))
        out[row] = torch.randn(*shape, generator=generator, dtype=torch.float64, device="cpu")
    return out


@dataclass
class SensorModel:
    kind: str = "none"  # none | additive | multiplicative
    sigma: float | Sequence[float] = 0.0  # noise std per channel (a3, a2, a1)
    relative: bool = True  # sigma and bias as fractions of each sample's channel RMS; else m/s^2
    bias: float | Sequence[float] = 0.0  # constant bias per channel
    quantisation: float = 0.0  # step in m/s^2, 0 = none
    seed: int = 0
    sigma_range: Sequence[float] | None = None  # [low, high]: per-sample level, log-uniform (replaces sigma)

    def validate(self) -> SensorModel:
        """Checks every field (one-line ValueError); returns self."""
        if self.kind not in KINDS:
            raise ValueError(f"sensor.kind = {self.kind!r} is not known; choose one of {list(KINDS)}")
        self._sigma = _per_channel(self.sigma, "sigma")
        self._bias = _per_channel(self.bias, "bias")
        q = float(self.quantisation)
        if not (math.isfinite(q) and q >= 0):
            raise ValueError(f"sensor.quantisation must be finite and >= 0, got {self.quantisation!r}")
        self._range = None
        if self.sigma_range is not None:
            try:
                low, high = (float(v) for v in self.sigma_range)
            except (TypeError, ValueError):
                raise ValueError(f"sensor.sigma_range must be [low, high], got {self.sigma_range!r}") from None
            if not (math.isfinite(high) and 0 < low <= high):
                raise ValueError(f"sensor.sigma_range must satisfy 0 < low <= high, got {self.sigma_range!r}")
            if any(self._sigma):
                raise ValueError(
                    f"sensor.sigma_range = {self.sigma_range!r} replaces sensor.sigma = {self.sigma!r}: set sigma=0"
                )
            if self.kind == "none":
                raise ValueError("sensor.kind = 'none' takes no sigma_range; pick sensor=additive or multiplicative")
            self._range = (low, high)
        if self.kind == "none" and (any(self._sigma) or any(self._bias) or q > 0):
            raise ValueError(
                f"sensor.kind = 'none' takes no sigma, bias or quantisation (got sigma={self.sigma!r}, "
                f"bias={self.bias!r}, quantisation={q}); pick sensor=additive or sensor=multiplicative"
            )
        return self

    @property
    def active(self) -> bool:
        return self.kind != "none"

    def _checked(self) -> SensorModel:
        return self if hasattr(self, "_sigma") else self.validate()

    def describe(self) -> str:
        """One line for report titles, e.g. 'additive noise 5 % of channel RMS' or 'none'."""
        self._checked()
        if not self.active:
            return "none"

        def amount(values: Sequence[float], percent: bool) -> str:
            shown = [f"{100 * v:g} %" if percent else f"{v:g} m/s²" for v in values]
            return shown[0] if len(set(shown)) == 1 else "(a3, a2, a1) = " + ", ".join(shown)

        # multiplicative sigma is always a fraction of the signal itself; the rest follows `relative`
        percent = self.relative or self.kind == "multiplicative"
        of_rms = " of channel RMS" if self.relative and self.kind == "additive" else ""
        if self._range is not None:
            low, high = (amount([v], percent) for v in self._range)
            level = f"{low} to {high}"
        else:
            level = amount(self._sigma, percent)
        per_sample = " (log-uniform per sample)" if self._range is not None else ""
        parts = [f"{self.kind} noise {level}{of_rms}{per_sample}"]
        if any(self._bias):
            parts.append(f"bias {amount(self._bias, self.relative)}{' of channel RMS' if self.relative else ''}")
        if float(self.quantisation) > 0:
            parts.append(f"quantisation {float(self.quantisation):g} m/s²")
        return ", ".join(parts)

    def _noise(self, index: Tensor, n_steps: int, salt: int) -> Tensor:
        """eta [b, T, 3] float64, sample i's from its own generator seeded by (seed, salt, i)."""
        keys = [[int(self.seed), int(salt) % 2**63, int(i) % 2**63] for i in index.tolist()]
        return keyed_normals(keys, (n_steps, 3))

    def levels(self, index: Tensor, salt: int = 0) -> Tensor:
        """[b, 3] noise level sigma_c per sample: the configured sigma, or with `sigma_range` a log-uniform
        draw per sample from its own generator seeded by (seed, salt, i, 1) (a stream apart from eta's)."""
        self._checked()
        if self._range is None:
            return torch.tensor(self._sigma, dtype=torch.float64).expand(index.shape[0], 3)
        low, high = self._range
        u = torch.tensor(
            [
                np.random.default_rng(
                    np.random.SeedSequence([int(self.seed), int(salt) % 2**63, int(i) % 2**63, 1])
                ).random()
                for i in index.tolist()
            ],
            dtype=torch.float64,
        )
        return (low * (high / low) ** u)[:, None].expand(-1, 3)

    def _scale(self, accel: Tensor) -> Tensor:
        """[b, 3]: each sample's channel RMS (relative) or ones."""
        if self.relative:
            return accel.double().pow(2).mean(1).sqrt()
        return torch.ones(accel.shape[0], 3, dtype=torch.float64, device=accel.device)

    def apply(self, accel: Tensor, index: Tensor, salt: int = 0) -> Tensor:
        """accel [b, T, 3] (NaN channels stay NaN), index [b] global sample ids -> measured accel [b, T, 3]
        (same dtype). The noise of sample i depends only on (seed, salt, i)."""
        self._checked()
        if not self.active:
            return accel
        if accel.ndim != 3 or accel.shape[-1] != 3 or index.shape != accel.shape[:1]:
            raise ValueError(
                f"sensor: accel must be [b, T, 3] and index [b], got {tuple(accel.shape)}, {tuple(index.shape)}"
            )
        x = accel.double()
        sigma = self.levels(index, salt)[:, None, :].to(x.device)  # [b, 1, 3]
        bias = torch.tensor(self._bias, dtype=torch.float64)
        scale = self._scale(x)[:, None, :]  # [b, 1, 3]
        eta = self._noise(index, x.shape[1], salt).to(x.device)
        if self.kind == "additive":
            x = x + sigma * scale * eta
        else:
            x = x * (1 + sigma * eta)
        x = x + bias * scale
        if self.quantisation > 0:
            x = torch.round(x / self.quantisation) * self.quantisation
        return x.to(accel.dtype)

    def noise_std(self, accel: Tensor, index: Tensor | None = None, salt: int = 0) -> Tensor:
        """[b, 3] nominal noise std per channel (for residual weighting): sigma s_c (additive) or
        sigma RMS_c (multiplicative), with the quantisation's step/sqrt(12) added in quadrature.
        With `sigma_range` the per-sample levels need the sample ids `index` (and apply's salt)."""
        self._checked()
        if self._range is not None and index is None:
            raise ValueError(
                "sensor.sigma_range: per-sample noise levels need the sample ids (noise_std(accel, index))"
            )
        sigma = torch.tensor(self._sigma, dtype=torch.float64) if self._range is None else self.levels(index, salt)
        if self.kind == "multiplicative":
            std = sigma * accel.double().pow(2).mean(1).sqrt()
        elif self.kind == "additive":
            std = sigma * self._scale(accel)
        else:
            std = torch.zeros(accel.shape[0], 3, dtype=torch.float64)
        return (std.pow(2) + float(self.quantisation) ** 2 / 12).sqrt()


def build_sensor(spec: Mapping | SensorModel | None) -> SensorModel:
    """A validated SensorModel from a config mapping (unknown keys: one-line ValueError)."""
    if spec is None:
        return SensorModel().validate()
    if isinstance(spec, SensorModel):
        return spec.validate()
    spec = dict(spec)
    unknown = sorted(set(spec) - set(SensorModel.__dataclass_fields__))
    if unknown:
        raise ValueError(f"sensor: unknown option(s) {unknown}; known: {sorted(SensorModel.__dataclass_fields__)}")
    return SensorModel(**spec).validate()


def apply_to_channels(sensor: SensorModel, x: Tensor, names: Sequence[str], index: Tensor, salt: int = 0) -> Tensor:
    """The sensor on the accelerometer channels of x [b, C, N] named `names` (others, e.g. pu_u, untouched)."""
    if not sensor.active:
        return x
    where = [(c, CHANNELS.index(n)) for c, n in enumerate(names) if n in CHANNELS]
    if not where:
        return x
    accel = torch.full((x.shape[0], x.shape[2], 3), float("nan"), dtype=x.dtype)
    for c, k in where:
        accel[..., k] = x[:, c]
    measured = sensor.apply(accel, index, salt)
    out = x.clone()
    for c, k in where:
        out[:, c] = measured[..., k]
    return out


def additive_augmentation(
    x: Tensor, names: Sequence[str], sigma_max: float, generator: torch.Generator | None = None
) -> Tensor:
    """Training augmentation: additive white noise on the accelerometer channels of x [b, C, N],
    std = s * RMS of the sample's channel, s ~ U[0, sigma_max] per sample."""
    if sigma_max <= 0:
        return x
    rows = [c for c, n in enumerate(names) if n in CHANNELS]
    if not rows:
        return x
    level = sigma_max * torch.rand(x.shape[0], generator=generator, dtype=torch.float64).to(x.dtype)
    out = x.clone()
    part = out[:, rows]
    rms = part.pow(2).mean(-1, keepdim=True).sqrt()
    noise = torch.randn(part.shape, generator=generator, dtype=torch.float64).to(x.dtype)
    out[:, rows] = part + level[:, None, None] * rms * noise
    return out


__all__ = ["SensorModel", "build_sensor", "apply_to_channels", "additive_augmentation", "keyed_normals", "KINDS"]
