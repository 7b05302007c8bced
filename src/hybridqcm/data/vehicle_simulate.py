"""Half-car and full-car datasets: draw vehicles and two-track roads, integrate exactly, stream to HDF5.

The quarter car's protocol (data/simulate.py) for the larger vehicles, continuous-time physics only:
one two-track road per profile shared by `samples_per_profile` vehicles, each driving U(warmup_s)
seconds from rest before its window (mid-drive), recorded exactly (physics/vehicle_response.py).
Random draws per split generator, in the order roads, vehicles, warm-ups.

Layout of a split (data/hdf5.py reads it; the names attributes make every column explicit):

    /<split>/accel             float32 [M, T, n_dof]    attribute dofs   (z3[_<seat>]..., z2, z1<w>..., pitch[, roll])
    /<split>/vel, disp         float64 [M, T, n_dof]    attribute dofs
    /<split>/road              float64 [M, T, n_wheels] attribute wheels (f, b | fl, fr, bl, br) in metres
    /<split>/road_vel          float64 [M, T, n_wheels] attribute wheels (only where tyres are damped) m/s
    /<split>/physical          float64 [M, P]           attribute names  (physics/vehicle_geometry.py)
    /<split>/state0            float64 [M, 2 n_dof]     attribute names  (v_<dof>..., q_<dof>...) at the window start
    /<split>/road_class int8 [M], profile_id int32 [M]
    file attributes: vehicle (half_car | full_car), layout (JSON: seats, tyre_damping), road_coherence,
    physics = continuous, h, n_steps, speed_mps, warmup_s, prior, seed, created_by

Angles in rad, rates rad/s and rad/s². Every stored (accel, vel, disp, road[, road_vel]) satisfies
M a + C v + K q = F u + G u̇ of the stored `physical` (tests/test_vehicles.py checks it independently).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from hybridqcm.data.dataset_writer import DatasetWriter
from hybridqcm.data.simulate import SplitSummary, _class_list, _samples_progress, _user, _warmups, check_warmup
from hybridqcm.physics.continuous import time_basis
from hybridqcm.physics.two_track_road import TwoTrackRoad
from hybridqcm.physics.vehicle_geometry import VehicleLayout, columns
from hybridqcm.physics.vehicle_model import VehicleModel
from hybridqcm.physics.vehicle_prior import VehiclePrior
from hybridqcm.physics.vehicle_response import linear_response


def simulate_vehicle_samples(
    prior: VehiclePrior,
    road: TwoTrackRoad,
    road_class: torch.Tensor,
    n_steps: int,
    h: float,
    speed_mps: float,
    generator: torch.Generator,
    samples_per_profile: int = 1,
    warmup_s: tuple[float, float] = (2.0, 20.0),
    basis: torch.Tensor | None = None,
) -> dict:
    """`len(road_class) * samples_per_profile` recordings of prior.layout's vehicle (float64 tensors):
    accel/vel/disp [M, T, n_dof], road [M, T, n_wheels] (and road_vel with damped tyres),
    physical [M, P], state0 [M, 2 n_dof], warmup [M], road_class [M], profile [M], n_drawn."""
    layout = prior.layout
    model = VehicleModel(layout)
    road_class = torch.as_tensor(road_class, dtype=torch.long).reshape(-1)
    profile = torch.arange(road_class.shape[0]).repeat_interleave(samples_per_profile)
    draw = road.draw(road_class, generator)[profile]
    vehicles = prior.sample(profile.shape[0], generator)
    physical = vehicles.params
    warmup = _warmups(profile.shape[0], warmup_s, generator)
    values = columns(layout.param_names, physical)
    wheelbase = values["l_f"] + values["l_b"]
    track = values["w_l"] + values["w_r"] if layout.full else torch.zeros_like(wheelbase)
    z = road.wheel_amplitudes(draw, layout.wheels, speed_mps, wheelbase, track)  # [M, n_w, W]
    omega_t = road.omega * float(speed_mps)
    if layout.tyre_damping:
        z = torch.cat([z, 1j * omega_t * z], 1)  # the road's velocities drive the tyre dampers
    A, B, C, E = model.matrices(model.model_params(physical))
    response = linear_response(A, B, z, omega_t, n_steps, h, warmup, basis)
    n = layout.n_dof
    vel, disp = response.states[..., :n], response.states[..., n:]
    accel = response.states @ C.transpose(1, 2) + response.inputs @ E.transpose(1, 2)
    n_w = len(layout.wheels)
    out = {
        "accel": accel,
        "vel": vel.contiguous(),
        "disp": disp.contiguous(),
        "road": response.inputs[..., :n_w].contiguous(),
        "physical": physical,
        "state0": response.state0,
        "warmup": warmup,
        "road_class": road_class[profile],
        "profile": profile,
        "n_drawn": vehicles.n_drawn,
    }
    if layout.tyre_damping:
        out["road_vel"] = response.inputs[..., n_w:].contiguous()
    return out


def _stored_arrays(layout: VehicleLayout, model: VehicleModel, n_steps: int) -> tuple[dict, dict]:
    """The split's extra keys {key: (dtype, trailing shape)} and the names of each one's last axis."""
    n, n_w, P = layout.n_dof, len(layout.wheels), len(layout.param_names)
    # accel as the quarter car's (float32: a logger's resolution); vel, disp and the road in float64: the
    # tyre's deflection z1 - u is a small difference of large numbers (long road waves lift wheel and road
    # by decimetres), and float32 would leave ~1e-5 of the wheel's acceleration in its equation of motion
    extra = {
        "accel": (np.dtype("float32"), (n_steps, n)),
        "vel": (np.dtype("float64"), (n_steps, n)),
        "disp": (np.dtype("float64"), (n_steps, n)),
        "road": (np.dtype("float64"), (n_steps, n_w)),
        "physical": (np.dtype("float64"), (P,)),
        "state0": (np.dtype("float64"), (2 * n,)),
    }
    if layout.tyre_damping:
        extra["road_vel"] = (np.dtype("float64"), (n_steps, n_w))
    column_names = {
        **{key: list(layout.dofs) for key in ("accel", "vel", "disp")},
        "road": list(layout.wheels),
        "road_vel": list(layout.wheels),
        "physical": list(layout.param_names),
        "state0": list(model.state_names),
    }
    return extra, column_names


def _write_vehicle_split(writer, split: str, split_index: int, classes: list[int], run: Mapping, advance):
    """Simulate one split chunk by chunk into ``writer``; ``run``: write_vehicle_dataset's settings."""
    layout, extra, samples_per_profile = run["prior"].layout, run["extra"], run["samples_per_profile"]
    generator = torch.Generator().manual_seed(int(run["seed"]) * 1000 + split_index)
    writer.create_split(split, len(classes) * samples_per_profile, run["n_steps"], ("road_class", "profile_id"), extra)
    for key in extra:
        writer.set_dataset_attr(
            split, key, "dofs" if key in ("accel", "vel", "disp") else _attr_name(key), run["column_names"][key]
        )
    summary = SplitSummary(peak_accel=np.zeros(layout.n_dof))
    start_time = time.perf_counter()
    order = torch.randperm(len(classes), generator=generator)
    classes_tensor = torch.tensor(classes, dtype=torch.long)[order]
    for first in range(0, len(classes), run["profiles_per_chunk"]):
        batch = simulate_vehicle_samples(
            run["prior"],
            run["road"],
            classes_tensor[first : first + run["profiles_per_chunk"]],
            run["n_steps"],
            run["h"],
            run["speed_mps"],
            generator,
            samples_per_profile,
            run["warmup_s"],
            run["basis"],
        )
        if not all(torch.isfinite(batch[k]).all() for k in ("accel", "vel", "disp", "road")):
            raise FloatingPointError(f"split {split}: non-finite simulation output in profiles {first}..")
        arrays = {key: batch[key].numpy().astype(extra[key][0]) for key in ("accel", "vel", "disp", "road")}
        if layout.tyre_damping:
            arrays["road_vel"] = batch["road_vel"].numpy()
        writer.write(
            split,
            first * samples_per_profile,
            physical=batch["physical"].numpy(),
            state0=batch["state0"].numpy(),
            road_class=batch["road_class"].numpy().astype(np.int8),
            profile_id=(batch["profile"] + first).numpy().astype(np.int32),
            **arrays,
        )
        summary.update({**batch, "params": batch["physical"]})
        advance(batch["physical"].shape[0])
    summary.seconds = time.perf_counter() - start_time
    return summary


