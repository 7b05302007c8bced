"""Where the configs live and the checks every app makes of its settings before any work: the run
folder writable, task_name a plain folder name, Lightning's devices/num_nodes, and an experiment
that belongs to the app asked to run it. Each failure is one ConfigError naming the key and value.

Layout: configs/<app>.yaml is app <app>'s primary config; the groups the apps share are folders of
configs/, and configs/<app>/ (on the app's search path: its `hydra.searchpath`, through the
${hybridqcm_config_dir:} resolver registered here) holds the groups of that app alone, its
experiments (configs/train/experiment/, configs/estimate/experiment/)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from hybridqcm.errors import ConfigError

# The configs live at the repository root (configs/); HYBRIDQCM_CONFIG_DIR points elsewhere.
CONFIG_DIR = Path(os.environ.get("HYBRIDQCM_CONFIG_DIR", Path(__file__).resolve().parents[2] / "configs"))


def _register_config_dir_resolver() -> None:
    """${hybridqcm_config_dir:} (the apps' `hydra.searchpath`): CONFIG_DIR, wherever the configs live;
    registered before anything composes a config (apps and tests import CONFIG_DIR from here)."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("hybridqcm_config_dir"):
        OmegaConf.register_new_resolver("hybridqcm_config_dir", lambda: str(CONFIG_DIR))


_register_config_dir_resolver()


def check_writable_dir(path: str | Path, key: str = "hydra.run.dir") -> Path:
    """Create `path` if needed and prove it writable (a probe file), before any work; ConfigError otherwise."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".write-probe-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as error:
        raise ConfigError(f"{key}={path}: run folder is not writable ({error.strerror or error})") from None
    return path


def check_task_name(name) -> None:
    """task_name names a folder under outputs/: one plain path component, no separators or '..'."""
    text = str(name)
    if not text or text in (".", "..") or "/" in text or "\\" in text or "\0" in text:
        raise ConfigError(f"task_name={text!r} must be a plain folder name (no '/', '..' or empty)")


def _devices_ok(devices) -> bool:
    """Lightning's `devices`: a count >= 1, -1 (all), "auto", or device indices (a list, or "0,1")."""
    if isinstance(devices, str):
        text = devices.strip()
        if text == "auto":
            return True
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if not parts or not all(p.lstrip("-").isdigit() for p in parts):
            return False
        devices = [int(p) for p in parts] if "," in text else int(parts[0])
    if isinstance(devices, bool):
        return False
    if isinstance(devices, int):
        return devices >= 1 or devices == -1
    try:
        items = list(devices)
    except TypeError:
        return False
    return bool(items) and all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in items)


def check_trainer_settings(group, prefix: str = "trainer") -> None:
    """trainer.devices and trainer.num_nodes as Lightning takes them, in one line naming the key and
    value, before any work (Lightning's own message came wrapped in Hydra's, or as a traceback)."""
    group = group or {}
    if not _devices_ok(group.get("devices", 1)):
        raise ConfigError(
            f"{prefix}.devices={group.get('devices')!r}: give a number of devices >= 1, -1 (all), auto, "
            f"or device indices such as [0,1]"
        )
    nodes = group.get("num_nodes", 1)
    if isinstance(nodes, bool) or not isinstance(nodes, int) or nodes < 1:
        raise ConfigError(f"{prefix}.num_nodes={nodes!r}: give a number of nodes >= 1")


def app_experiments(app: str, config_dir: Path = CONFIG_DIR) -> list[str]:
    """The experiments of app `app` (train, estimate): configs/<app>/experiment/*.yaml."""
    return sorted(p.stem for p in (Path(config_dir) / app / "experiment").glob("*.yaml"))


def check_experiment_overrides(args: Sequence[str], app: str, config_dir: Path = CONFIG_DIR) -> None:
    """Fail early, in one line, on an experiment=NAME that is not one of this app's, naming the app that runs
    it where another one does (Hydra's own message is a page: the options and the whole search path)."""
    root = Path(config_dir)
    if not (root / app / "experiment").is_dir():  # an app without experiments: Hydra refuses the override itself
        return
    for arg in args:
        key, _, value = arg.partition("=")
        if key.lstrip("+~") != "experiment" or not value or value == "null":
            continue
        for name in (n.strip() for n in value.split(",")):
            if (root / app / "experiment" / f"{name}.yaml").is_file():
                continue
            others = sorted(p.parent.parent.name for p in root.glob(f"*/experiment/{name}.yaml"))
            what = (
                f"experiment {name!r} is a qcm-{others[0]} experiment (configs/{others[0]}/experiment/{name}.yaml): "
                f"run it with qcm-{others[0]}"
                if others
                else f"unknown experiment {name!r} (no configs/{app}/experiment/{name}.yaml)"
            )
            raise ConfigError(f"{what}; qcm-{app} experiments: {', '.join(app_experiments(app, root))}")
