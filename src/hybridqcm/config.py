"""Where the configs live and the checks every app makes of its settings before any work: the run
folder writable, task_name a plain folder name, Lightning's devices/num_nodes, an experiment that
belongs to the app asked to run it, and, for an app whose config is a structured config (a dataclass
schema registered in Hydra's ConfigStore as ``schema/<app>``: estimation/settings.py), its settings
against that schema. Each failure is one ConfigError naming the key and value.

Layout: configs/<app>.yaml is app <app>'s primary config; the groups the apps share are folders of
configs/, and configs/apps/<app>/ (on the app's search path: its `hydra.searchpath`, through the
${hybridqcm_config_dir:} resolver registered here) holds the groups of that app alone, its
experiments (configs/apps/train/experiment/, configs/apps/estimate/experiment/)."""

from __future__ import annotations

import dataclasses
import os
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

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
    """The experiments of app `app` (train, estimate): configs/apps/<app>/experiment/*.yaml."""
    return sorted(p.stem for p in (Path(config_dir) / "apps" / app / "experiment").glob("*.yaml"))


def check_experiment_overrides(args: Sequence[str], app: str, config_dir: Path = CONFIG_DIR) -> None:
    """Fail early, in one line, on an experiment=NAME that is not one of this app's, naming the app that runs
    it where another one does (Hydra's own message is a page: the options and the whole search path)."""
    root = Path(config_dir)
    if not (
        root / "apps" / app / "experiment"
    ).is_dir():  # an app without experiments: Hydra refuses the override itself
        return
    for arg in args:
        key, _, value = arg.partition("=")
        if key.lstrip("+~") != "experiment" or not value or value == "null":
            continue
        for name in (n.strip() for n in value.split(",")):
            if (root / "apps" / app / "experiment" / f"{name}.yaml").is_file():
                continue
            others = sorted(p.parent.parent.name for p in root.glob(f"apps/*/experiment/{name}.yaml"))
            what = (
                f"experiment {name!r} is a qcm-{others[0]} experiment (configs/apps/{others[0]}/experiment/{name}.yaml): "
                f"run it with qcm-{others[0]}"
                if others
                else f"unknown experiment {name!r} (no configs/apps/{app}/experiment/{name}.yaml)"
            )
            raise ConfigError(f"{what}; qcm-{app} experiments: {', '.join(app_experiments(app, root))}")


# -- settings against a dataclass schema (a structured config: hybridqcm.estimation.settings) -------------
def schema_type(schema: type, dotted: str) -> Any:
    """The annotation of `dotted` (a.b, a.b[0], a.b.key of a dict) in a dataclass schema; None where it is
    not one of its fields, Any inside an Any field."""
    node: Any = schema
    for part in dotted.replace("[", ".[").split("."):
        origin = typing.get_origin(node)
        if node is Any:
            return Any
        if origin in (list, dict):  # an element of a list, a value of a dict
            node = typing.get_args(node)[-1]
            continue
        if not dataclasses.is_dataclass(node):
            return None
        hints = typing.get_type_hints(node)
        if part not in hints:
            return None
        node = hints[part]
    return node


def _kind(annotation: Any) -> str:
    """What a value of this annotation is, for a one-line message: give true or false / a whole number ..."""
    args = typing.get_args(annotation)
    nullable = typing.get_origin(annotation) is typing.Union and type(None) in args
    if nullable:
        annotation = next(a for a in args if a is not type(None))
    words = {bool: "true or false", int: "a whole number", float: "a number", str: "a name"}
    origin = typing.get_origin(annotation)
    if origin is list:
        what = f"a list [...] of {words.get(typing.get_args(annotation)[0], 'values').removeprefix('a ')}s"
    elif origin is dict:
        what = "a mapping {key: value}"
    else:
        what = words.get(annotation, "a value")
    return what + (" or null" if nullable else "")


