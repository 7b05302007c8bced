"""Reading half-car and full-car files: their layout checked, and one seat seen as a quarter car's seat.

A vehicle file (data/vehicle_simulate.py) says what it holds: the file attribute ``vehicle``
(half_car | full_car; absent: the quarter car), ``layout`` (JSON: seats, tyre damping), and per
array the names of its columns (``dofs`` of accel/vel/disp, ``wheels`` of road/road_vel, ``names``
of physical). :func:`vehicle_layout` rebuilds the layout and checks that every array's names are
the layout's, in one line naming the file, key and value otherwise.

The seat view (:func:`read_seat_split`): the road-free occupant estimate and the CNN need, per seat,
what a seat-pad and a seat-base accelerometer record — the seat's z3 and the seat base's
z2 + x_s α + y_s β (physics/vehicle_geometry.seat_base, composed here from the stored chassis
motion and the seat's stored position, at every sample: exact, since the stored motion is). It is
returned in the quarter car's layout, so the quarter car's pipelines read it unchanged:

    accel, vel, disp [M, T, 3]  (a3, a2, a1) = (the seat, its base, NaN: no wheel under a seat)
    params [M, 10]              (p1, p2) = (c3/m3, k3/m3) of the seat, p3..p10 NaN (not a quarter car)
    road_class, profile_id      as stored

The seat's k3 is kept beside it (``k3`` [M]) for the occupant mass m3 = k3 / p2.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import torch

from hybridqcm.data.hdf5 import column_names, dataset_info, read_split
from hybridqcm.errors import DatasetError
from hybridqcm.physics.vehicle_geometry import VEHICLES, VehicleLayout, physical_problems, seat_base

QUARTER_CAR = "quarter_car"
SEAT_KEYS = ("accel", "vel", "disp", "params", "road_class", "profile_id")


def vehicle_of(info: Mapping) -> str:
    """The vehicle a file holds (dataset_info's attrs): half_car, full_car or quarter_car (no attribute)."""
    return str(info["attrs"].get("vehicle", QUARTER_CAR))


def vehicle_layout(path: str | os.PathLike, split: str | None = None, info: Mapping | None = None) -> VehicleLayout:
    """The layout of a half-car / full-car file, checked against the names stored with its arrays
    (of ``split``, or of every split); DatasetError (one line) for a quarter-car file, an unknown
    vehicle, an unreadable layout or names that are not the layout's."""
    import h5py

    path = Path(path)
    info = dataset_info(path) if info is None else info
    kind = vehicle_of(info)
    if kind == QUARTER_CAR:
        raise DatasetError(f"{path}: a quarter-car file (no attribute vehicle), not a half or full car")
    if kind not in VEHICLES:
        raise DatasetError(f"{path}: attribute vehicle = {kind!r} is not one of {[QUARTER_CAR, *VEHICLES]}")
    raw = info["attrs"].get("layout")
    try:
        layout = VehicleLayout.from_description(json.loads(raw))
    except (TypeError, ValueError, KeyError) as error:
        raise DatasetError(f"{path}: attribute layout = {raw!r} is not a vehicle layout ({error})") from None
    if layout.kind != kind:
        raise DatasetError(f"{path}: attribute layout describes a {layout.kind}, attribute vehicle says {kind}")
    expected = {
        "accel": list(layout.dofs),
        "vel": list(layout.dofs),
        "disp": list(layout.dofs),
        "road": list(layout.wheels),
        "road_vel": list(layout.wheels),
        "physical": list(layout.param_names),
    }
    attr = {"road": "wheels", "road_vel": "wheels", "physical": "names"}
    splits = [split] if split is not None else list(info["splits"])
    with h5py.File(path, "r") as handle:
        for name in splits:
            if name not in handle:
                raise DatasetError(f"{path}: split {name!r} not found; available splits: {sorted(info['splits'])}")
            for key, names in expected.items():
                if key not in handle[name]:
                    continue
                stored = column_names(handle[name][key])
                if stored != names:
                    raise DatasetError(
                        f"{path}: /{name}/{key} attribute {attr.get(key, 'dofs')} = {stored} does not match the "
                        f"{kind} of its layout ({names})"
                    )
    return layout


def check_vehicle_physical(path, split: str, layout: VehicleLayout, physical: np.ndarray) -> None:
    """The stored physical parameters must describe a vehicle (positive masses, inertias, ...; every
    seat on the chassis); DatasetError naming file, row and column otherwise."""
    problems = physical_problems(layout, torch.as_tensor(np.asarray(physical, dtype=np.float64)), f"/{split}/physical")
    if problems:
        raise DatasetError(f"{path}: {problems[0]}")


def choose_seat(path, layout: VehicleLayout, seat: str | None) -> str:
    """The seat asked for, or the only one; ConfigError-like DatasetError otherwise."""
    if seat is None:
        if len(layout.seats) == 1:
            return layout.seat_names[0]
        raise DatasetError(
            f"{path}: the {layout.kind} has seats {list(layout.seat_names)}: choose one with seat=<name>"
        )
    if str(seat) not in layout.seat_names:
        raise DatasetError(f"{path}: seat={seat!r} is not one of the file's seats {list(layout.seat_names)}")
    return str(seat)


def read_seat_split(
    path: str | os.PathLike,
    split: str,
    seat: str | None,
    keys: Iterable[str] = ("accel", "params"),
    n_steps: int | None = None,
    index=None,
    check_finite: bool = True,
) -> dict[str, np.ndarray]:
    """One seat of a vehicle file in the quarter car's layout (module docstring): the requested
    ``keys`` among accel, vel, disp, params, road_class, profile_id (plus ``k3`` [M] and ``h``)."""
    path = Path(path)
    info = dataset_info(path)
    layout = vehicle_layout(path, split, info)
    seat = choose_seat(path, layout, seat)
    keys = list(keys)
    unknown = [k for k in keys if k not in SEAT_KEYS]
    if unknown:
        raise DatasetError(f"{path}: a seat of a {layout.kind} offers {list(SEAT_KEYS)}, not {unknown}")
    motion = [k for k in keys if k in ("accel", "vel", "disp")]
    stored = read_split(
        path,
        split,
        motion + ["physical"] + [k for k in keys if k in ("road_class", "profile_id")],
        n_steps=n_steps,
        index=index,
        check_finite=check_finite,
    )
    check_vehicle_physical(path, split, layout, stored["physical"])
    physical = torch.from_numpy(np.asarray(stored["physical"], dtype=np.float64))
    names = layout.param_names
    out: dict[str, np.ndarray] = {}
    for key in motion:
        data = torch.from_numpy(np.asarray(stored[key], dtype=np.float64))  # [M, T, n_dof]
        columns = [data[..., layout.seat_dof(seat)], seat_base(layout, physical, seat, data)]
        columns.append(torch.full_like(columns[0], float("nan")))
        out[key] = (
            torch.stack(columns, -1).to(torch.float32 if stored[key].dtype == np.float32 else torch.float64).numpy()
        )
    m3 = physical[:, names.index(layout.seat_param("m3", seat))]
    k3 = physical[:, names.index(layout.seat_param("k3", seat))]
    c3 = physical[:, names.index(layout.seat_param("c3", seat))]
    if "params" in keys:
        params = torch.full((physical.shape[0], 10), float("nan"), dtype=torch.float64)
        params[:, 0], params[:, 1] = c3 / m3, k3 / m3
        out["params"] = params.numpy()
    for key in ("road_class", "profile_id"):
        if key in keys:
            out[key] = stored[key]
    out["k3"] = k3.numpy()
    if "h" in stored:
        out["h"] = stored["h"]
    return out


def seat_split_info(path: str | os.PathLike, split: str, seat: str | None) -> dict:
    """What the seat view of /<split> holds: {"seat", "layout", "n_samples", "n_steps", "keys", "h"}."""
    path = Path(path)
    info = dataset_info(path)
    layout = vehicle_layout(path, split, info)
    seat = choose_seat(path, layout, seat)
    have = set(info["splits"][split]["keys"])
    keys = [k for k in ("accel", "vel", "disp", "road_class", "profile_id") if k in have]
    if "physical" in have:
        keys.append("params")
    return {
        "seat": seat,
        "layout": layout,
        "n_samples": info["splits"][split]["n_samples"],
        "n_steps": info["splits"][split]["n_steps"],
        "keys": sorted(keys),
        "h": info["attrs"].get("h"),
    }


# ------------------------------------------------------------------------------------------------ sensor
def apply_sensor(sensor, accel: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """data/sensor.py's accelerometer model on any number of channels, accel [b, T, n]: the channels go
    through it three at a time, group g with salt g (so that no two channels share their noise);
    the sensor's sigma and bias must be one number for every channel (checked by uniform_sensor)."""
    if not sensor.active:
        return accel
    out = torch.empty_like(accel)
    n = accel.shape[-1]
    for group, first in enumerate(range(0, n, 3)):
        part = accel[..., first : first + 3]
        width = part.shape[-1]
        padded = torch.cat([part, part[..., :1].expand(*part.shape[:-1], 3 - width)], -1) if width < 3 else part
        out[..., first : first + 3] = sensor.apply(padded, index, salt=group)[..., :width]
    return out


def sensor_std(sensor, accel: torch.Tensor) -> torch.Tensor:
    """[b, n] the sensor's nominal noise std per channel of accel [b, T, n] (noise_std by groups of three)."""
    parts = []
    n = accel.shape[-1]
    for first in range(0, n, 3):
        part = accel[..., first : first + 3]
        width = part.shape[-1]
        padded = torch.cat([part, part[..., :1].expand(*part.shape[:-1], 3 - width)], -1) if width < 3 else part
        parts.append(sensor.noise_std(padded)[:, :width])
    return torch.cat(parts, -1)


def uniform_sensor(sensor) -> str | None:
    """None when the sensor treats every channel alike (one sigma, one bias), else the reason (a
    vehicle's channels are not the quarter car's a3, a2, a1)."""
    if not sensor.active:
        return None
    sensor._checked()
    if len(set(sensor._sigma)) > 1 or len(set(sensor._bias)) > 1:
        return f"sensor.sigma={sensor.sigma!r}, sensor.bias={sensor.bias!r} are per channel (a3, a2, a1); give one number each"
    return None


__all__ = [
    "QUARTER_CAR",
    "SEAT_KEYS",
    "vehicle_of",
    "vehicle_layout",
    "check_vehicle_physical",
    "choose_seat",
    "read_seat_split",
    "seat_split_info",
    "apply_sensor",
    "sensor_std",
    "uniform_sensor",
]