def write_vehicle_dataset(
    output: str | Path,
    splits: Mapping[str, Mapping],
    prior: VehiclePrior,
    road: TwoTrackRoad,
    n_steps: int,
    h: float,
    speed_mps: float,
    samples_per_profile: int,
    seed: int,
    overwrite: bool = False,
    profiles_per_chunk: int = 10,
    progress: bool = True,
    compression: str | None = "gzip",
    warmup_s=(2.0, 20.0),
    attrs: Mapping | None = None,
) -> dict[str, SplitSummary]:
    """Simulate every split of prior.layout's vehicle and stream it into `output` (atomically, module
    docstring for the layout). splits: {split: {"profiles": {"A": n, ...}}}; the same seed gives the
    same arrays. Returns a summary per split (SplitSummary over the physical parameters)."""
    from hybridqcm import __version__

    layout: VehicleLayout = prior.layout
    if n_steps < 1 or samples_per_profile < 1 or h <= 0 or speed_mps <= 0 or profiles_per_chunk < 1:
        raise ValueError(
            f"need n_steps, samples_per_profile, profiles_per_chunk >= 1, h > 0, speed > 0; got "
            f"{n_steps}, {samples_per_profile}, {profiles_per_chunk}, {h}, {speed_mps}"
        )
    warmup_s = check_warmup(warmup_s)
    plan = {split: _class_list(spec.get("profiles", {}), split) for split, spec in splits.items()}
    total = sum(len(c) * samples_per_profile for c in plan.values())
    if total == 0:
        raise ValueError("nothing to simulate: every split has zero profiles")
    import platform

    file_attrs = {
        "h": float(h),
        "n_steps": int(n_steps),
        "speed_mps": float(speed_mps),
        "prior": prior.name,
        "seed": int(seed),
        "samples_per_profile": int(samples_per_profile),
        "integrator": "exact",
        "physics": "continuous",
        "warmup_s": np.array(warmup_s, dtype=np.float64),
        "vehicle": layout.kind,
        "layout": json.dumps(layout.describe()),
        "road_coherence": road.coherence_model,
        "created_by": f"hybridqcm {__version__} qcm-simulate ({_user()}@{platform.node()})",
        **dict(attrs or {}),
    }
    extra, column_names = _stored_arrays(layout, VehicleModel(layout), n_steps)
    run = dict(
        prior=prior,
        road=road,
        n_steps=n_steps,
        h=h,
        speed_mps=speed_mps,
        samples_per_profile=samples_per_profile,
        seed=seed,
        profiles_per_chunk=profiles_per_chunk,
        warmup_s=warmup_s,
        basis=time_basis(road.omega * speed_mps, n_steps, h),
        extra=extra,
        column_names=column_names,
    )
    summaries: dict[str, SplitSummary] = {}
    with (
        DatasetWriter(output, attrs=file_attrs, overwrite=overwrite, compression=compression) as writer,
        _samples_progress(progress) as bar,
    ):
        task = bar.add_task(f"simulating {Path(output).name} ({layout.kind})", total=total)
        for split_index, (split, classes) in enumerate(plan.items()):
            summaries[split] = _write_vehicle_split(
                writer, split, split_index, classes, run, lambda n: bar.advance(task, n)
            )
        writer.set_attr("summary", json.dumps({s: v.as_dict() for s, v in summaries.items()}))
    return summaries


def _attr_name(key: str) -> str:
    """The attribute naming a stored array's last axis: wheels (road, road_vel) or names (the rest)."""
    return "wheels" if key in ("road", "road_vel") else "names"


__all__ = ["simulate_vehicle_samples", "write_vehicle_dataset"]