def _one_line(error: Exception, schema: type, values, app: str) -> ConfigError:
    """OmegaConf's error (several lines: message, full_key, object_type) as one ConfigError line."""
    from omegaconf import OmegaConf
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError

    key = str(getattr(error, "full_key", "") or "")
    value = OmegaConf.select(values, key, default=None, throw_on_resolution_failure=False) if key else None
    if isinstance(error, (ConfigKeyError, ConfigAttributeError)):
        prefix = key.rpartition(".")[0]
        parent = schema_type(schema, prefix) if prefix else schema
        known = sorted(f.name for f in dataclasses.fields(parent)) if dataclasses.is_dataclass(parent) else []
        return ConfigError(
            f"unknown setting {key}={value!r} (qcm-{app} does not use it); known under {prefix or 'the top level'}: {known}"
        )
    return ConfigError(f"{key}={value!r}: give {_kind(schema_type(schema, key))}")


def check_settings_against(schema: type, cfg, app: str) -> None:
    """A composed config of app `app` against its dataclass schema: the first unknown key or wrongly typed
    value as one ConfigError line naming the key and value (`hydra`, when composed with it, is Hydra's)."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    # plain values: a config composed against the schema may carry keys added with `+key=` (Hydra adds them)
    data = OmegaConf.to_container(cfg, resolve=False) if isinstance(cfg, DictConfig) else dict(cfg)
    values = OmegaConf.create({k: v for k, v in data.items() if k != "hydra"})
    try:
        OmegaConf.merge(OmegaConf.structured(schema), values)
    except OmegaConfBaseException as error:
        raise _one_line(error, schema, values, app) from None


def _groups(app: str, config_dir: Path) -> set[str]:
    """The config groups configs/<app>.yaml's defaults list names (experiment, solver, hydra, ...)."""
    import yaml

    data = yaml.safe_load((Path(config_dir) / f"{app}.yaml").read_text()) or {}
    return {
        str(next(iter(entry))).split("@")[0].removeprefix("override ").removeprefix("optional ").strip()
        for entry in data.get("defaults") or []
        if isinstance(entry, dict)
    }


def check_overrides_against(schema: type, args: Sequence[str], app: str, config_dir: Path = CONFIG_DIR) -> None:
    """The command line's overrides of app `app` (configs/<app>.yaml) against its dataclass schema, before
    Hydra composes: a key the schema lacks (not added with `+`) or a value of the wrong type, each element
    of a sweep `a=1,2` too, is one ConfigError line naming the key and value (Hydra's is a page)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import ChoiceSweep
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    groups = _groups(app, config_dir)
    for arg in args:
        try:
            (override,) = OverridesParser.create().parse_overrides([arg])
        except HydraException:
            continue  # not an override (a flag such as --cfg): Hydra's to judge
        key = override.key_or_group
        top = key.split(".")[0].split("[")[0]
        if override.is_delete() or override.package is not None or top in groups or top.startswith("hydra"):
            continue
        if schema_type(schema, key) is None and override.is_add():
            continue  # a new key: `check_settings_against` names it after composing
        value = override.value()
        choices = value.list if isinstance(value, ChoiceSweep) else [] if override.is_sweep_override() else [value]
        for choice in choices:
            if isinstance(choice, str) and "${" in choice:
                continue  # an interpolation: typed when resolved
            values = OmegaConf.create()
            OmegaConf.update(values, key, choice, force_add=True)
            check_settings_against(schema, values, app)


def check_schema_overrides(args: Sequence[str], app: str, config_dir: Path = CONFIG_DIR) -> None:
    """`check_overrides_against` with the schema app `app` registered in Hydra's ConfigStore as
    ``schema/<app>`` (configs/<app>.yaml's defaults list names it); nothing to check without one."""
    from hydra.core.config_store import ConfigStore
    from hydra.plugins.config_source import ConfigLoadError
    from omegaconf import OmegaConf

    try:
        node = ConfigStore.instance().load(f"schema/{app}.yaml")
    except ConfigLoadError:  # no schema registered for this app
        return
    check_overrides_against(OmegaConf.get_type(node.node), args, app, config_dir)
