"""qcm-estimate's inputs, streamed: the file is read in contiguous blocks of recordings.

Block k holds rows [k B, min((k+1) B, M)) of the split (B = batch_size, M = n_samples) and is
one predict batch, whatever the number of processes: the GN peer test and the multi-start
generator see the same batches in a 2-process run as in a 1-process one, so the estimates are
identical. A block is read from the HDF5 file when it is needed (the file is opened per read, in
whichever process or worker reads it), so memory holds one block, never the file.

Random numbers are those of the in-memory reading, bit for bit: the initial guesses
p0 = p_ref (1 + σ_init δ), δ rows of ONE draw [M, 10] from ``seed``, and the source's noise
a (1 + σ η), η rows of ONE draw [M, T, 3] from ``seed + 1`` (estimation/draws.py takes any slice
of such a draw). The sensor model seeds each sample by its index already.

    batch = {"accel" [b, T, 3], "road" [b, T], "pu" [b], "init" [b, 10], "index" [b] int64,
             "true" [b, 10] (file has params), "noise_std" [b, 3] / "noise_sigma" [b] (noise-aware),
             "window_status" [b] (0: fit it; estimation/window_check.py), "block" int}

A block's batch holds the windows to fit only; those a window check keeps from the fit (a car
standing still, a clipped channel) travel beside it as "skipped_index" / "skipped_status".
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from hybridqcm.data.hdf5 import read_split
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.draws import NormalStream
from hybridqcm.estimation.plan_settings import window_check_settings
from hybridqcm.estimation.window_check import WindowCheck, window_status
from hybridqcm.physics.parameters import CHANNELS, PhysicalConstants


@dataclass(frozen=True)
class InputSettings:
    """The config values the inputs depend on, as plain values (they travel to spawned ranks)."""

    seed: int
    init_sigma: float
    vehicle: tuple[tuple[str, float], ...]
    known_source: str
    pu_known: bool
    noise_sigma: float
    noise_weighting: bool
    window_check: WindowCheck = WindowCheck()

    @classmethod
    def from_config(cls, cfg) -> InputSettings:
        return cls(
            seed=int(cfg.seed),
            init_sigma=float(cfg.init.relative_sigma),
            vehicle=tuple((str(k), float(v)) for k, v in cfg.vehicle.items()),
            known_source=str(cfg.known_source),
            pu_known=bool(cfg.pu_known),
            noise_sigma=float(cfg.noise_sigma),
            noise_weighting=bool(cfg.noise_weighting),
            window_check=window_check_settings(cfg),
        )


class _Streams:
    """The two seeded draws of a run (δ, η), each read block after block in one pass."""

    def __init__(self, settings: InputSettings, n_samples: int, n_steps: int):
        self.delta = NormalStream(settings.seed, n_samples * 10)
        self.noise = NormalStream(settings.seed + 1, n_samples * n_steps * 3) if settings.noise_sigma > 0 else None


def build_inputs(cfg, plan: Mapping, rows: slice | None = None, streams: _Streams | None = None) -> dict:
    """Inputs of rows [start, stop) of the split (default: all n_samples): read, δ drawn, noise applied.

    cfg: the run config or its InputSettings. Returns the batch dict of the module docstring
    ("true" is None without params). Raises DatasetError/ConfigError naming the file and sample."""
    settings = cfg if isinstance(cfg, InputSettings) else InputSettings.from_config(cfg)
    n_total = int(plan["n_samples"])
    rows = slice(0, n_total) if rows is None else rows
    start, stop = int(rows.start), int(rows.stop)
    road_free = plan["base_excitation"] is not None
    keys = ["accel"] + ([] if road_free else ["road"]) + (["params"] if plan["has_params"] else [])
    try:
        if plan.get("seat") is not None:  # one seat of a half / full car, in the quarter car's layout
            from hybridqcm.data.vehicle_files import read_seat_split

            arrays = read_seat_split(
                plan["path"], plan["split"], plan["seat"], keys, n_steps=plan["n_read_steps"], index=slice(start, stop)
            )
        else:
            arrays = read_split(
                plan["path"], plan["split"], keys, n_steps=plan["n_read_steps"], index=slice(start, stop)
            )
    except DatasetError as error:
        if start == 0:
            raise
        raise DatasetError(f"{error} (in the block of rows {start}..{stop - 1})") from None
    return batch_from_arrays(settings, plan, arrays, start, streams)


def batch_from_arrays(cfg, plan: Mapping, arrays: Mapping, start: int = 0, streams: _Streams | None = None) -> dict:
    """The batch of rows [start, start + b) from their arrays: "accel" [b, T, 3] (a3, a2, a1) m/s², "road"
    [b, T] m (road-driven plans), "params" [b, 10] (plans with has_params); the initial guesses drawn,
    the source's noise and the sensor model applied, as build_inputs does for the file's rows."""
    settings = cfg if isinstance(cfg, InputSettings) else InputSettings.from_config(cfg)
    n_total = int(plan["n_samples"])
    road_free = plan["base_excitation"] is not None
    accel = torch.from_numpy(np.asarray(arrays["accel"], dtype=np.float64))
    stop = start + int(accel.shape[0])
    for c in plan["observed"]:  # unrecorded channels may be NaN in a file; the ones used may not
        column = accel[:, :, CHANNELS.index(c)]
        if not bool(torch.isfinite(column).all()):
            bad = start + int((~torch.isfinite(column)).any(1).nonzero()[0])
            raise ConfigError(
                f"{plan['path']}: /{plan['split']}/accel channel {c} has NaN/inf (sample {bad}); "
                f"it is in observed={plan['observed']}"
            )
    # A window standing still or clipped in a fitted channel is not fitted (estimation/window_check.py).
    fitted = [CHANNELS.index(c) for c in plan["observed"]]
    window = window_status(accel[:, :, fitted], settings.window_check)
    road = (
        torch.zeros(accel.shape[:2], dtype=torch.float64)
        if road_free
        else torch.from_numpy(np.asarray(arrays["road"], dtype=np.float64))
    )
    m = accel.shape[0]
    index = torch.arange(start, stop)
    streams = streams or _Streams(settings, n_total, accel.shape[1])
    p_ref = PhysicalConstants(**dict(settings.vehicle)).to_params()
    true = torch.from_numpy(np.asarray(arrays["params"], dtype=np.float64)) if plan["has_params"] else None

    # The same δ for every experiment: rows of one draw [n_samples, 10] from `seed`.
    delta = settings.init_sigma * torch.from_numpy(streams.delta.take(start * 10, stop * 10)).reshape(m, 10)
    init = p_ref * (1.0 + delta)
    init = torch.where(init > 0, init, p_ref.expand_as(init))  # a δ < -1 would start outside the domain
    from_file = true is not None and settings.known_source == "file"
    known_values = true if from_file else p_ref.expand(m, 10)
    for j in plan["known"]:
        init[:, j] = known_values[:, j]
    if settings.pu_known and from_file:
        pu = known_values[:, 9] - known_values[:, 8]
    else:  # the reference vehicle's (without pu_known only the U-Net reads it)
        pu = torch.full((m,), float(p_ref[9] - p_ref[8]), dtype=torch.float64)

    sigma = settings.noise_sigma
    if sigma > 0:
        per_row = accel.shape[1] * 3
        eta = torch.from_numpy(streams.noise.take(start * per_row, stop * per_row)).reshape(accel.shape)
        accel = accel * (1.0 + sigma * eta)
    sensor = plan["sensor"]
    out = {"accel": accel, "road": road, "pu": pu, "init": init, "true": true, "index": index, "window_status": window}
    if sensor.active:
        out["accel"] = sensor.apply(accel, index)
        if settings.noise_weighting:  # the user knows the sensor: weight each channel by 1/σ_c
            out["noise_std"] = sensor.noise_std(accel).clamp_min(1e-12)
    if sigma > 0 and settings.noise_weighting:
        out["noise_sigma"] = torch.full((m,), sigma, dtype=torch.float64)
    return out


def block_rows(n_samples: int, batch_size: int) -> list[tuple[int, int]]:
    """[(start, stop)] of every block: contiguous rows, at most batch_size each, in a power-of-two
    number of blocks whose sizes differ by at most one.

    Ranks take blocks round-robin, so with 1, 2, 4, ... processes each solves the same number of
    recordings (17 000 in blocks of 4 096 used to split 8 808 / 8 192 over two). The blocks depend
    on n_samples and batch_size only, never on the number of processes: a run resumed or repeated
    on another count solves the same batches, with the same estimates."""
    if n_samples < 1 or batch_size < 1:
        raise ValueError(f"block_rows: n_samples and batch_size must be >= 1, got {n_samples}, {batch_size}")
    count = 1 << (math.ceil(n_samples / batch_size) - 1).bit_length()  # next power of two >= ceil(n / size)
    count = min(count, n_samples)
    return [(n_samples * k // count, n_samples * (k + 1) // count) for k in range(count)]


class RecordingBlocks(torch.utils.data.Dataset):
    """Map-style dataset over the blocks still to estimate; item k is block ``blocks[k]``'s batch.

    Used with ``DataLoader(batch_size=None, sampler=RankBlocks(len(blocks)))``: one item is one
    predict batch, rank r of W takes the items r, r + W, ... The δ/η draws are continued block after
    block within a process."""

    def __init__(self, settings: InputSettings, plan: Mapping, blocks: list[tuple[int, int, int]]):
        self.settings = settings
        self.plan = dict(plan)
        self.blocks = list(blocks)  # (block id, start, stop)
        self._streams = None

    def __len__(self) -> int:
        return len(self.blocks)

    def __getitem__(self, k: int) -> dict:
        block, start, stop = self.blocks[k]
        if self._streams is None:  # per process / worker: opened where it is used
            self._streams = _Streams(self.settings, int(self.plan["n_samples"]), int(self.plan["n_read_steps"]))
        batch = build_inputs(self.settings, self.plan, slice(start, stop), self._streams)
        batch = without_skipped(batch)
        batch["block"] = int(block)
        return batch


def without_skipped(batch: Mapping) -> dict:
    """The batch of the windows to fit; those a window check kept from the fit (window_status != 0)
    travel beside it as "skipped_index" [k], "skipped_status" [k] and "skipped_true" [k, 10] (with a
    truth): their rows in the tables."""
    status = batch["window_status"]
    keep = status == 0
    b = int(status.shape[0])
    out = {
        key: value[keep] if isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == b else value
        for key, value in batch.items()
        if value is not None and key != "window_status"
    }
    out["skipped_index"] = batch["index"][~keep]
    out["skipped_status"] = status[~keep]
    if batch.get("true") is not None:
        out["skipped_true"] = batch["true"][~keep]
    return out


class RankBlocks(torch.utils.data.Sampler):
    """Items r, r + W, ... of ``n_items`` for rank r of the W processes of the default process group
    (read when iterated, after the strategy has set the group up; one process without one).

    Unrepeated, like Lightning's predict sampler (a padded sampler's repeats would rewrite the same
    shard), but a rank may get no item at all: fewer blocks than processes (a small file, or a
    resumed run with one block left) is a rank with nothing to do, where Lightning's sampler asserts.
    Use with ``Trainer(use_distributed_sampler=False)``."""

    def __init__(self, n_items: int):
        self.n_items = int(n_items)

    def _mine(self) -> range:
        dist = torch.distributed
        rank, world = (
            (dist.get_rank(), dist.get_world_size()) if dist.is_available() and dist.is_initialized() else (0, 1)
        )
        return range(rank, self.n_items, world)

    def __len__(self) -> int:
        return len(self._mine())

    def __iter__(self):
        return iter(self._mine())


__all__ = [
    "batch_from_arrays",
    "InputSettings",
    "build_inputs",
    "block_rows",
    "RecordingBlocks",
    "RankBlocks",
    "without_skipped",
]
