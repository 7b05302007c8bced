"""Export a trained network checkpoint: TorchScript (.pt) + ONNX (.onnx) + its contract (.json), parity-checked.

The exported graph is the checkpoint's physical-unit inference (models/export.py): raw
accelerations [batch, channels, time] in m/s² in, parameters or signals out, normalisation
inside, batch axis dynamic. Each export is checked against the checkpoint's own `estimate` /
`denoise` / `complete` on held-out recordings (`data`, default split test) or, without a data
file, on synthetic smooth signals; a deviation beyond `tol` raises ParityError. Files are
published atomically and exclusively (an existing export only replaced with overwrite).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

from hybridqcm.atomic import forget, new_temporary
from hybridqcm.errors import ConfigError

FORMATS = ("torchscript", "onnx")
SPEC_H = 0.01  # the step size the networks are trained at (SPEC §5) when neither the data nor the checkpoint says


class ParityError(RuntimeError):
    """An export whose outputs deviate from the checkpoint's own inference beyond the tolerance."""


def load_for_export(path: str):
    """The checkpoint's LightningModule on the CPU, in eval mode, through the safe loader (no code in the
    file runs: weights only, classes from the allow-list). The one place checkpoints are read here."""
    from hybridqcm.errors import CheckpointError
    from hybridqcm.models.checkpoint import load_checkpoint

    try:
        return load_checkpoint(path, None, "ckpt")
    except CheckpointError as error:
        raise ConfigError(str(error)) from None


def _publish(tmp: Path, path: Path, overwrite: bool = False) -> Path:
    """Put the finished temporary file in place: replacing `path` only with overwrite, else exclusively
    (os.link fails if the path appeared meanwhile: another export's or the user's file is never replaced)."""
    os.chmod(tmp, 0o644)
    if overwrite:
        os.replace(tmp, path)
        return path
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise ConfigError(f"{path} appeared while exporting; not replaced (pass --overwrite to replace it)") from None
    finally:
        tmp.unlink(missing_ok=True)
    return path


@contextlib.contextmanager
def _publishing(path: Path, overwrite: bool, suffix: str = ""):
    """A new temporary file beside ``path`` to write, put in place by :func:`_publish` when the block ends, and
    removed (and forgotten: atomic.new_temporary) whether the block or the publication fails or not."""
    tmp = new_temporary(path, suffix)
    try:
        yield tmp
        _publish(tmp, path, overwrite)
    finally:
        tmp.unlink(missing_ok=True)
        forget(tmp)


def _targets(out: Path, stem: str, formats: Sequence[str]) -> list[Path]:
    suffix = {"torchscript": ".pt", "onnx": ".onnx"}
    return [out / f"{stem}{suffix[f]}" for f in FORMATS if f in formats] + [out / f"{stem}.json"]


def parity_inputs(model, time_steps: int, data: str | None, split: str, n: int, seed: int = 0):
    """Inputs [n, C, time_steps] float32 in m/s²: held-out recordings from `data`, else smooth synthetic signals.

    Synthetic: white noise smoothed over ~10 steps, scaled to ~1 m/s² RMS; it exercises the graph
    (every operation and the per-sample scaling), not the physics."""
    import numpy as np
    import torch

    from hybridqcm.models.export import io_names

    inputs, _ = io_names(model)
    if data:
        from hybridqcm.data.channels import required_keys, select_channels
        from hybridqcm.data.hdf5 import read_split

        keys = sorted(required_keys(inputs))
        arrays = read_split(data, split, keys=keys, n_steps=time_steps, index=slice(0, n))
        return torch.from_numpy(np.ascontiguousarray(select_channels(arrays, inputs, dtype=np.float32))), arrays.get(
            "h"
        )
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(n, len(inputs), time_steps + 9, generator=generator)
    smooth = noise.unfold(-1, 10, 1).mean(-1)[..., :time_steps]
    return (smooth / smooth.pow(2).mean(-1, keepdim=True).sqrt()).float(), None


