"""The one checkpoint loader: untrusted `.ckpt` files in, a LightningModule of ours out (or one line).

A checkpoint is something users exchange ("send me your trained CNN"), so it is read as data,
never executed:

1. ``torch.load(weights_only=True)``: tensors and plain containers only, no pickled objects
   (a pickle payload is refused before any of its code can run).
2. The stored class name (``hybridqcm_class``) must be one of ours and fit the requested kind
   (vocabulary: "cnn" | "unet" | "cae").
3. The stored hyper-parameters are plain data checked against the class's ``__init__``
   signature; every ``_target_`` anywhere in them must be on the allow-list (our network
   classes, torch optimizers and LR schedulers), because the module builds its net with Hydra
   ``instantiate`` from them. Nothing outside the allow-list is ever instantiated.
4. The state_dict is loaded strictly: a missing, unexpected or mis-shaped key is refused.

    load_checkpoint(path, kind, config_key=None) -> module in eval mode on the CPU
    load_module(path, cls)                        -> the same, refused unless the file holds a `cls`
    read_checkpoint(path, kind, config_key=None) -> CheckpointInfo (class, hparams; no module built)
    stored_class(path, config_key=None)          -> the class name a file stores (None: not ours)

Every failure is a CheckpointError (hybridqcm.errors) with one line naming the file (and setting).
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
from lightning import LightningModule

from hybridqcm.errors import CheckpointError
from hybridqcm.models.estimators import LabelledEstimator, PhysicsResidualEstimator
from hybridqcm.models.gaussian_estimator import GaussianEstimator
from hybridqcm.models.signal_models import CompletionUNet, DenoisingAutoencoder
from hybridqcm.models.untrusted import check_config_tree, read_raw

# The classes a checkpoint may name, by the class name it stores (``hybridqcm_class``): a file
# records no module path, so moving a class between modules leaves every checkpoint loadable.
MODULES = {
    cls.__name__: cls
    for cls in (LabelledEstimator, GaussianEstimator, PhysicsResidualEstimator, DenoisingAutoencoder, CompletionUNet)
}
KINDS: dict[str, tuple[str, ...]] = {
    "cnn": ("LabelledEstimator", "GaussianEstimator", "PhysicsResidualEstimator"),
    "unet": ("CompletionUNet",),
    "cae": ("DenoisingAutoencoder",),
}
PHYSICS = ("euler", "continuous")
KIND_OF_CLASS = {name: kind for kind, names in KINDS.items() for name in names}


@dataclass(frozen=True)
class CheckpointInfo:
    """What a checkpoint file holds, read as plain data: class name, hyper-parameters, state_dict."""

    path: Path
    class_name: str
    kind: str
    hparams: dict
    state_dict: dict


def _where(path, config_key: str | None) -> str:
    return f"{config_key}={path}" if config_key else str(path)


def _class_name(raw: Mapping) -> str | None:
    stored = raw.get("hybridqcm_class")
    return stored if isinstance(stored, str) else None


def stored_class(path: str | os.PathLike, config_key: str | None = None) -> str | None:
    """The class name a checkpoint file stores (None for a foreign checkpoint), read as data; the one
    reader of ``hybridqcm_class``. CheckpointError (one line) for a missing, unreadable or refused file."""
    return _class_name(read_raw(Path(path), _where(path, config_key)))


def read_checkpoint(path: str | os.PathLike, kind: str | None = None, config_key: str | None = None) -> CheckpointInfo:
    """Read and check a checkpoint without building anything; raises CheckpointError (one line).

    kind: "cnn" | "unet" | "cae" (None: any of our classes)."""
    if kind is not None and kind not in KINDS:
        raise CheckpointError(f"checkpoint kind {kind!r} is unknown; choose one of {sorted(KINDS)}")
    path = Path(path)
    where = _where(path, config_key)
    raw = read_raw(path, where)
    stored = _class_name(raw)
    allowed = KINDS[kind] if kind else tuple(KIND_OF_CLASS)
    if stored not in allowed:
        what = f"a {stored}" if stored else "a non-hybridqcm"
        need = f"{kind} needs one of {list(allowed)}" if kind else f"expected one of {list(allowed)}"
        raise CheckpointError(f"{where}: holds {what} checkpoint, but {need}")
    hparams = raw.get("hyper_parameters", {})
    if not isinstance(hparams, Mapping):
        raise CheckpointError(f"{where}: hyper_parameters is a {type(hparams).__name__}, not a mapping")
    hparams = dict(hparams)
    check_config_tree(hparams, where)
    cls = MODULES[stored]
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self"}
    unknown = sorted(set(hparams) - accepted)
    if unknown:
        raise CheckpointError(f"{where}: hyper_parameters {unknown} are not arguments of {stored}; refused")
    physics = hparams.get("physics", "euler")
    if physics not in PHYSICS:
        raise CheckpointError(f"{where}: hyper_parameters.physics = {physics!r}; expected one of {list(PHYSICS)}")
    state = raw.get("state_dict")
    if not isinstance(state, Mapping) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise CheckpointError(f"{where}: state_dict is missing or holds non-tensor values")
    return CheckpointInfo(path, stored, KIND_OF_CLASS[stored], hparams, dict(state))


def _strict_shapes(module: LightningModule, state: Mapping[str, torch.Tensor], where: str, name: str) -> None:
    own = module.state_dict()
    bad = [
        f"{k} {tuple(v.shape)} vs {tuple(own[k].shape)}"
        for k, v in state.items()
        if k in own and v.shape != own[k].shape
    ]
    if bad:
        raise CheckpointError(f"{where}: state_dict shapes do not match {name}: {bad[:3]}")


def load_checkpoint(path: str | os.PathLike, kind: str | None = None, config_key: str | None = None) -> LightningModule:
    """The checkpoint's module (eval mode, CPU), built only from the allow-list; CheckpointError otherwise.

    kind: "cnn" (LabelledEstimator, PhysicsResidualEstimator), "unet" (CompletionUNet),
    "cae" (DenoisingAutoencoder), or None for any of them. config_key names the setting in
    messages (e.g. "cnn_ckpt")."""
    info = read_checkpoint(path, kind, config_key)
    where = _where(info.path, config_key)
    cls = MODULES[info.class_name]
    # Shapes first: load_state_dict raises a multi-line RuntimeError on a shape mismatch.
    try:
        probe = cls(**info.hparams)
    except Exception as error:  # noqa: BLE001
        first = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise CheckpointError(
            f"{where}: hyper_parameters do not build a {info.class_name} ({type(error).__name__}: {first})"
        ) from None
    _strict_shapes(probe, info.state_dict, where, info.class_name)
    result = probe.load_state_dict(info.state_dict, strict=False)
    problems = []
    if result.missing_keys:
        problems.append(f"missing keys {result.missing_keys[:5]}{' ...' if len(result.missing_keys) > 5 else ''}")
    if result.unexpected_keys:
        problems.append(
            f"unexpected keys {result.unexpected_keys[:5]}{' ...' if len(result.unexpected_keys) > 5 else ''}"
        )
    if problems:
        raise CheckpointError(f"{where}: state_dict does not match {info.class_name}: {'; '.join(problems)}")
    probe.eval()
    return probe


def load_module(path: str | os.PathLike, cls: type) -> LightningModule:
    """A checkpoint of exactly class ``cls`` through load_checkpoint; CheckpointError (one line) for a
    missing, refused or foreign file, or one holding another class."""
    stored = stored_class(path)
    if stored != cls.__name__:
        raise CheckpointError(f"checkpoint {path} holds a {stored or 'non-hybridqcm'} model, expected {cls.__name__}")
    return load_checkpoint(path)


def kind_of(module: LightningModule) -> str | None:
    """The loader vocabulary's kind of one of our modules ("cnn" | "unet" | "cae"), None for others."""
    return KIND_OF_CLASS.get(type(module).__name__)


__all__ = [
    "KINDS",
    "MODULES",
    "warm_start",
    "CheckpointInfo",
    "read_checkpoint",
    "stored_class",
    "load_checkpoint",
    "load_module",
    "kind_of",
]


def warm_start(model: LightningModule) -> LightningModule:
    """Apply ``model.hparams.init_from`` (a trained parameter-CNN checkpoint, loaded here by the one
    safe loader) to a GaussianEstimator before training: its backbone, normalisation and means."""
    path = model.hparams.get("init_from")
    if path and hasattr(model, "warm_start"):
        model.warm_start(load_checkpoint(path, "cnn", "model.init_from"), str(path))
    return model
