"""The HDF5 dataset format (SPEC §5, §9) — the interface other tools write to and read from.

    attrs: schema = "hybridqcm.dataset/2", h, n_steps, speed_mps, prior, seed, created_by,
           physics ("euler" | "continuous"), warmup_s [low, high] seconds driven before a window
    /<split>/accel float32 [M, n_steps, 3] (a3, a2, a1)   /<split>/vel, /<split>/disp likewise
    /<split>/road  float32 [M, n_steps]   u in metres     /<split>/params float64 [M, 10]
    /<split>/road_class int8 [M]                          /<split>/profile_id int32 [M]
    /<split>/state0 float64 [M, 6]  state at the window start (v3 v2 v1 q3 q2 q1)
    optional: /<split>/occupant_params float64 [M, 3 n_modes]  a seated person's (r_i, k_i, c_i)
              per body mode (physics/occupant.py), with the split attribute occupant
              ("rigid" | "body1" | "body2"); a split without the attribute is a rigid occupant
              for our generator's files (params keep p1 = C3/M, p2 = K3/M, M the static mass)

Schema /1 files (no physics, no state0) still read. A file without `physics` from another
producer (a real logger) is taken as continuous physics with an unknown initial state. Files
may lack /road (nobody measures it) and accel may hold an all-NaN column (an unrecorded
channel): readers check only what the task asks for.

The optional key and attribute came with schema /2 unchanged: readers take any key they do not
know (read_split checks only the shapes of LAYOUT's keys), so older readers still read new files.

Readers accept any producer's file that has the keys the task needs. Writers never leave a
half-written file that looks valid: they write to a temporary file beside the target and
rename it into place only after everything was written and flushed.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import h5py
import numpy as np

from hybridqcm.errors import DatasetError
from hybridqcm.physics.parameters import CHANNELS

SCHEMA = "hybridqcm.dataset/2"
SCHEMA_FAMILY = "hybridqcm.dataset/"
SUPPORTED_SCHEMAS = ("hybridqcm.dataset/1", SCHEMA)
PHYSICS = ("continuous", "euler")  # the values of the `physics` attribute (absent: continuous, another producer)

# key -> (dtype, trailing shape given n_steps); the leading dimension is the sample count M.
LAYOUT: dict[str, tuple[np.dtype, tuple]] = {
    "accel": (np.dtype("float32"), ("n_steps", 3)),
    "vel": (np.dtype("float32"), ("n_steps", 3)),
    "disp": (np.dtype("float32"), ("n_steps", 3)),
    "road": (np.dtype("float32"), ("n_steps",)),
    "params": (np.dtype("float64"), (10,)),
    "road_class": (np.dtype("int8"), ()),
    "profile_id": (np.dtype("int32"), ()),
    "state0": (np.dtype("float64"), (6,)),
}
TIME_KEYS = ("accel", "vel", "disp", "road")


def trailing_shape(key: str, n_steps: int) -> tuple[int, ...]:
    return tuple(n_steps if dim == "n_steps" else dim for dim in LAYOUT[key][1])


def _open(path: str | os.PathLike) -> h5py.File:
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: dataset file does not exist (create one with `qcm-simulate output={path}`)")
    try:
        handle = h5py.File(path, "r")
    except OSError as error:
        raise DatasetError(f"{path}: not a readable HDF5 file ({error})") from None
    try:
        _check_links(path, handle)
    except BaseException:
        handle.close()
        raise
    return handle


def _check_links(path: Path, handle: h5py.File) -> None:
    """Data must be stored in the file itself: a run's fingerprint (shards, completion markers) is the
    file's size and time, which a linked file's change does not touch. An external link, a virtual
    dataset mapping another file, or a soft link that leads nowhere is one DatasetError naming it
    (before: h5py's KeyError traceback for a missing target or a loop, silent data from elsewhere)."""

    def problem(name: str, link) -> str | None:  # a message stops the visit (raising inside it cannot)
        if isinstance(link, h5py.ExternalLink):
            target = Path(link.filename) if Path(link.filename).is_absolute() else path.parent / link.filename
            if not target.exists():
                state = "a file that does not exist"
            elif target.resolve() == path.resolve():
                state = "this file itself: a loop"
            else:
                state = "another file, whose changes would not be noticed"
            return (
                f"{path}: /{name} is an external link to {link.filename}:{link.path} ({state}); "
                f"copy the data into the file (e.g. h5copy) so it holds what it is read for"
            )
        if isinstance(link, h5py.SoftLink):
            try:
                target = handle.get(name)
            except (KeyError, RuntimeError, OSError):  # "too many links": a loop
                target = None
            if target is None:
                return f"{path}: /{name} is a soft link to {link.path}, which leads nowhere or in a loop"
        if isinstance(link, h5py.HardLink):
            obj = handle.get(name)
            if isinstance(obj, h5py.Dataset) and obj.is_virtual:
                others = sorted({s.file_name for s in obj.virtual_sources() if s.file_name != "."})
                if others:
                    return (
                        f"{path}: /{name} is a virtual dataset mapping {others[0]}; copy the data into the file "
                        f"so it holds what it is read for"
                    )
        return None

    message = handle.visititems_links(problem)
    if message:
        raise DatasetError(message)


def _check_schema(path: Path, handle: h5py.File) -> None:
    if "h" in handle.attrs:
        _step(path, handle)
    schema = handle.attrs.get("schema")
    if schema is None:
        return  # other producers may omit it; the layout checks below still apply
    schema = schema.decode() if isinstance(schema, bytes) else str(schema)
    if schema not in SUPPORTED_SCHEMAS:
        raise DatasetError(
            f"{path}: attribute schema = {schema!r} is not supported (expected one of {list(SUPPORTED_SCHEMAS)})"
        )


def _step(path: Path, handle: h5py.File) -> float:
    """Attribute h as a positive finite float, or a one-line DatasetError."""
    raw = _attr_value(handle.attrs["h"])
    try:
        value = float(raw) if not isinstance(raw, (str, bool)) else float("nan")
    except (TypeError, ValueError):
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise DatasetError(f"{path}: attribute h = {raw!r} must be a positive number of seconds (the sampling period)")
    return value


def _physics(attrs: Mapping) -> tuple[str, str]:
    """(physics, initial_state) of a file: initial_state is "rest", "mid-drive" or "unknown"."""
    physics = attrs.get("physics")
    ours = str(attrs.get("created_by", "")).startswith("hybridqcm")
    if physics is None:
        if ours and "integrator" in attrs:  # schema /1 from our generator: Euler from rest
            return "euler", "rest"
        return "continuous", "unknown"  # another producer, e.g. a real logger
    warmup = attrs.get("warmup_s")
    if isinstance(warmup, str):  # lists are stored as JSON text by DatasetWriter
        try:
            warmup = json.loads(warmup)
        except ValueError:
            raise DatasetError(
                f"attribute warmup_s = {warmup!r} is not a number or [low, high] range of seconds"
            ) from None
    try:
        high = max(np.atleast_1d(np.asarray(warmup, dtype=float))) if warmup is not None else None
    except (TypeError, ValueError):
        raise DatasetError(f"attribute warmup_s = {warmup!r} is not a number or [low, high] range of seconds") from None
    if high is None:
        return str(physics), "unknown"
    return str(physics), "rest" if high == 0 else "mid-drive"


def _attr_value(value):
    """A plain Python value for an HDF5 attribute (bytes decoded, numpy scalars and arrays unwrapped)."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray):
        return value.item() if value.ndim == 0 else value.tolist()
    return value.item() if hasattr(value, "item") else value


def _row_selection(path: Path, split: str, index, n_samples: int):
    """(sorted unique rows to read, how to put them back in the requested order) for `index`."""
    if index is None or isinstance(index, slice):
        return index, None
    index = np.asarray(index)
    if index.dtype == bool:
        if index.shape != (n_samples,):
            raise DatasetError(f"{path}: boolean index of shape {index.shape} for /{split} with {n_samples} samples")
        index = np.flatnonzero(index)
    if index.ndim != 1 or index.dtype.kind not in "iu":
        raise DatasetError(
            f"{path}: index must be a slice, a boolean mask or a 1-D integer array, got {index.dtype} {index.shape}"
        )
    index = np.where(index < 0, index + n_samples, index)
    if index.size and (index.min() < 0 or index.max() >= n_samples):
        raise DatasetError(
            f"{path}: index out of range for /{split} with {n_samples} samples "
            f"(min {int(index.min())}, max {int(index.max())})"
        )
    unique, inverse = np.unique(index, return_inverse=True)  # h5py reads increasing, unique rows only
    return unique, inverse


def dataset_info(path: str | os.PathLike) -> dict:
    """File attributes and, per split, its sample count, step count and keys."""
    path = Path(path)
    with _open(path) as handle:
        _check_schema(path, handle)
        attrs = {k: _attr_value(v) for k, v in handle.attrs.items()}
        physics, initial_state = _physics(attrs)
        if physics not in PHYSICS:  # before: taken for continuous physics, silently
            raise DatasetError(f"{path}: attribute physics = {physics!r} is not one of {list(PHYSICS)}")
        splits = {}
        for name, group in handle.items():
            if not isinstance(group, h5py.Group):
                continue
            keys = sorted(group.keys())
            for key in ("accel", "road"):
                if key in group and not isinstance(group[key], h5py.Dataset):
                    raise DatasetError(
                        f"{path}: /{name}/{key} is a {type(group[key]).__name__}, not an array with one row per sample"
                    )
            first = next((group[k] for k in ("accel", "road") if k in group), None)
            splits[name] = {
                "n_samples": int(first.shape[0]) if first is not None else 0,
                "n_steps": int(first.shape[1]) if first is not None and first.ndim > 1 else None,
                "keys": keys,
            }
            if "occupant" in group.attrs:  # only where a producer wrote it (older files: none)
                splits[name]["occupant"] = str(_attr_value(group.attrs["occupant"]))
    return {"path": str(path), "attrs": attrs, "splits": splits, "physics": physics, "initial_state": initial_state}


def column_names(data: h5py.Dataset) -> list[str] | None:
    """The names of a stored array's last axis, where its producer wrote them: the ``dofs`` of a
    half-car / full-car file's accel/vel/disp, the ``wheels`` of its road, the ``names`` of its
    physical parameters; None for the quarter car's fixed layout."""
    for attr in ("dofs", "wheels", "names"):
        if attr in data.attrs:
            return [v.decode() if isinstance(v, bytes) else str(v) for v in np.atleast_1d(data.attrs[attr])]
    return None


def recorded_channels(path: str | os.PathLike, split: str = "test") -> list[str]:
    """Accelerometer channels of /<split>/accel (of a3, a2, a1) that hold any finite value."""
    arrays = read_split(path, split, ("accel",))
    finite = np.isfinite(arrays["accel"]).any(axis=(0, 1))
    return [name for name, ok in zip(CHANNELS, finite) if ok]


def read_split(
    path: str | os.PathLike,
    split: str = "test",
    keys: Iterable[str] = ("accel", "road", "params"),
    n_steps: int | None = None,
    index: slice | np.ndarray | None = None,
    check_finite: bool = True,
) -> dict[str, np.ndarray]:
    """Read `keys` of one split, time-series cropped to the first `n_steps` steps.

    `index` (a slice, a boolean mask or integer rows, in any order, repeats allowed) selects
    samples; rows come back in the order asked for.
    Returns numpy arrays keyed as in the file plus "h" (float, step size) when the file has it.
    Raises DatasetError for a missing file/split/key, a wrong shape, a window longer than the
    stored steps, or NaN/inf values.
    """
    path = Path(path)
    keys = list(keys)
    with _open(path) as handle:
        _check_schema(path, handle)
        if split not in handle:
            available = [k for k, v in handle.items() if isinstance(v, h5py.Group)]
            raise DatasetError(f"{path}: split {split!r} not found; available splits: {available}")
        group = handle[split]
        if not isinstance(group, h5py.Group):
            raise DatasetError(f"{path}: /{split} is a {type(group).__name__}, not a group of datasets")
        missing = [k for k in keys if k not in group]
        if missing:
            raise DatasetError(
                f"{path}: /{split} lacks dataset(s) {missing} needed here; it has {sorted(group.keys())}"
            )
        out: dict[str, np.ndarray] = {}
        n_samples = None
        rows = inverse = None
        for key in keys:
            data = group[key]
            if not isinstance(data, h5py.Dataset) or data.ndim < 1:
                raise DatasetError(f"{path}: /{split}/{key} is not an array with one row per sample")
            if n_samples is None:
                n_samples = data.shape[0]
                rows, inverse = _row_selection(path, split, index, n_samples)
            elif data.shape[0] != n_samples:
                raise DatasetError(f"{path}: /{split}/{key} has {data.shape[0]} samples, other keys have {n_samples}")
            if key in TIME_KEYS or key == "road_vel":
                stored = data.shape[1] if data.ndim > 1 else 0
                expected_tail = (3,) if key != "road" else ()
                named = column_names(data)  # a half-car / full-car file names its columns (dofs, wheels)
                if named is not None:
                    expected_tail = (len(named),)
                if data.ndim != 2 + len(expected_tail) or tuple(data.shape[2:]) != expected_tail:
                    raise DatasetError(
                        f"{path}: /{split}/{key} has shape {data.shape}, expected "
                        f"[M, n_steps{''.join(f', {d}' for d in expected_tail)}]"
                    )
                window = stored if n_steps is None else int(n_steps)
                if window < 1 or window > stored:
                    raise DatasetError(f"{path}: window n_steps = {n_steps} but /{split}/{key} stores {stored} steps")
                array = data[:, :window] if rows is None else data[rows, :window]
            else:
                if key in LAYOUT and tuple(data.shape[1:]) != trailing_shape(key, 0):
                    raise DatasetError(
                        f"{path}: /{split}/{key} has shape {data.shape}, expected [M{', ' if LAYOUT[key][1] else ''}{', '.join(map(str, LAYOUT[key][1]))}]"
                    )
                array = data[()] if rows is None else data[rows]
            array = np.asarray(array)
            if inverse is not None:
                array = array[inverse]
            if key == "accel" and array.dtype not in (np.float32, np.float64):
                raise DatasetError(f"{path}: /{split}/accel has dtype {array.dtype}; expected float32 or float64")
            finite = np.isfinite(array) if check_finite and array.dtype.kind == "f" else None
            if finite is not None and key == "accel" and array.size:
                # an all-NaN channel is an unrecorded one (the consumer decides whether it needs it)
                unrecorded = np.isnan(array).all(axis=(0, 1))
                finite = finite | unrecorded[None, None, :]
            if finite is not None and not finite.all():
                bad = np.argwhere(~finite)[0]
                raise DatasetError(
                    f"{path}: /{split}/{key} contains non-finite values (first at index {tuple(int(i) for i in bad)}: {array[tuple(bad)]})"
                )
            out[key] = array
        if "h" in handle.attrs:
            out["h"] = _step(path, handle)
    return out
