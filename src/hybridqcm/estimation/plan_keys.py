"""qcm-estimate's hand-parsed settings checks: keys it does not know, and values of the wrong type.

The known keys and their types are read from configs/estimate.yaml and the estimation experiments
(task: estimate); a key or type outside them is one ConfigError line naming key and value.
"""

from __future__ import annotations

from hybridqcm.config import CONFIG_DIR
from hybridqcm.errors import ConfigError


def _known_key_tree() -> dict:
    """Keys qcm-estimate understands: configs/estimate.yaml plus what its experiments and solvers set."""
    import yaml

    def merge(into: dict, data) -> None:
        for k, v in (data or {}).items():
            if isinstance(v, dict) and isinstance(into.get(k, {}), dict):
                merge(into.setdefault(k, {}), v)
            else:
                into.setdefault(k, None)

    tree: dict = {}
    merge(tree, yaml.safe_load((CONFIG_DIR / "estimate.yaml").read_text()))
    for path in sorted((CONFIG_DIR / "experiment").glob("*.yaml")):
        data = yaml.safe_load(path.read_text()) or {}
        if isinstance(data, dict) and data.get("task") == "estimate":
            merge(tree, data)
    for group in ("paths", "hydra", "solver", "experiment", "sensor", "trainer"):
        tree[group] = None  # groups: their own schemas (checked by solver_settings and build_sensor)
    return tree


# Mappings whose entries are free-form (GN stage lists, vehicle constants are checked where used).
_OPEN_KEYS = ("stages", "vehicle", "defaults")


def check_known_keys(cfg) -> None:
    """Refuse keys qcm-estimate does not know (e.g. `+data.pathh=x`, which would otherwise be ignored)."""
    from omegaconf import DictConfig

    def walk(node, tree, prefix: str) -> None:
        for key in node.keys():
            name = f"{prefix}{key}"
            if key not in tree:
                raise ConfigError(
                    f"unknown setting {name}={node[key]!r} (qcm-estimate does not use it); "
                    f"known under {prefix or 'the top level'}: {sorted(tree)}"
                )
            sub = tree[key]
            if isinstance(sub, dict) and key not in _OPEN_KEYS and isinstance(node[key], DictConfig):
                walk(node[key], sub, f"{name}.")

    walk(cfg, _known_key_tree(), "")


_NULLABLE = ("misfit_peer_factor", "skip_windows.clip_samples", "vehicle_prior.rel_std")


def _setting_types() -> dict[str, set[str]]:
    """{dotted key: type names of its values} in estimate.yaml and the estimation experiments."""
    import yaml

    types: dict[str, set[str]] = {"n_samples": {"int", "NoneType"}}  # null by default: all samples
    for key in _NULLABLE:  # documented "null: off" with a number by default
        types.setdefault(key, set()).add("NoneType")

    def walk(data, prefix: str = "") -> None:
        for key, value in (data or {}).items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}.")
            else:
                types.setdefault(f"{prefix}{key}", set()).add(type(value).__name__)

    walk(yaml.safe_load((CONFIG_DIR / "estimate.yaml").read_text()))
    for path in sorted((CONFIG_DIR / "experiment").glob("*.yaml")):
        data = yaml.safe_load(path.read_text()) or {}
        if isinstance(data, dict) and data.get("task") == "estimate":
            walk(data)
    return types


def check_setting_types(cfg, own: tuple[str, ...] = ()) -> None:
    """A number or a switch given as something else (`n_samples=abc`, `plots=maybe`): one line naming
    key and value, before any work. The type is the one every default of the key has; ``own``: keys the
    caller checks itself (the vehicle's init.equation_error also takes `seats`)."""
    from omegaconf import OmegaConf

    for key, names in _setting_types().items():
        if key in own:
            continue
        value = OmegaConf.select(cfg, key, default=None)
        if value is None and "NoneType" in names:
            continue
        kinds = names - {"NoneType"}
        if kinds == {"bool"} and not isinstance(value, bool):
            raise ConfigError(f"{key}={value!r}: give true or false")
        numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
        if kinds == {"int"} and not (numeric and isinstance(value, int)):
            raise ConfigError(f"{key}={value!r}: give a whole number" + (" or null" if "NoneType" in names else ""))
        if kinds and kinds <= {"int", "float"} and not numeric:
            raise ConfigError(f"{key}={value!r}: give a number" + (" or null" if "NoneType" in names else ""))


__all__ = ["check_known_keys", "check_setting_types"]
