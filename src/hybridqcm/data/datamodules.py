"""Lightning datamodules: a fixed HDF5 dataset (SPEC §5) or an endless stream of fresh simulations.

Both yield batches as dicts, in physical units (the models normalise inputs themselves, so a
checkpoint accepts raw data at inference):

    x       float32 [B, C_in, N]   input channels, with multiplicative noise a (1 + eta) if sigma > 0
    y       float32 [B, C_out, N]  target time channels (clean)   or  float64 [B, P] target parameters
    aux     float [B, C_aux, N]    clean auxiliary channels, e.g. a3 v3 v2 q3 q2 for the physics residual
                                   (float64 when streamed, float32 from HDF5 as stored)
    params  float64 [B, 10]        all parameters, where the data has them (for metrics)
    index   int64   [B]            sample index within its split (for predictions.csv)

Noise: training batches draw fresh eta every time; validation/test noise is drawn once from a
seeded generator, so a metric at sigma > 0 is reproducible. Two ways to ask for it:
`noise_sigma` (the source's multiplicative a (1 + eta), kept bit-for-bit for the reproduction
tables) or `sensor` (data/sensor.py: additive / multiplicative noise, bias, quantisation; the noise
of a sample depends only on (sensor.seed, sample index), whatever the batching). Not both.
`train_additive_max` > 0 adds, to training batches only, additive noise of a per-sample level
drawn from U[0, max] times the channel RMS (augmentation for realistic sensors).

Normalisation statistics (per channel mean/std of inputs and targets over the training split)
are computed in `setup` and kept in `stats` (and in the datamodule's state_dict, hence in
checkpoints). The models compute their own normalisation buffers from `stats_batch()`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from lightning import LightningDataModule
from torch.utils.data import DataLoader, Dataset

from hybridqcm.data.batches import ChannelSpec, TensorBatches, channel_stats
from hybridqcm.data.hdf5 import dataset_info, read_split
from hybridqcm.data.sensor import SensorModel, build_sensor
from hybridqcm.data.stream import SimulatedStream, StreamSimulator
from hybridqcm.errors import DatasetError

log = logging.getLogger(__name__)


def _identity_collate(batch):
    return batch


def _check_sigma(sigma: float, where: str) -> float:
    sigma = float(sigma)
    if not math.isfinite(sigma) or sigma < 0:
        raise ValueError(f"{where}: noise_sigma must be a finite number >= 0, got {sigma}")
    return sigma


class _BaseDataModule(LightningDataModule):
    """Shared channel handling, statistics and loaders."""

    def __init__(
        self,
        inputs: Sequence[str] = ("a3", "a2"),
        targets: Sequence[str] | None = ("p1", "p2"),
        aux: Sequence[str] | None = None,
        window: int = 500,
        noise_sigma: float = 0.0,
        batch_size: int = 256,
        eval_batch_size: int | None = None,
        num_workers: int = 0,
        pin_memory: bool = False,
        seed: int = 0,
        targets_optional: bool = False,
        stats_samples: int = 2048,
        sensor: Mapping | SensorModel | None = None,
        train_additive_max: float = 0.0,
    ) -> None:
        super().__init__()
        self.spec = ChannelSpec(inputs, targets, aux, targets_optional)
        self.window = int(window)
        if self.window < 1:
            raise ValueError(f"{type(self).__name__}: window must be >= 1, got {window}")
        self.noise_sigma = _check_sigma(noise_sigma, type(self).__name__)
        self.sensor = build_sensor(sensor)
        if self.sensor.active and self.noise_sigma > 0:
            raise ValueError(
                f"{type(self).__name__}: noise_sigma = {self.noise_sigma} and sensor.kind = {self.sensor.kind!r} "
                f"both add noise; use one (noise_sigma is the source's multiplicative model)"
            )
        self.train_additive_max = float(train_additive_max)
        if not (math.isfinite(self.train_additive_max) and self.train_additive_max >= 0):
            raise ValueError(
                f"{type(self).__name__}: train_additive_max must be a finite number >= 0, got {train_additive_max}"
            )
        if int(batch_size) < 1:
            raise ValueError(f"{type(self).__name__}: batch_size must be >= 1, got {batch_size}")
        self.batch_size = int(batch_size)
        self.eval_batch_size = int(eval_batch_size or max(batch_size, 512))
        self.num_workers = int(num_workers)
        self.pin_memory = bool(pin_memory)
        self.seed = int(seed)
        self.stats_samples = int(stats_samples)
        self.stats: dict[str, torch.Tensor] = {}
        self.data_train: Dataset | None = None
        self.data_val: Dataset | None = None
        self.data_test: Dataset | None = None

    # -- to be provided -------------------------------------------------------------------------
    def stats_batch(self, n: int | None = None) -> dict[str, torch.Tensor]:
        """Up to n clean training samples (a batch dict) for model normalisation statistics."""
        raise NotImplementedError

    # -- loaders ------------------------------------------------------------------------------------
    def _loader(self, dataset: Dataset | None, shuffle: bool, batch_size: int) -> DataLoader:
        if dataset is None:
            raise RuntimeError(f"{type(self).__name__}: call setup() before asking for a dataloader")
        return DataLoader(
            dataset,
            batch_size=batch_size,
            shuffle=shuffle,
            collate_fn=_identity_collate,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=False,
        )

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.data_val, False, self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.data_test, False, self.eval_batch_size)

    def predict_dataloader(self) -> DataLoader:
        return self.test_dataloader()

    def state_dict(self) -> dict[str, Any]:
        return {
            "stats": {k: v.clone() for k, v in self.stats.items()},
            "inputs": self.spec.inputs,
            "targets": self.spec.targets,
            "window": self.window,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.stats = dict(state_dict.get("stats", {}))


class HDF5DataModule(_BaseDataModule):
    """A SPEC §5 HDF5 file: train/val carved from `train_split`, test from `test_split`.

    The validation part is whole road profiles (when the file has profile_id) chosen by `seed`,
    so validation never sees a road the network trained on. `limit_*` cap sample counts for
    quick runs (prefixes; the file's splits are shuffled by class at generation).
    """

    def __init__(
        self,
        path: str,
        train_split: str = "train",
        test_split: str = "test",
        val_fraction: float = 0.1,
        limit_train: int | None = None,
        limit_test: int | None = None,
        seat: str | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.path = Path(str(path))
        # a half / full car file: the channels of this seat, in the quarter car's layout (a3 the seat, a2 its
        # base; p1, p2 its c3/m3, k3/m3; data/vehicle_files.read_seat_split); None: a quarter-car file
        self.seat = None if seat is None else str(seat)
        self.train_split, self.test_split = train_split, test_split
        if not 0 <= float(val_fraction) < 1:
            raise ValueError(f"HDF5DataModule: val_fraction must be in [0, 1), got {val_fraction}")
        self.val_fraction = float(val_fraction)
        self.limit_train = None if limit_train is None else int(limit_train)
        self.limit_test = None if limit_test is None else int(limit_test)
        self._train_tensors: dict[str, torch.Tensor] | None = None

    def check(self, stages: Sequence[str] = ("fit", "test")) -> dict:
        """Validate file, splits, keys and window without reading the data; returns dataset_info."""
        info = dataset_info(self.path)
        needed, _ = self.spec.keys()
        splits = ([self.train_split] if "fit" in stages else []) + ([self.test_split] if "test" in stages else [])
        for split in splits:
            if split not in info["splits"]:
                raise DatasetError(
                    f"{self.path}: split {split!r} not found; available splits: {sorted(info['splits'])}"
                )
            have = self._keys(info, split)
            missing = sorted(needed - set(have))
            if missing:
                raise DatasetError(
                    f"{self.path}: /{split} lacks dataset(s) {missing} needed for channels "
                    f"inputs={self.spec.inputs} targets={self.spec.targets} aux={self.spec.aux}; it has {have}"
                )
            occupant = info["splits"][split].get("occupant", "rigid")
            if split == self.train_split and "fit" in stages and self.spec.aux and occupant != "rigid":
                # the physics residual a3 = -p1 (v3 - v2) - p2 (q3 - q2) is the rigid occupant's equation
                raise DatasetError(
                    f"{self.path}: /{split} holds seated persons (occupant = {occupant}); the physics-residual "
                    f"loss (aux {list(self.spec.aux)}) assumes a rigid occupant: train the labelled CNN on it"
                )
            stored = info["splits"][split]["n_steps"]
            if stored is not None and self.window > stored:
                raise DatasetError(
                    f"{self.path}: window = {self.window} is longer than the {stored} steps stored in /{split}"
                )
        return info

    def _keys(self, info: dict, split: str) -> list[str]:
        """The keys /<split> offers: the file's, or its seat view's (data/vehicle_files.py)."""
        from hybridqcm.data.vehicle_files import QUARTER_CAR, seat_split_info, vehicle_of

        if vehicle_of(info) == QUARTER_CAR:
            if self.seat is not None:
                raise DatasetError(f"{self.path}: data.seat={self.seat!r} but this is a quarter-car file (one seat)")
            return info["splits"][split]["keys"]
        return seat_split_info(self.path, split, self.seat)["keys"]

    def _read(self, split: str, limit: int | None, info: dict) -> dict[str, torch.Tensor]:
        needed, optional = self.spec.keys()
        have = set(self._keys(info, split))
        keys = sorted(needed | (optional & have))
        n = info["splits"][split]["n_samples"]
        index = slice(0, min(n, limit)) if limit is not None else None
        from hybridqcm.data.vehicle_files import QUARTER_CAR, read_seat_split, vehicle_of

        if vehicle_of(info) != QUARTER_CAR:  # a seat of a half / full car
            arrays = read_seat_split(self.path, split, self.seat, keys, n_steps=self.window, index=index)
            arrays.pop("k3", None)
        else:
            arrays = read_split(self.path, split, keys, n_steps=self.window, index=index)
        m = arrays[keys[0]].shape[0]
        tensors = self.spec.build(arrays, torch.arange(m))
        for part, names in (("x", self.spec.inputs), ("aux", self.spec.aux), ("y", self.spec.targets)):
            if part in tensors and tensors[part].ndim == 3 and m:
                # a file may hold an unrecorded (all-NaN) channel; only a channel this task reads is an error
                missing = [n for c, n in enumerate(names) if bool(torch.isnan(tensors[part][:, c]).all())]
                if missing:
                    raise DatasetError(
                        f"{self.path}: /{split} channel(s) {missing} are not recorded (all NaN) "
                        f"but this task reads them as {'inputs' if part == 'x' else part}"
                    )
        if "profile_id" in arrays:
            tensors["profile_id"] = torch.as_tensor(arrays["profile_id"]).long()
        return tensors

    def _carve(self, tensors: dict[str, torch.Tensor]) -> tuple[dict, dict]:
        m = tensors["x"].shape[0]
        generator = torch.Generator().manual_seed(self.seed)
        if self.val_fraction == 0:
            return tensors, {k: v[:0] for k, v in tensors.items()}
        if "profile_id" in tensors:
            profiles = tensors["profile_id"].unique()
            n_val = max(1, round(self.val_fraction * len(profiles))) if len(profiles) > 1 else 0
            chosen = profiles[torch.randperm(len(profiles), generator=generator)[:n_val]]
            is_val = torch.isin(tensors["profile_id"], chosen)
        else:
            is_val = torch.zeros(m, dtype=torch.bool)
            is_val[torch.randperm(m, generator=generator)[: max(1, round(self.val_fraction * m))]] = True
        if is_val.all() or not is_val.any():  # too few profiles: fall back to samples
            is_val = torch.zeros(m, dtype=torch.bool)
            is_val[torch.randperm(m, generator=generator)[: max(1, round(self.val_fraction * m))]] = True
        return ({k: v[~is_val] for k, v in tensors.items()}, {k: v[is_val] for k, v in tensors.items()})

    def setup(self, stage: str | None = None) -> None:
        stages = ("fit", "test") if stage is None else ("fit",) if stage in ("fit", "validate") else ("test",)
        info = self.check(stages)
        if "fit" in stages and self.data_train is None:
            train, val = self._carve(self._read(self.train_split, self.limit_train, info))
            self._train_tensors = train
            self.stats = channel_stats(train)
            self.data_train = TensorBatches(
                train, self.noise_sigma, sensor=self.sensor, names=self.spec.inputs, augment_max=self.train_additive_max
            )
            self.data_val = TensorBatches(
                val, self.noise_sigma, fixed_noise_seed=self.seed + 1, sensor=self.sensor, names=self.spec.inputs
            )
            log.info(
                "HDF5DataModule %s: %d train / %d val samples, window %d, sigma %g",
                self.path,
                len(self.data_train),
                len(self.data_val),
                self.window,
                self.noise_sigma,
            )
        if "test" in stages and self.data_test is None:
            test = self._read(self.test_split, self.limit_test, info)
            self.data_test = TensorBatches(
                test, self.noise_sigma, fixed_noise_seed=self.seed + 2, sensor=self.sensor, names=self.spec.inputs
            )
            log.info("HDF5DataModule %s: %d test samples", self.path, len(self.data_test))

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.data_train, True, self.batch_size)

    def stats_batch(self, n: int | None = None) -> dict[str, torch.Tensor]:
        if self._train_tensors is None:
            self.setup("fit")
        n = n or self.stats_samples
        return {k: v[:n] for k, v in self._train_tensors.items()}


class StreamingDataModule(_BaseDataModule):
    """Unlimited fresh training samples; fixed validation (and test) sets simulated once with their own seeds.

    An "epoch" is `samples_per_epoch` streamed samples. The test set is simulated with
    `test_seed` unless `path` names an HDF5 file (then its `test_split` is used, capped at
    `limit_test` samples), so `data.path=FILE` means "test on that file" for both
    datamodules.
    """

    def __init__(
        self,
        prior: Mapping | None = None,
        road_classes: Mapping[str, float] | None = None,
        h: float = 0.01,
        speed_kmh: float = 30.0,
        integrator: str = "semi_explicit_euler",
        physics: str = "euler",
        warmup_s: float | Sequence[float] = 0.0,
        samples_per_epoch: int = 51200,
        val_samples: int = 2000,
        test_samples: int = 2000,
        val_seed: int = 1_000_001,
        test_seed: int = 2_000_002,
        path: str | None = None,
        test_split: str = "test",
        limit_test: int | None = None,
        replay: float = 0.0,
        occupant: str = "rigid",
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if occupant != "rigid" and self.spec.aux:
            # the physics residual a3 = -p1 (v3 - v2) - p2 (q3 - q2) is the rigid occupant's equation
            raise ValueError(
                f"data.occupant = {occupant!r}: the physics-residual loss (aux {list(self.spec.aux)}) assumes a rigid "
                f"occupant, which a seated person is not; train the labelled CNN (experiment=exp1_labelled_persons)"
            )
        # above 0.5 the previous step's fresh part would be smaller than the replayed part
        if not (isinstance(replay, (int, float)) and 0.0 <= float(replay) <= 0.5):
            raise ValueError(f"StreamingDataModule: data.replay must be a number in [0, 0.5], got {replay!r}")
        self.replay = float(replay)
        self.simulator = StreamSimulator(
            prior,
            road_classes,
            self.window,
            h,
            speed_kmh,
            integrator,
            physics=physics,
            warmup_s=warmup_s,
            occupant=occupant,
        )
        if int(samples_per_epoch) < 1 or int(val_samples) < 0 or int(test_samples) < 0:
            raise ValueError(
                f"StreamingDataModule: need samples_per_epoch >= 1 and val/test_samples >= 0, got "
                f"{samples_per_epoch}, {val_samples}, {test_samples}"
            )
        self.samples_per_epoch = int(samples_per_epoch)
        self.val_samples, self.test_samples = int(val_samples), int(test_samples)
        self.val_seed, self.test_seed = int(val_seed), int(test_seed)
        self.path, self.test_split = (str(path) if path else None), test_split
        self.limit_test = None if limit_test is None else int(limit_test)
        if self.seed in (self.val_seed, self.test_seed):
            raise ValueError(f"StreamingDataModule: seed {self.seed} must differ from val_seed/test_seed")
        self._val_tensors: dict[str, torch.Tensor] | None = None
        self._stats_tensors: dict[str, torch.Tensor] | None = None

    def check(self, stages: Sequence[str] = ("fit", "test")) -> dict | None:
        """Validate the test file (if any) against channels, window and the simulator's step size."""
        if not self.path or "test" not in stages:
            return None
        hdf5 = self._hdf5_test()
        info = hdf5.check(("test",))
        h = info["attrs"].get("h")
        if h is not None and abs(float(h) - self.simulator.h) > 1e-12:
            raise DatasetError(
                f"{self.path}: attribute h = {h} differs from the stream's h = {self.simulator.h}; "
                f"set data.h={h} so training and test data share the time step"
            )
        return info

    def _hdf5_test(self) -> HDF5DataModule:
        return HDF5DataModule(
            self.path,
            test_split=self.test_split,
            inputs=self.spec.inputs,
            targets=self.spec.targets,
            aux=self.spec.aux,
            window=self.window,
            noise_sigma=self.noise_sigma,
            seed=self.seed,
            sensor=self.sensor,
            limit_test=self.limit_test,
            targets_optional=self.spec.targets_optional,
        )

    def _fixed_set(self, n: int, seed: int, chunk: int = 1000) -> dict[str, torch.Tensor]:
        generator = torch.Generator().manual_seed(seed)
        parts = []
        for start in range(0, n, chunk):
            arrays = self.simulator(min(chunk, n - start), generator)
            parts.append(self.spec.build(arrays, torch.arange(start, start + arrays["accel"].shape[0])))
        if not parts:
            arrays = self.simulator(1, generator)
            return {k: v[:0] for k, v in self.spec.build(arrays, torch.arange(1)).items()}
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}

    def setup(self, stage: str | None = None) -> None:
        stages = ("fit", "test") if stage is None else ("fit",) if stage in ("fit", "validate") else ("test",)
        if "fit" in stages and self.data_train is None:
            self._val_tensors = self._fixed_set(self.val_samples, self.val_seed)
            self.stats = channel_stats(self.stats_batch())
            self.data_val = TensorBatches(
                self._val_tensors,
                self.noise_sigma,
                fixed_noise_seed=self.val_seed + 1,
                sensor=self.sensor,
                names=self.spec.inputs,
            )
            self.data_train = SimulatedStream(
                self.simulator,
                self.spec,
                self.batch_size,
                max(1, self.samples_per_epoch // self.batch_size),
                self.noise_sigma,
                self.seed,
                sensor=self.sensor,
                augment_max=self.train_additive_max,
                replay=self.replay,
            )
        if "test" in stages and self.data_test is None:
            if self.path:
                self.check(("test",))
                hdf5 = self._hdf5_test()
                hdf5.setup("test")
                self.data_test = hdf5.data_test
            else:
                self.data_test = TensorBatches(
                    self._fixed_set(self.test_samples, self.test_seed),
                    self.noise_sigma,
                    fixed_noise_seed=self.test_seed + 1,
                    sensor=self.sensor,
                    names=self.spec.inputs,
                )

    def train_dataloader(self) -> DataLoader:
        if self.data_train is None:
            raise RuntimeError("StreamingDataModule: call setup('fit') first")
        # The stream yields whole batches; batch_size=None turns off re-batching.
        return DataLoader(self.data_train, batch_size=None, num_workers=self.num_workers, pin_memory=self.pin_memory)

    def stats_batch(self, n: int | None = None) -> dict[str, torch.Tensor]:
        n = n or self.stats_samples
        # Training statistics = the prior's; a seeded draw distinct from val/test/stream seeds.
        if self._stats_tensors is None or self._stats_tensors["x"].shape[0] < n:
            self._stats_tensors = self._fixed_set(n, self.seed + 7919)
        return {k: v[:n] for k, v in self._stats_tensors.items()}


__all__ = ["HDF5DataModule", "StreamingDataModule"]
