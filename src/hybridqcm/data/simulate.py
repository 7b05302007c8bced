"""Sample generation: draw parameters and roads, integrate, and stream datasets to HDF5.

One road profile is shared by `samples_per_profile` parameter draws (the reference protocol:
340 train / 170 test profiles x 100 draws). Generation runs in chunks of whole profiles and
each chunk is written before the next is simulated, so memory stays bounded by the chunk.
"""

from __future__ import annotations

import getpass
import json
import math
import platform
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from hybridqcm import __version__
from hybridqcm.data.dataset_writer import DatasetWriter
from hybridqcm.physics.continuous import simulate_continuous, time_basis
from hybridqcm.physics.integrators import METHODS, simulate
from hybridqcm.physics.occupant import N_MODES
from hybridqcm.physics.prior import _RejectionPrior
from hybridqcm.physics.road import ROAD_CLASSES, RoadProfile, road_class_index
from hybridqcm.physics.seated import check_occupant, draw_body, is_stable_seated

# redraws of a seated person's body parameters whose coupled system (with the vehicle's p) is not
# stable, before giving up
BODY_REDRAWS = 100

PHYSICS = ("continuous", "euler")
# seconds driven before a window when none is given: mid-drive for continuous data, the source's
# "from rest" for the Euler protocol
DEFAULT_WARMUP_S = {"continuous": (2.0, 20.0), "euler": (0.0, 0.0)}


