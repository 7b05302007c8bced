"""Endless fresh training samples: the quarter car simulated a batch at a time (StreamingDataModule's source).

StreamSimulator(n, generator) -> arrays of n fresh samples (the prior, roads, occupants, physics)
SimulatedStream                -> batches [B, C, N] of those, seeded per (rank, worker, pass)
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from hybridqcm.data.batches import ChannelSpec, apply_noise
from hybridqcm.data.sensor import SensorModel, additive_augmentation, apply_to_channels
from hybridqcm.physics.occupant import OCCUPANT_MODELS

KMH = 1 / 3.6


class SimulatedStream(IterableDataset):
    """Endless fresh samples, simulated a batch at a time.

    Every (rank, worker, pass) has its own seed, so workers and distributed ranks never repeat
    each other's samples: seed = SeedSequence(seed, rank, worker, pass). `pass` is the
    DataLoader's per-iterator base seed inside workers (it changes every epoch) or a counter of
    iterations when there are no workers. One pass yields `batches_per_epoch` batches in total,
    split across ranks and workers.

    `replay` = r in [0, 0.5]: each batch is (1 - r) fresh samples plus r of the previous batch's fresh
    samples with new sensor and augmentation noise, so every clean sample is used in two consecutive
    steps and the simulator runs on (1 - r) of a batch per step (at r = 0.5, half). The first batch
    of a pass is all fresh.
    """

    def __init__(
        self,
        simulator: StreamSimulator,
        spec: ChannelSpec,
        batch_size: int,
        batches_per_epoch: int,
        noise_sigma: float,
        seed: int,
        sensor: SensorModel | None = None,
        augment_max: float = 0.0,
        replay: float = 0.0,
    ) -> None:
        if not 0.0 <= float(replay) <= 0.5:
            raise ValueError(f"data.replay must be in [0, 0.5], got {replay}")
        self.replay = float(replay)
        self.simulator, self.spec = simulator, spec
        self.sensor = sensor if sensor is not None and sensor.active else None
        self.augment_max = float(augment_max)
        self.batch_size, self.batches_per_epoch = int(batch_size), int(batches_per_epoch)
        self.noise_sigma, self.seed = float(noise_sigma), int(seed)
        self._passes = 0

    @staticmethod
    def _rank() -> tuple[int, int]:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            return torch.distributed.get_rank(), torch.distributed.get_world_size()
        return 0, 1

    def stream_seed(self) -> tuple[int, int, int]:
        """(seed for this worker's generator, number of shards, shard index)."""
        rank, world = self._rank()
        info = get_worker_info()
        if info is None:
            worker, n_workers, salt = 0, 1, self._passes
            self._passes += 1
        else:
            worker, n_workers, salt = info.id, info.num_workers, (info.seed - info.id) % (2**62)
        sequence = np.random.SeedSequence([self.seed, rank, worker, salt])
        return int(sequence.generate_state(1, np.uint64)[0] % (2**63 - 1)), world * n_workers, rank * n_workers + worker

    def __len__(self) -> int:
        return self.batches_per_epoch

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        seed, shards, shard = self.stream_seed()
        generator = torch.Generator().manual_seed(seed)
        n_batches = len(range(shard, self.batches_per_epoch, shards))
        n_replay = min(int(round(self.replay * self.batch_size)), self.batch_size // 2)
        previous: dict[str, torch.Tensor] | None = None
        for _ in range(n_batches):
            if previous is None or n_replay == 0:
                fresh = self.spec.build(
                    self.simulator(self.batch_size, generator), torch.full((self.batch_size,), -1, dtype=torch.long)
                )
                batch = fresh
            else:
                n_fresh = self.batch_size - n_replay
                fresh = self.spec.build(
                    self.simulator(n_fresh, generator), torch.full((n_fresh,), -1, dtype=torch.long)
                )
                # the replayed part: the previous step's fresh samples, clean (noise is added below)
                pick = torch.randperm(previous["x"].shape[0], generator=generator)[:n_replay]
                batch = {k: torch.cat([fresh[k], previous[k][pick]]) for k in fresh}
            previous = fresh
            batch = dict(batch)
            batch["x"] = apply_noise(batch["x"], self.noise_sigma, generator)
            if self.sensor is not None:  # fresh, seeded noise: random sample ids from the stream's generator
                ids = torch.randint(0, 2**62, (self.batch_size,), generator=generator)
                batch["x"] = apply_to_channels(self.sensor, batch["x"], self.spec.inputs, ids, salt=self.seed)
            if self.augment_max > 0:
                batch["x"] = additive_augmentation(batch["x"], self.spec.inputs, self.augment_max, generator)
            yield batch


# data.occupant: one occupant model for every sample, or "mixed": rigid, body1, body2 drawn per sample
STREAM_OCCUPANTS = ("rigid", "body1", "body2", "mixed")


class StreamSimulator:
    """Callable (n, generator) -> arrays dict of n fresh samples (picklable, for DataLoader workers).

    occupant: "rigid", "body1", "body2" (a seated person, physics/seated.py; continuous physics) or "mixed"
    (each sample's occupant drawn from the three with equal probability, its index in OCCUPANT_MODELS in
    `occupant` [n]; no `occupant_params` then, their widths differ). A person's params keep p1 = C3/M,
    p2 = K3/M with M the static mass."""

    def __init__(
        self,
        prior: Mapping | None = None,
        road_classes: Mapping[str, float] | None = None,
        n_steps: int = 500,
        h: float = 0.01,
        speed_kmh: float = 30.0,
        integrator: str = "semi_explicit_euler",
        n_waves: int = 1000,
        physics: str = "euler",
        warmup_s: float | Sequence[float] = 0.0,
        occupant: str = "rigid",
    ) -> None:
        from hybridqcm.data.simulate import check_occupant_physics, check_physics, check_warmup
        from hybridqcm.physics import RoadProfile, build_prior, road_class_index

        self.physics = check_physics(physics)
        if occupant not in STREAM_OCCUPANTS:
            raise ValueError(f"data.occupant = {occupant!r} is not known; choose one of {list(STREAM_OCCUPANTS)}")
        for name in ("body1",) if occupant == "mixed" else (occupant,):
            check_occupant_physics(name, self.physics)
        self.occupant = occupant
        self.warmup_s = check_warmup(warmup_s, "data.warmup_s")
        if not float(h) > 0:
            raise ValueError(f"data.h must be > 0, got {h}")
        prior = dict(prior or {"name": "thesis"})
        name = prior.pop("name", "thesis")
        if "mass_range" in prior:
            prior["mass_range"] = tuple(prior["mass_range"])
        # continuous physics: only the eigenvalues of A need be stable (no Euler step map)
        self.prior = build_prior(name, h=h if physics == "euler" else None, **prior)
        road_classes = dict(road_classes or {"A": 200, "B": 140, "C": 60})
        weights = [float(w) for w in road_classes.values()]
        if any(w < 0 for w in weights) or sum(weights) <= 0:
            raise ValueError(f"road_classes weights must be >= 0 with a positive sum, got {road_classes}")
        self.class_index = torch.tensor([road_class_index(c) for c in road_classes], dtype=torch.long)
        self.class_weights = torch.tensor(weights, dtype=torch.float64)
        self.road = RoadProfile(n_waves=n_waves)
        self.n_steps, self.h, self.speed_mps, self.integrator = (
            int(n_steps),
            float(h),
            float(speed_kmh) * KMH,
            integrator,
        )
        self._basis: torch.Tensor | None = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_basis": None}  # a worker rebuilds the 8 MB time basis itself

    def basis(self) -> torch.Tensor | None:
        """The continuous simulator's time basis [2 W, n_steps], built once (it is the same for every batch)."""
        if self.physics != "continuous":
            return None
        if self._basis is None:
            from hybridqcm.physics.continuous import time_basis

            self._basis = time_basis(self.road.omega * self.speed_mps, self.n_steps, self.h)
        return self._basis

    def __call__(self, n: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        if self.occupant == "mixed":  # a third of each, drawn per sample; one simulation per occupant model
            kinds = torch.randint(0, 3, (n,), generator=generator)
            parts = [self._simulate(int((kinds == i).sum()), generator, name) for i, name in enumerate(OCCUPANT_MODELS)]
            for i, part in enumerate(parts):
                part["occupant"] = torch.full((part["accel"].shape[0],), i, dtype=torch.long)
            parts = [p for p in parts if p["accel"].shape[0] > 0]
            return {
                k: torch.cat([p[k] for p in parts])
                if isinstance(parts[0][k], torch.Tensor)
                else sum(p[k] for p in parts)
                for k in parts[0]
                if k != "occupant_params"
            }
        return self._simulate(n, generator, self.occupant)

    def _simulate(self, n: int, generator: torch.Generator, occupant: str) -> dict[str, torch.Tensor]:
        from hybridqcm.data.simulate import simulate_samples

        pick = torch.multinomial(self.class_weights, n, replacement=True, generator=generator)
        classes = self.class_index[pick]
        arrays = simulate_samples(
            self.prior,
            self.road,
            classes,
            self.n_steps,
            self.h,
            self.speed_mps,
            generator,
            1,
            self.integrator,
            self.physics,
            self.warmup_s,
            basis=self.basis(),
            occupant=occupant,
            body_rng=generator,
        )
        arrays["profile_id"] = arrays.pop("profile")
        return arrays
