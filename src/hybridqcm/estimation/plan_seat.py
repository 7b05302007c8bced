"""qcm-estimate's seats: the road-free seat estimate on a half-car or full-car file (issue 30), and the
seat file's law (seat_file=, estimation/calibration.py) for the occupant's mass.

``experiment=occupant_roadfree seat=<name> data.path=<a half / full car file>``: the seat's z3 is the
model's output and the seat base's z2 + x_s α + y_s β its input (data/vehicle_files.read_seat_split
composes it from the stored chassis motion), so the quarter car's seat model (SPEC § 9) runs on it
unchanged; the occupant mass is m3 = K3 / p2 with the seat's stiffness, which must be ``K3``.
"""

from __future__ import annotations

import numpy as np

from hybridqcm.data.hdf5 import read_split
from hybridqcm.data.vehicle_files import QUARTER_CAR, seat_split_info, vehicle_of
from hybridqcm.errors import ConfigError


def seat_view_plan(cfg, path, split: str, info: dict, base: str | None) -> dict | None:
    """None for a quarter-car file (``seat`` must then be null); for a vehicle file run by a quarter-car
    experiment, the seat view: {"seat", "vehicle", "keys"} after checking that the experiment is the
    road-free seat model and the seat's k3 is K3. ConfigError / DatasetError (one line) otherwise."""
    kind = vehicle_of(info)
    seat = cfg.get("seat")
    if kind == QUARTER_CAR:
        if seat is not None:
            raise ConfigError(
                f"seat={seat!r}: {path} is a quarter-car file with its one seat (drop seat=; a seat calibration "
                "of qcm-calibrate is read with seat_file=)"
            )
        return None
    name = cfg.get("experiment_name", "custom")
    if base != "seat":
        raise ConfigError(
            f"{path} holds a {kind} (attribute vehicle), but experiment {name} fits the quarter car: use "
            f"experiment={'hcm' if kind == 'half_car' else 'fcm'}_full_observation, or experiment=occupant_roadfree "
            f"seat=<name> for one seat"
        )
    view = seat_split_info(path, split, seat)
    layout, chosen = view["layout"], view["seat"]
    if "params" in view["keys"]:
        n = int(view["n_samples"]) if cfg.get("n_samples") is None else min(int(cfg.n_samples), int(view["n_samples"]))
        physical = read_split(path, split, ("physical",), index=slice(0, n))["physical"]
        k3 = np.asarray(physical)[:, layout.param_names.index(layout.seat_param("k3", chosen))]
        K3 = float(cfg.K3)
        off = np.flatnonzero(np.abs(k3 - K3) > 1e-9 * abs(K3))
        if off.size:
            i = int(off[0])
            raise ConfigError(
                f"{path}: seat {chosen!r} has k3 = {float(k3[i])!r} N/m (recording {i}), but the occupant mass "
                f"m3 = K3 / p2 uses K3 = {K3!r}: pass K3={float(k3[i])!r}"
                + ("" if np.all(k3 == k3[0]) else " (its k3 differs between recordings: estimate them apart)")
            )
    return {"seat": chosen, "vehicle": kind, "keys": view["keys"]}


def seat_plan(cfg, plan):
    """The seat file's law (seat_file=, estimation/calibration.py) or None. Every quarter-car model reads one:
    the road-free seat and sprung models and the road-driven quarter car (exp5 .. exp10) all fit p2 = K3 / M as
    their second parameter, which the law inverts; the half and full car (``plan`` None) do not. The key is not
    ``seat``: that names a seat of a half / full car file (seat_view_plan)."""
    path = cfg.get("seat_file")
    if path is None:
        return None
    from hybridqcm.estimation.calibration import load_seat

    if plan is None:
        raise ConfigError(
            f"seat_file={path}: a seat calibration is read by the quarter car's models (its p2 = K3 / M); "
            f"vehicle_model={cfg.get('vehicle_model')} fits the seats' k3 and m3 of its own (drop seat_file=)"
        )
    return load_seat(path)


__all__ = ["seat_plan", "seat_view_plan"]