def check_warmup(warmup_s, where: str = "window.warmup_s") -> tuple[float, float]:
    """(low, high) seconds from a number or a [low, high] pair; one-line ValueError otherwise."""
    values = [warmup_s] if isinstance(warmup_s, (int, float)) else list(warmup_s)
    if len(values) == 1:
        values = values * 2
    try:
        low, high = (float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be seconds or a [low, high] range, got {warmup_s!r}") from None
    if len(values) != 2 or not (math.isfinite(low) and math.isfinite(high)) or low < 0 or high < low:
        raise ValueError(f"{where} must be a range 0 <= low <= high (seconds), got {warmup_s!r}")
    return low, high


def check_physics(physics: str) -> str:
    if physics not in PHYSICS:
        raise ValueError(f"physics = {physics!r} is not known; choose one of {list(PHYSICS)}")
    return physics


def check_occupant_physics(occupant: str, physics: str) -> str:
    """The occupant model, valid for `physics`; one-line ValueError otherwise."""
    check_occupant(occupant)
    if occupant != "rigid" and physics != "continuous":
        raise ValueError(
            f"occupant = {occupant!r} needs physics=continuous (physics={physics} keeps the source's rigid occupant)"
        )
    return occupant


def body_generator(seed: int, split_index: int) -> torch.Generator:
    """The generator of a split's body parameters: its own stream, so the vehicle's draws (roads, p,
    warm-ups) of a seed are the same whatever the occupant."""
    return torch.Generator().manual_seed((int(seed) * 1000 + split_index) ^ 0x5EA7ED0CC0FFEE)


def _draw_stable_body(occupant: str, params: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Body parameters [M, 3 n_modes] for vehicles `params` [M, 10]; draws whose coupled system is
    not stable are drawn again (at most BODY_REDRAWS times)."""
    body = draw_body(occupant, params.shape[0], generator)
    for _ in range(BODY_REDRAWS):
        bad = ~is_stable_seated(params, body)
        if not bad.any():
            return body
        body[bad] = draw_body(occupant, int(bad.sum()), generator)
    raise ValueError(
        f"occupant={occupant}: {int(bad.sum())} vehicle(s) stay unstable with every drawn body after {BODY_REDRAWS} tries"
    )


def _warmups(n: int, warmup_s: tuple[float, float], generator: torch.Generator) -> torch.Tensor:
    low, high = warmup_s
    return low + (high - low) * torch.rand(n, generator=generator, dtype=torch.float64)


def _euler_mid_drive(
    params: torch.Tensor,
    amplitude: torch.Tensor,
    phase: torch.Tensor,
    road_profile: RoadProfile,
    steps_before: torch.Tensor,
    n_steps: int,
    h: float,
    speed_mps: float,
    method: str,
) -> dict:
    """Euler recursion from rest `steps_before[i]` steps before the window. All samples share one grid
    of max(steps_before) + n_steps steps; sample i's drive starts at index max - steps_before[i] and its
    forcing is zero before that, so its state stays exactly at rest until then."""
    lead = int(steps_before.max())
    total = lead + n_steps
    start = lead - steps_before  # [b]
    shift = (start.to(torch.float64) * h * speed_mps)[:, None]  # distance offset
    # u at index j is the road at time (j - start) h: the phases absorb the start offset
    road_full = road_profile.evaluate(
        amplitude, phase + road_profile.omega[None, :] * shift, road_profile._distance(total, h, speed_mps)
    )
    road_full = road_full * (torch.arange(total)[None, :] >= start[:, None])
    trajectory = simulate(params, road_full, h, method)
    window = slice(lead, total)
    vel, disp = trajectory.vel[:, window], trajectory.disp[:, window]
    return {
        "accel": trajectory.accel[:, window],
        "vel": vel,
        "disp": disp,
        "road": road_full[:, window],
        "state0": torch.cat([vel[:, 0], disp[:, 0]], -1),
    }


def simulate_samples(
    prior: _RejectionPrior,
    road_profile: RoadProfile,
    road_class: torch.Tensor,
    n_steps: int,
    h: float,
    speed_mps: float,
    generator: torch.Generator,
    samples_per_profile: int = 1,
    method: str = "semi_explicit_euler",
    physics: str = "euler",
    warmup_s: tuple[float, float] = (0.0, 0.0),
    basis: torch.Tensor | None = None,
    occupant: str = "rigid",
    body_rng: torch.Generator | None = None,
) -> dict[str, torch.Tensor | int]:
    """Simulate `len(road_class) * samples_per_profile` samples.

    road_class: LongTensor [profiles]. Returns float64 tensors accel/vel/disp [M, n_steps, 3],
    road [M, n_steps], params [M, 10], state0 [M, 6] (v3 v2 v1 q3 q2 q1 at the window start),
    warmup [M] seconds, road_class [M], profile [M] (0-based within this call) and `n_drawn`,
    the prior's candidate count (for its acceptance rate).

    physics = "euler": the recursion `method` at step h; "continuous": the exact response
    (physics.continuous; `method` unused). Each sample drives U(warmup_s) seconds on its road
    from rest before the window (euler: rounded to whole steps). Random draws come in the
    order roads, parameters, warm-ups, so euler data with warm-up 0 are those of earlier versions.

    occupant: "rigid" (m3 one rigid mass, as always) or "body1"/"body2" (continuous physics only): a
    seated person (physics/seated.py) with body parameters drawn per sample from `body_rng` (a stream
    of its own, so p, roads and warm-ups are those of the rigid occupant), returned as
    `occupant_params` [M, 3 n_modes] (r_i, k_i, c_i); params keep p1 = C3/M, p2 = K3/M.
    """
    check_physics(physics)
    check_occupant_physics(occupant, physics)
    road_class = torch.as_tensor(road_class, dtype=torch.long).reshape(-1)
    n_profiles = road_class.shape[0]
    profile = torch.arange(n_profiles).repeat_interleave(samples_per_profile)
    mid_drive = warmup_s[1] > 0
    if physics == "euler" and not mid_drive:
        roads = road_profile.sample(road_class, n_steps, h, speed_mps, generator)  # [profiles, n_steps]
        draw = prior.sample(n_profiles * samples_per_profile, generator)
        road = roads[profile]
        trajectory = simulate(draw.params, road, h, method)
        out = {
            "accel": trajectory.accel,
            "vel": trajectory.vel,
            "disp": trajectory.disp,
            "road": road,
            "state0": torch.zeros(road.shape[0], 6, dtype=torch.float64),
            "warmup": torch.zeros(road.shape[0], dtype=torch.float64),
        }
    else:
        amplitude, phase = road_profile.draw(road_class, generator)
        draw = prior.sample(n_profiles * samples_per_profile, generator)
        warmup = (
            _warmups(profile.shape[0], warmup_s, generator)
            if mid_drive
            else torch.zeros(profile.shape[0], dtype=torch.float64)
        )
        if physics == "euler":
            steps_before = torch.round(warmup / h).long()
            out = _euler_mid_drive(
                draw.params,
                amplitude[profile],
                phase[profile],
                road_profile,
                steps_before,
                n_steps,
                h,
                speed_mps,
                method,
            )
            warmup = steps_before.to(torch.float64) * h
        else:
            body = None
            if occupant != "rigid":
                body = _draw_stable_body(occupant, draw.params, body_rng or torch.Generator().manual_seed(0))
            response = simulate_continuous(
                draw.params,
                amplitude[profile],
                phase[profile],
                road_profile.omega * speed_mps,
                n_steps,
                h,
                warmup,
                basis=basis,
                body=body,
            )
            out = {
                "accel": response.accel,
                "vel": response.vel,
                "disp": response.disp,
                "road": response.road,
                "state0": response.state0,
            }
            if body is not None:
                out["occupant_params"] = body
        out["warmup"] = warmup
    if getattr(draw, "occupant", None) is not None:  # a seat law's prior (physics/seat_law.py)
        out["occupant_mass"] = draw.occupant
    return {
        **out,
        "params": draw.params,
        "road_class": road_class[profile],
        "profile": profile,
        "n_drawn": draw.n_drawn,
    }


@dataclass
class SplitSummary:
    """What a written split holds, for the console and the file's attributes."""

    n_samples: int = 0
    n_drawn: int = 0
    per_class: dict = field(default_factory=dict)
    param_min: np.ndarray | None = None
    param_max: np.ndarray | None = None
    peak_accel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    seconds: float = 0.0

    def update(self, batch: Mapping) -> None:
        params = batch["params"].numpy()
        self.n_samples += params.shape[0]
        self.n_drawn += int(batch["n_drawn"])
        for c in batch["road_class"].unique().tolist():
            name = ROAD_CLASSES[c]
            self.per_class[name] = self.per_class.get(name, 0) + int((batch["road_class"] == c).sum())
        low, high = params.min(0), params.max(0)
        self.param_min = low if self.param_min is None else np.minimum(self.param_min, low)
        self.param_max = high if self.param_max is None else np.maximum(self.param_max, high)
        self.peak_accel = np.maximum(self.peak_accel, batch["accel"].abs().amax((0, 1)).numpy())

    @property
    def acceptance_rate(self) -> float:
        return self.n_samples / max(self.n_drawn, 1)

    def as_dict(self) -> dict:
        return {
            "n_samples": self.n_samples,
            "per_class": self.per_class,
            "prior_acceptance_rate": round(self.acceptance_rate, 5),
            "param_min": [float(x) for x in (self.param_min if self.param_min is not None else [])],
            "param_max": [float(x) for x in (self.param_max if self.param_max is not None else [])],
            "peak_accel_a3_a2_a1": [float(x) for x in self.peak_accel],
            "seconds": round(self.seconds, 2),
        }


def _class_list(profiles: Mapping[str, int], split: str) -> list[int]:
    classes: list[int] = []
    for name, count in profiles.items():
        try:
            index = road_class_index(name)
        except ValueError as error:
            raise ValueError(f"splits.{split}.profiles: {error}") from None
        if not isinstance(count, int) or count < 0:
            raise ValueError(f"splits.{split}.profiles.{name} must be a non-negative integer, got {count!r}")
        classes += [index] * count
    return classes


def _user() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no login name (some containers)
        return "unknown"


def _check_settings(n_steps, h, speed_mps, samples_per_profile, profiles_per_chunk, method, physics, occupant):
    if n_steps < 1 or samples_per_profile < 1 or h <= 0 or speed_mps <= 0:
        raise ValueError(
            f"need n_steps >= 1, samples_per_profile >= 1, h > 0, speed > 0; got "
            f"{n_steps}, {samples_per_profile}, {h}, {speed_mps}"
        )
    if profiles_per_chunk < 1:
        raise ValueError(f"profiles_per_chunk must be >= 1, got {profiles_per_chunk}")
    if method not in METHODS:
        raise ValueError(f"unknown integrator {method!r}; choose one of {METHODS}")
    check_physics(physics)
    check_occupant_physics(occupant, physics)


def _samples_progress(progress: bool):
    """A rich progress bar counting samples (nothing when disabled)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("samples"),
        TimeRemainingColumn(),
    )
    return Progress(*columns, disable=not progress, transient=False)


def seat_truth_keys(prior) -> tuple[str, ...]:
    """The keys a seat law's prior adds to a split: truth_occupant_mass [M] kg (the occupant alone) and, for
    calibration drives with known loads, known_mass [M] kg (the same values: the load on the empty seat)."""
    if not hasattr(prior, "seat"):
        return ()
    return ("truth_occupant_mass",) + (("known_mass",) if prior.known_loads is not None else ())


def _write_split(writer, split: str, split_index: int, classes: list[int], run: Mapping, advance) -> SplitSummary:
    """Simulate one split chunk by chunk into ``writer``; ``run``: write_dataset's settings (and basis, n_body)."""
    seed, samples_per_profile, n_body = run["seed"], run["samples_per_profile"], run["n_body"]
    generator = torch.Generator().manual_seed(int(seed) * 1000 + split_index)
    n_samples = len(classes) * samples_per_profile
    extra = {"occupant_params": (np.dtype("float64"), (n_body,))} if n_body else {}
    seat_keys = seat_truth_keys(run["prior"])  # a seat law's truth (physics/seat_law.py): {} for the reference seat
    extra.update({key: (np.dtype("float64"), ()) for key in seat_keys})
    writer.create_split(split, n_samples, run["n_steps"], extra=extra or None)
    writer.set_split_attr(split, "occupant", run["occupant"])
    body_rng = body_generator(seed, split_index)
    if seat_keys:
        run["prior"].reset()  # each split's known loads cycle from the first
    summary = SplitSummary()
    start_time = time.perf_counter()
    # Shuffle the class order so a prefix of the split is a fair mix of classes.
    order = torch.randperm(len(classes), generator=generator)
    classes_tensor = torch.tensor(classes, dtype=torch.long)[order] if classes else torch.zeros(0, dtype=torch.long)
    for first in range(0, len(classes), run["profiles_per_chunk"]):
        chunk = classes_tensor[first : first + run["profiles_per_chunk"]]
        batch = simulate_samples(
            run["prior"],
            run["road_profile"],
            chunk,
            run["n_steps"],
            run["h"],
            run["speed_mps"],
            generator,
            samples_per_profile,
            run["method"],
            run["physics"],
            run["warmup_s"],
            run["basis"],
            run["occupant"],
            body_rng,
        )
        row = first * samples_per_profile
        if not all(torch.isfinite(batch[k]).all() for k in ("accel", "vel", "disp")):
            raise FloatingPointError(f"split {split}: non-finite simulation output in profiles {first}..")
        writer.write(
            split,
            row,
            accel=batch["accel"].float().numpy(),
            vel=batch["vel"].float().numpy(),
            disp=batch["disp"].float().numpy(),
            road=batch["road"].float().numpy(),
            params=batch["params"].numpy(),
            state0=batch["state0"].numpy(),
            road_class=batch["road_class"].numpy().astype(np.int8),
            profile_id=(batch["profile"] + first).numpy().astype(np.int32),
            **({"occupant_params": batch["occupant_params"].numpy()} if n_body else {}),
            **{key: batch["occupant_mass"].numpy() for key in seat_keys},
        )
        summary.update(batch)
        advance(batch["params"].shape[0])
    summary.seconds = time.perf_counter() - start_time
    return summary


def write_dataset(
    output: str | Path,
    splits: Mapping[str, Mapping],
    prior: _RejectionPrior,
    road_profile: RoadProfile,
    n_steps: int,
    h: float,
    speed_mps: float,
    samples_per_profile: int,
    seed: int,
    overwrite: bool = False,
    profiles_per_chunk: int = 10,
    method: str = "semi_explicit_euler",
    attrs: Mapping | None = None,
    progress: bool = True,
    compression: str | None = "gzip",
    physics: str = "euler",
    warmup_s=(0.0, 0.0),
    occupant: str = "rigid",
) -> dict[str, SplitSummary]:
    """Simulate every split and stream it into `output` (atomically). Returns a summary per split.

    physics: "euler" (the recursion `method`, the source protocol) or "continuous" (exact
    response); warmup_s: [low, high] seconds driven before each window (0 = from rest).
    occupant: "rigid" | "body1" | "body2" (simulate_samples); a seated person's body parameters go
    to /<split>/occupant_params [M, 3 n_modes], the model's name to the split's attribute `occupant`.

    splits: {split: {"profiles": {"A": 200, ...}}}. The same seed gives identical arrays: each
    split has its own generator seeded from (seed, split position).
    """
    _check_settings(n_steps, h, speed_mps, samples_per_profile, profiles_per_chunk, method, physics, occupant)
    n_body = 3 * N_MODES[occupant]
    warmup_s = check_warmup(warmup_s)
    prior_h = getattr(prior, "h", None)
    if physics == "euler" and prior_h is not None and abs(float(prior_h) - float(h)) > 1e-12 * float(h):
        # the prior rejects draws that are unstable under the Euler map of *its* h
        raise ValueError(f"the prior checks stability at h = {prior_h} but the data are simulated at h = {h}")
    plan = {split: _class_list(spec.get("profiles", {}), split) for split, spec in splits.items()}
    total = sum(len(c) * samples_per_profile for c in plan.values())
    if total == 0:
        raise ValueError("nothing to simulate: every split has zero profiles")
    file_attrs = {
        "h": float(h),
        "n_steps": int(n_steps),
        "speed_mps": float(speed_mps),
        "prior": getattr(prior, "name", "custom"),
        "seed": int(seed),
        "samples_per_profile": int(samples_per_profile),
        "integrator": method if physics == "euler" else "exact",
        "physics": physics,
        "warmup_s": np.array(warmup_s, dtype=np.float64),
        "created_by": f"hybridqcm {__version__} qcm-simulate ({_user()}@{platform.node()})",
        **dict(attrs or {}),
    }
    basis = time_basis(road_profile.omega * speed_mps, n_steps, h) if physics == "continuous" else None
    run = dict(
        prior=prior,
        road_profile=road_profile,
        n_steps=n_steps,
        h=h,
        speed_mps=speed_mps,
        samples_per_profile=samples_per_profile,
        seed=seed,
        profiles_per_chunk=profiles_per_chunk,
        method=method,
        physics=physics,
        warmup_s=warmup_s,
        basis=basis,
        occupant=occupant,
        n_body=n_body,
    )
    summaries: dict[str, SplitSummary] = {}
    with (
        DatasetWriter(output, attrs=file_attrs, overwrite=overwrite, compression=compression) as writer,
        _samples_progress(progress) as bar,
    ):
        task = bar.add_task(f"simulating {Path(output).name}", total=total)
        for split_index, (split, classes) in enumerate(plan.items()):
            summaries[split] = _write_split(writer, split, split_index, classes, run, lambda n: bar.advance(task, n))
        writer.set_attr("summary", json.dumps({s: v.as_dict() for s, v in summaries.items()}))
    return summaries


def kmh_to_mps(speed_kmh: float) -> float:
    return float(speed_kmh) / 3.6


__all__ = [
    "simulate_samples",
    "write_dataset",
    "SplitSummary",
    "kmh_to_mps",
    "check_warmup",
    "check_physics",
    "check_occupant_physics",
    "PHYSICS",
    "DEFAULT_WARMUP_S",
]