def export(
    ckpt: str,
    out_dir: str | Path | None = None,
    stem: str | None = None,
    formats: Sequence[str] = FORMATS,
    time_steps: int | None = None,
    data: str | None = None,
    split: str = "test",
    n_check: int = 64,
    tol: float = 1e-5,
    overwrite: bool = False,
) -> dict:
    """Write the exports and the JSON contract; returns the contract (with a `parity` entry per format).

    An existing export (STEM.pt, STEM.onnx, STEM.json) is refused before any work unless overwrite.
    Raises ConfigError for bad input and ParityError when an export deviates beyond `tol` (the
    files are then left in place for inspection, the contract records the deviation)."""
    import torch

    from hybridqcm.models.export import PhysicalGraph, contract, export_time_steps, parity_error, reference_output

    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ConfigError(f"--format {list(formats)}: choose from {list(FORMATS)}")
    if "onnx" in formats:
        missing = [m for m in ("onnx", "onnxruntime", "onnxscript") if importlib.util.find_spec(m) is None]
        if missing:
            raise ConfigError(
                f"--format onnx needs the package(s) {missing}: pip install -e '.[export]' (or --format torchscript)"
            )
    out = Path(out_dir) if out_dir else Path(ckpt).parent
    stem = stem or Path(ckpt).stem
    existing = [p for p in _targets(out, stem, formats) if p.exists()]
    if existing and not overwrite:  # before: replaced without a word
        raise ConfigError(f"{existing[0]} exists; pass --overwrite to replace the export (or --out/--name)")
    model = load_for_export(ckpt)
    try:
        steps = export_time_steps(model, time_steps)
    except ValueError as error:
        raise ConfigError(f"--time-steps {time_steps}: {error}") from None
    out.mkdir(parents=True, exist_ok=True)

    x, h = parity_inputs(model, steps, data, split, n_check)
    graph = PhysicalGraph(model).eval()
    reference = reference_output(model, x)
    sidecar = contract(model, steps, float(h) if h is not None else SPEC_H)
    sidecar["h_source"] = f"attrs of {data}" if h is not None else "SPEC default (no --data given)"
    sidecar.update({"checkpoint": str(Path(ckpt).resolve()), "files": {}, "parity": {}})
    sidecar["parity_inputs"] = (
        f"{len(x)} recordings of {data} /{split}" if data else f"{len(x)} synthetic smooth signals"
    )
    sidecar["parity_measure"] = (
        "max |Δp| / |p| per element" if model.kind == "estimator" else "max |Δ| / RMS of the reference channel"
    )
    example = x[: min(2, len(x))]
    with torch.no_grad():
        if "torchscript" in formats:
            path = out / f"{stem}.pt"
            with warnings.catch_warnings():
                # The time axis is fixed at export by design (padding is computed from it); the tracer says so per layer.
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                traced = torch.jit.trace(graph, example, check_trace=False)
            with _publishing(path, overwrite) as tmp:
                torch.jit.save(traced, str(tmp))
            loaded = torch.jit.load(str(path))
            sidecar["files"]["torchscript"] = path.name
            sidecar["parity"]["torchscript"] = parity_error(model, reference, loaded(x))
        if "onnx" in formats:
            path = out / f"{stem}.onnx"
            sidecar["files"]["onnx"] = path.name
            sidecar["parity"]["onnx"] = _export_onnx(graph, example, x, path, model, reference, overwrite)
    sidecar["tolerance"] = tol
    contract_path = out / f"{stem}.json"
    with _publishing(contract_path, overwrite) as tmp:
        tmp.write_text(json.dumps(sidecar, indent=2) + "\n")
    worst = {k: v for k, v in sidecar["parity"].items() if not v <= tol}
    if worst:
        raise ParityError(
            f"{ckpt}: export deviates from the checkpoint beyond {tol:g}: {worst} "
            f"({sidecar['parity_measure']}); files left in {out}"
        )
    return sidecar


def _export_onnx(graph, example, x, path: Path, model, reference, overwrite: bool = False) -> float:
    """torch.onnx (dynamo) export with a dynamic batch axis; returns the ONNX Runtime parity error."""
    import logging

    import onnxruntime
    import torch

    from hybridqcm.models.export import parity_error

    logging.getLogger("torch.onnx").setLevel(logging.ERROR)
    with _publishing(path, overwrite, ".onnx") as tmp:  # the exporter wants the .onnx suffix
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                torch.onnx.export(
                    graph,
                    (example,),
                    str(tmp),
                    input_names=["accel"],
                    output_names=["params" if model.kind == "estimator" else "signals"],
                    dynamic_shapes={"x": {0: torch.export.Dim("batch")}},
                    dynamo=True,
                    verbose=False,
                    external_data=False,
                )
        finally:
            for leftover in path.parent.glob(f"{tmp.name}?*"):  # the exporter's side files, ours only
                leftover.unlink(missing_ok=True)
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (result,) = session.run(None, {"accel": x.numpy()})
    return parity_error(model, reference, torch.from_numpy(result))
