"""qcm-estimate's networks: the checkpoints a plan needs, loaded once through the safe loader and checked
against the experiment, the observed channels, each other and the file (estimation/plan.py composes them).
"""

from __future__ import annotations

from hybridqcm.errors import ConfigError


def network_plan(cfg, observed: list[str], stages: list[dict]) -> tuple[dict, bool]:
    """The checkpoints: present, readable, of the right kind, and the ones the experiment needs; loaded
    once, through the one safe loader (models.checkpoint: weights_only, allow-list, strict keys).
    Returns ({key: network}, completes: a U-Net completes the unobserved a2, a1)."""
    from hybridqcm.errors import CheckpointError
    from hybridqcm.models.checkpoint import load_checkpoint
    from hybridqcm.physics.parameters import CHANNELS

    networks = {}
    for key, kind in {"cnn_ckpt": "cnn", "unet_ckpt": "unet", "cae_ckpt": "cae"}.items():
        if cfg.get(key):
            try:
                networks[key] = load_checkpoint(cfg[key], kind, key)
            except CheckpointError as error:
                raise ConfigError(str(error)) from None
    if cfg.init.cnn and not cfg.cnn_ckpt:
        raise ConfigError(
            f"experiment {cfg.experiment_name} initialises p1, p2 with the CNN: give cnn_ckpt=PATH "
            f"(or init.cnn=false for a random init)"
        )
    completes = bool(cfg.unet_ckpt) and not {"a2", "a1"} <= set(observed)
    if cfg.init.equation_error and not (completes or set(observed) == set(CHANNELS)):
        raise ConfigError(
            f"init.equation_error needs all three accelerations: observe them or give unet_ckpt=PATH "
            f"(observed={observed})"
        )
    for stage in stages:  # explicit channel lists must be measured or completed
        if not isinstance(stage["channels"], str):
            available = set(observed) | ({"a2", "a1"} if completes else set())
            missing = [c for c in stage["channels"] if c not in available]
            if missing:
                raise ConfigError(
                    f"stage {stage['name']!r} uses channels {missing}, which are neither observed "
                    f"(observed={observed}) nor completed by a U-Net"
                )
        elif stage["channels"] not in ("all", "observed"):
            raise ConfigError(f"stage {stage['name']!r}: channels={stage['channels']!r}; use all, observed or a list")
    if cfg.init.cnn and "a2" not in observed and not completes and not cfg.cnn_a2_from_file:
        raise ConfigError(
            "the CNN initialiser reads a2, which is not observed: give unet_ckpt=PATH to complete it "
            "(or cnn_a2_from_file=true to use the file's a2 for the initial guess only)"
        )
    if cfg.cae_ckpt and "a2" not in observed and not completes:
        raise ConfigError("cae_ckpt denoises (a3, a2) but a2 is neither observed nor completed (give unet_ckpt)")
    return networks, completes


def network_windows(cfg, networks: dict, data: dict, n_steps: int) -> tuple[dict, int]:
    """The networks checked against each other and the file's period, the CNN prior against the CNN;
    ({key: window}, the steps a recording must hold: n_steps, or the CNN's window if longer)."""
    from hybridqcm.errors import CheckpointError, DatasetError
    from hybridqcm.estimation.front import check_networks
    from hybridqcm.estimation.fusion import check_cnn_prior

    cnn = networks.get("cnn_ckpt") if cfg.init.cnn else None
    try:
        check_networks(cnn, networks.get("unet_ckpt"), networks.get("cae_ckpt"), data["h"] or 0.01)
    except CheckpointError as error:
        raise ConfigError(str(error)) from None
    try:  # init.cnn_prior=network: the CNN must predict its variance (estimation/fusion.py)
        check_cnn_prior(cfg.init.get("cnn_prior"), cnn, cfg.init.get("cnn_prior_rel_std"))
    except ValueError as error:
        raise ConfigError(str(error)) from None
    needed = n_steps
    windows = {}
    for key in ("cnn_ckpt", "unet_ckpt", "cae_ckpt"):
        if key in networks and (key != "cnn_ckpt" or cfg.init.cnn):
            windows[key] = int(networks[key].hparams.window)
    if cfg.init.cnn:
        needed = max(needed, windows.get("cnn_ckpt", n_steps))
    if needed > data["stored"]:
        what = "n_steps" if needed == n_steps else f"the CNN window ({needed})"
        raise DatasetError(
            f"{data['path']}: {what} = {needed} steps but /{data['split']}/accel stores {data['stored']} steps"
        )
    return windows, needed


__all__ = ["network_plan", "network_windows"]
