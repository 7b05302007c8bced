"""Reading an untrusted checkpoint file as data (no code runs), below the loader and the modules.

``read_raw``: ``torch.load(weights_only=True)`` — tensors and plain containers only, a pickle
payload is refused before any of its code can run. ``check_config_tree``: every ``_target_``
anywhere in stored hyper-parameters must be on the allow-list (our network classes, torch
optimizers and LR schedulers). ``models.checkpoint`` (the loader) and ``models.base`` (which
builds its networks from hyper-parameters) both use these; neither imports the other's layer.
"""

from __future__ import annotations

import inspect
import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from hybridqcm.errors import CheckpointError
from hybridqcm.models.networks import NETWORKS

NETWORK_TARGETS = frozenset(NETWORKS)
# Optimizer / scheduler configs travel in hparams too (used only when training resumes).
OPTIMIZER_PREFIXES = ("torch.optim.",)
SPECIAL_KEYS = frozenset({"_target_", "_partial_"})


def _allowed_target(target: Any) -> bool:
    if not isinstance(target, str):
        return False
    if target in NETWORK_TARGETS:
        return True
    if target.startswith(OPTIMIZER_PREFIXES) and target.count(".") in (2, 3) and target.replace(".", "").isidentifier():
        module_name, _, attr = target.rpartition(".")
        if module_name not in ("torch.optim", "torch.optim.lr_scheduler"):
            return False
        obj = getattr(torch.optim if module_name == "torch.optim" else torch.optim.lr_scheduler, attr, None)
        return inspect.isclass(obj) and (
            issubclass(obj, torch.optim.Optimizer) or issubclass(obj, torch.optim.lr_scheduler.LRScheduler)
        )
    return False


def check_config_tree(value: Any, where: str, key: str = "hyper_parameters") -> None:
    """Refuse any ``_target_`` outside the allow-list (and any other Hydra special key) anywhere in ``value``."""
    if isinstance(value, Mapping):
        for k, v in value.items():
            name = f"{key}.{k}"
            if isinstance(k, str) and k.startswith("_") and k.endswith("_"):
                if k not in SPECIAL_KEYS:
                    raise CheckpointError(f"{where}: {name} is refused (Hydra key {k} is not allowed in a checkpoint)")
                if k == "_target_" and not _allowed_target(v):
                    raise CheckpointError(
                        f"{where}: {name} = {v!r} is not on the allow-list of networks "
                        f"{sorted(NETWORK_TARGETS)} and torch optimizers/schedulers; refused"
                    )
            check_config_tree(v, where, name)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            check_config_tree(v, where, f"{key}[{i}]")
    elif not (value is None or isinstance(value, (bool, int, float, str, torch.Tensor))):
        raise CheckpointError(f"{where}: {key} holds a {type(value).__name__}, not plain data; refused")


def read_raw(path: Path, where: str) -> dict:
    """The checkpoint dict, loaded with weights_only=True; CheckpointError (one line) for anything else."""
    if not path.is_file():
        raise CheckpointError(f"{where}: checkpoint file does not exist")
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - any unreadable file is the same user error
        text = str(error).strip()
        culprit = next((line.strip() for line in text.splitlines() if "GLOBAL" in line), "")
        if isinstance(error, pickle.UnpicklingError) and culprit:
            # torch names the refused global ("Trying to load unsupported GLOBAL posix.system ...").
            raise CheckpointError(
                f"{where}: refused, the file holds pickled objects other than tensors and plain data ({culprit[:160]})"
            ) from None
        if isinstance(error, pickle.UnpicklingError):
            detail = next(
                (
                    line.strip()
                    for line in text.splitlines()[1:]
                    if line.strip()
                    and "error:" not in line
                    and "Check the documentation" not in line
                    and "Please file" not in line
                ),
                "",
            )
            raise CheckpointError(
                f"{where}: not a readable torch checkpoint ({detail[:160] or 'unpickling failed'})"
            ) from None
        first = text.splitlines()[0][:160] if text else ""
        raise CheckpointError(f"{where}: not a readable torch checkpoint ({type(error).__name__}: {first})") from None
    if not isinstance(raw, dict):
        raise CheckpointError(f"{where}: not a Lightning checkpoint (a {type(raw).__name__}, not a dict)")
    return raw
