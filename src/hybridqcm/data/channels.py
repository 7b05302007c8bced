"""Named channels of a dataset and how to cut them out of the stored arrays.

Time channels (each [M, N] per sample set):

    a3 a2 a1   accel[..., 0..2]   accelerations of occupant, chassis, wheel [m/s^2]
    v3 v2 v1   vel[..., 0..2]     velocities [m/s]
    q3 q2 q1   disp[..., 0..2]    displacements [m]
    u          road               road profile [m]
    pu_u       (p10 - p9) * road  wheel forcing p_u u [m/s^2] (needs params)

Parameter "channels" p1..p10 are columns of `params` [M, 10].

Works on numpy arrays and torch tensors alike (the simulator returns tensors, HDF5 numpy).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import torch

from hybridqcm.errors import DatasetError
from hybridqcm.physics.parameters import PARAM_NAMES

CHANNEL_NAMES: tuple[str, ...] = ("a3", "a2", "a1", "v3", "v2", "v1", "q3", "q2", "q1", "u", "pu_u")

# name -> (stored key, column or None)
_SOURCE: dict[str, tuple[str, int | None]] = {
    **{f"a{b}": ("accel", i) for i, b in enumerate((3, 2, 1))},
    **{f"v{b}": ("vel", i) for i, b in enumerate((3, 2, 1))},
    **{f"q{b}": ("disp", i) for i, b in enumerate((3, 2, 1))},
    "u": ("road", None),
}


class ChannelError(DatasetError):
    """An unknown or inconsistent channel name, or data lacking a channel's source key."""


def _as_list(names: str | Iterable[str] | None) -> list[str]:
    if names is None:
        return []
    if isinstance(names, str):
        return [names]
    return [str(n) for n in names]


def validate_channels(
    names: str | Iterable[str] | None, what: str = "channels", allow_params: bool = True
) -> list[str]:
    """Check names; a list is either all time channels or all parameters. Returns the list."""
    names = _as_list(names)
    valid = set(CHANNEL_NAMES) | (set(PARAM_NAMES) if allow_params else set())
    unknown = [n for n in names if n not in valid]
    if unknown:
        options = list(CHANNEL_NAMES) + (list(PARAM_NAMES) if allow_params else [])
        raise ChannelError(f"{what}: unknown channel name(s) {unknown}; valid names are {options}")
    if len(set(names)) != len(names):
        raise ChannelError(f"{what}: duplicate channel names in {names}")
    kinds = {is_param(n) for n in names}
    if len(kinds) > 1:
        raise ChannelError(f"{what}: {names} mixes time channels and parameters; use one kind per list")
    return names


def is_param(name: str) -> bool:
    return name in PARAM_NAMES


def required_keys(names: str | Iterable[str] | None) -> set[str]:
    """HDF5/simulator keys needed to build these channels, e.g. {'accel', 'params'}."""
    keys: set[str] = set()
    for name in validate_channels(names):
        if is_param(name):
            keys.add("params")
        elif name == "pu_u":
            keys |= {"road", "params"}
        else:
            keys.add(_SOURCE[name][0])
    return keys


def _channel(arrays: Mapping, name: str):
    if name == "pu_u":
        params = arrays["params"]
        gain = params[..., 9] - params[..., 8]
        return gain[:, None] * arrays["road"]
    key, column = _SOURCE[name]
    data = arrays[key]
    return data if column is None else data[..., column]


def select_channels(arrays: Mapping, names: Sequence[str], dtype=None):
    """Stack time channels -> [M, C, N] (torch if the source arrays are tensors, else numpy)."""
    names = validate_channels(names)
    if any(is_param(n) for n in names):
        raise ChannelError(f"select_channels: {names} are parameters; use select_params")
    missing = sorted(required_keys(names) - set(arrays))
    if missing:
        raise ChannelError(f"channels {names} need key(s) {missing}, which the data lacks (it has {sorted(arrays)})")
    columns = [_channel(arrays, n) for n in names]
    if isinstance(columns[0], torch.Tensor):
        out = torch.stack([torch.as_tensor(c) for c in columns], 1)
        return out if dtype is None else out.to(dtype)
    out = np.stack([np.asarray(c) for c in columns], 1)
    return out if dtype is None else out.astype(dtype, copy=False)


def select_params(arrays: Mapping, names: Sequence[str]):
    """Parameter columns -> [M, P] (float64)."""
    names = validate_channels(names)
    if not all(is_param(n) for n in names):
        raise ChannelError(f"select_params: {names} are not all parameters p1..p10")
    if "params" not in arrays:
        raise ChannelError(f"parameters {names} need key 'params', which the data lacks (it has {sorted(arrays)})")
    index = [PARAM_NAMES.index(n) for n in names]
    params = arrays["params"]
    if isinstance(params, torch.Tensor):
        return params[:, index].to(torch.float64)
    return np.asarray(params)[:, index].astype(np.float64)


def select(arrays: Mapping, names: Sequence[str], dtype=None):
    """Time channels [M, C, N] or parameters [M, P], whichever `names` are."""
    names = validate_channels(names)
    if names and is_param(names[0]):
        return select_params(arrays, names)
    return select_channels(arrays, names, dtype)


__all__ = [
    "CHANNEL_NAMES",
    "ChannelError",
    "validate_channels",
    "is_param",
    "required_keys",
    "select_channels",
    "select_params",
    "select",
]
