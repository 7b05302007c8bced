"""Training and testing one network of the project (qcm-train's work, usable from Python).

    cfg = compose("train", overrides=["experiment=exp2_physics", "data.path=FILE"])
    metrics = train(cfg)            # checks every input (prepare), fits, tests, writes the run folder

`prepare` builds the model (or loads it from ckpt_path, class-checked) and the datamodule with every
user-input check first: a bad setting is one ConfigError naming the key, before any training step.
Run folder (cfg.paths.output_dir): checkpoints/, tensorboard/, test_metrics.json and the test
artefacts of reports/train.py.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Mapping
from pathlib import Path

import yaml

from hybridqcm import config, runfolder
from hybridqcm.atomic import atomic_write_text
from hybridqcm.config import CONFIG_DIR
from hybridqcm.errors import ConfigError, HybridQCMError

log = logging.getLogger("qcm-train")


def build_datamodule(data_cfg: Mapping, requirements: Mapping, train: bool):
    """Instantiate the datamodule with the channels/window the model needs (config values are checked against them)."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    cfg = OmegaConf.to_container(data_cfg, resolve=True) if not isinstance(data_cfg, dict) else dict(data_cfg)
    for key in ("inputs", "targets", "aux"):
        given = cfg.get(key)
        if given is None:
            cfg[key] = list(requirements[key])
        elif list(given) != list(requirements[key]):
            raise ConfigError(f"data.{key} = {list(given)} but the model needs {list(requirements[key])}")
    window = cfg.get("window")
    if window is None:
        cfg["window"] = int(requirements["window"])
    elif int(window) < int(requirements["window"]):
        raise ConfigError(f"data.window = {window} is shorter than the model's window {requirements['window']}")
    cfg["targets_optional"] = bool(requirements.get("targets_optional")) or not train
    if not train and cfg["aux"] and not _split_has(cfg.get("path"), cfg.get("test_split"), cfg["aux"]):
        # Evaluation reads the network's inputs and the labels; the auxiliaries only add the training
        # loss, and a logger's or another simulator's file stores no velocities or displacements.
        log.warning(
            "%s: /%s has no %s (the training loss's auxiliary channels): testing without that loss",
            cfg["path"],
            cfg["test_split"],
            cfg["aux"],
        )
        cfg["aux"] = []
    return instantiate(cfg, _convert_="all")


def _split_has(path, split, channels) -> bool:
    """Whether an HDF5 file's split stores every dataset these channels read (True where there is no
    file to ask: a streaming datamodule simulates them)."""
    if not path or not split or not Path(str(path)).is_file():
        return True
    from hybridqcm.data.channels import required_keys
    from hybridqcm.data.hdf5 import dataset_info
    from hybridqcm.errors import DatasetError

    try:
        stored = dataset_info(path)["splits"].get(str(split))
    except (DatasetError, OSError):
        return True  # the datamodule's own check reports an unreadable file, naming it
    return stored is None or required_keys(channels) <= set(stored["keys"])


def load_model(cfg, train: bool):
    """The model: instantiated from cfg.model, or loaded (and class-checked) from cfg.ckpt_path for evaluation."""
    from hydra.utils import get_class, instantiate

    from hybridqcm.models.checkpoint import MODULES, load_module

    model_cls = get_class(cfg.model._target_)
    if model_cls.__name__ not in MODULES:
        raise ConfigError(
            f"model._target_ = {cfg.model._target_!r} is not one of the project's models {sorted(MODULES)}"
        )
    if cfg.get("ckpt_path"):
        # The one safe loader: weights_only, allow-listed classes/targets, strict state_dict.
        checked = load_module(str(cfg.ckpt_path), model_cls)
        if not train:
            return checked
    return instantiate(cfg.model)


def record_data_step(model, datamodule) -> None:
    """Store the data's step h in the model's hparams (saved in its checkpoints, checked by the estimator)."""
    simulator = getattr(datamodule, "simulator", None)
    h = getattr(simulator, "h", None)
    path = getattr(datamodule, "path", None)
    if h is None and path:
        from hybridqcm.data.hdf5 import dataset_info

        h = dataset_info(path)["attrs"].get("h")
    if h is not None:
        model.hparams["h"] = float(h)


def check_top_level_keys(cfg, config_dir: Path = CONFIG_DIR) -> None:
    """Refuse top-level keys qcm-train does not know (e.g. `+foo=1`, otherwise silently ignored).

    Known: configs/train.yaml's keys and groups, and what the training experiments, searches and debug configs set."""
    known = set(yaml.safe_load((config_dir / "train.yaml").read_text()) or {})
    for entry in (yaml.safe_load((config_dir / "train.yaml").read_text()) or {}).get("defaults", []):
        known |= set(entry) if isinstance(entry, dict) else {str(entry)}
    for folder in ("apps/train/experiment", "hparams_search", "debug", "launcher"):
        for path in (config_dir / folder).glob("*.yaml"):
            data = yaml.safe_load(path.read_text()) or {}
            if isinstance(data, dict):
                known |= set(data)
    unknown = sorted(str(k) for k in cfg.keys() if k not in known)
    if unknown:
        raise ConfigError(f"unknown setting {unknown[0]}={cfg[unknown[0]]!r} (qcm-train does not use it)")


def check_logger_callbacks(cfg) -> None:
    """Callbacks that need a logger (LearningRateMonitor) with logger=none: one line, before any work."""
    callbacks = cfg.get("callbacks") or {}
    loggers = [c for c in (cfg.get("logger") or {}).values() if c is not None and "_target_" in c]
    needs = [
        name
        for name, c in callbacks.items()
        if c is not None and str(c.get("_target_", "")).endswith("LearningRateMonitor")
    ]
    if needs and not loggers:
        raise ConfigError(
            f"callbacks.{needs[0]} (LearningRateMonitor) needs a logger, but logger=none; "
            f"add ~callbacks.{needs[0]} or choose logger=tensorboard"
        )


def check_optimizer(model_cfg) -> None:
    """model.optimizer's settings, tried on a dummy parameter now (the module builds the optimizer only
    when training starts): `lr=abc` or `lr=-1` is one line naming the key, not a TypeError mid-fit."""
    import torch
    from hydra.utils import instantiate

    optimizer = (model_cfg or {}).get("optimizer")
    if not optimizer:
        return
    for key, value in optimizer.items():
        if not str(key).startswith("_") and isinstance(value, str):
            raise ConfigError(f"model.optimizer.{key}={value!r}: give a number")
    try:
        instantiate(optimizer)([torch.nn.Parameter(torch.zeros(1))])
    except Exception as error:  # the optimizer's own check (torch: "Invalid learning rate: -1.0")
        cause = error.__cause__ or error
        raise ConfigError(f"model.optimizer ({optimizer.get('_target_')}): {cause}") from None


def _instantiate_group(group: Mapping | None) -> list:
    from hydra.utils import instantiate

    if not group:
        return []
    return [instantiate(c) for c in group.values() if c is not None and "_target_" in c]


def user_errors() -> tuple[type[BaseException], ...]:
    """The exceptions that mean bad user input (prepare turns them into one-line ConfigErrors)."""
    from hydra.errors import InstantiationException

    from hybridqcm.errors import CheckpointError, DatasetError

    return (
        HybridQCMError,
        ConfigError,
        DatasetError,
        CheckpointError,
        FileNotFoundError,
        InstantiationException,
        ValueError,
        KeyError,
    )


def prepare(cfg) -> dict:
    """Everything up to the trainer, with all user-input checks; any bad input raises ConfigError."""
    try:
        return _prepare(cfg)
    except user_errors() as error:
        if isinstance(error, ConfigError):
            raise
        message = str(error)
        cause = error.__cause__ or error.__context__
        if type(error).__name__ == "InstantiationException" and cause is not None:
            message = f"{message} ({type(cause).__name__}: {cause})" if str(cause) not in message else message
        raise ConfigError(message) from error


def _prepare(cfg) -> dict:
    import torch

    train, test = bool(cfg.get("train", True)), bool(cfg.get("test", True))
    if not train and not cfg.get("ckpt_path"):
        raise ConfigError("train=false needs ckpt_path=CKPT (the checkpoint to evaluate)")
    if not train and not test:
        raise ConfigError("train=false test=false leaves nothing to do")
    if cfg.get("denoiser_ckpt") and train:
        raise ConfigError("denoiser_ckpt applies at evaluation: use it with train=false ckpt_path=CKPT")
    if cfg.get("float32_matmul_precision"):
        torch.set_float32_matmul_precision(str(cfg.float32_matmul_precision))
    from hybridqcm.tracking import check_logger_packages

    check_logger_packages(cfg.get("logger"))  # a missing optional logger package fails now, naming its extra

    check_top_level_keys(cfg)
    check_logger_callbacks(cfg)
    config.check_trainer_settings(cfg.get("trainer"))
    check_optimizer(cfg.get("model"))
    model = load_model(cfg, train)
    if cfg.get("denoiser_ckpt"):
        from hybridqcm.models import DenoisingAutoencoder
        from hybridqcm.models.checkpoint import load_module

        if not hasattr(model, "attach_denoiser"):
            raise ConfigError(
                f"denoiser_ckpt given, but {type(model).__name__} takes no denoiser (only the parameter CNNs do)"
            )
        model.attach_denoiser(load_module(str(cfg.denoiser_ckpt), DenoisingAutoencoder))
    datamodule = build_datamodule(cfg.data, model.data_requirements(), train)
    stages = (["fit"] if train else []) + (["test"] if test else [])
    datamodule.check(stages)  # file/split/key/window errors now, not after training
    if train:
        record_data_step(model, datamodule)
        if model.hparams.get("init_from") and not cfg.get("ckpt_path"):  # fine-tune a trained CNN (exp13)
            from hybridqcm.models.checkpoint import warm_start

            warm_start(model)
    return {"model": model, "datamodule": datamodule, "train": train, "test": test}


def train(cfg) -> dict[str, float]:
    """Train and/or test per `cfg`; returns the metrics (validation and test) as floats."""
    import lightning as L
    from hydra.utils import instantiate

    L.seed_everything(int(cfg.get("seed", 0)), workers=True)
    config.check_task_name(cfg.get("task_name", "train"))
    parts = prepare(cfg)
    model, datamodule = parts["model"], parts["datamodule"]
    out_dir = config.check_writable_dir(Path(cfg.paths.output_dir))
    runfolder.prepare_run_dir(
        out_dir,
        runfolder.TRAIN_ARTEFACTS,
        bool(cfg.get("overwrite", False)),
        runfolder.TRAIN_GLOBS,
        inputs=[cfg.get("ckpt_path"), cfg.get("denoiser_ckpt")],
        scratch=runfolder.TRAIN_SCRATCH,
    )

    callbacks = _instantiate_group(cfg.get("callbacks"))
    loggers = _instantiate_group(cfg.get("logger"))
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)

    metrics: dict[str, float] = {}
    train_seconds = None
    if parts["train"]:
        start = time.perf_counter()
        trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"), weights_only=True)
        train_seconds = time.perf_counter() - start
        metrics.update({k: float(v) for k, v in trainer.callback_metrics.items()})
        log.info("training took %.1f s (%d steps)", train_seconds, trainer.global_step)

    if parts["test"]:
        checkpoint = None
        if (
            parts["train"]
            and trainer.checkpoint_callback is not None
            and getattr(trainer.checkpoint_callback, "best_model_path", "")
        ):
            checkpoint = trainer.checkpoint_callback.best_model_path
        tester = trainer
        if trainer.world_size > 1:
            # Spawned ranks keep their test outputs to themselves: test once, in this process, on one device.
            tester = instantiate(
                cfg.trainer, devices=1, num_nodes=1, strategy="auto", callbacks=[], logger=loggers or False
            )
        results = tester.test(model, datamodule=datamodule, ckpt_path=checkpoint, weights_only=True)
        test_metrics = {k: float(v) for k, v in (results[0] if results else {}).items()}
        metrics.update(test_metrics)
        from hybridqcm.tracking import hparams_of, log_test_hparams

        log_test_hparams(loggers, hparams_of(cfg), test_metrics)  # TensorBoard HPARAMS: this run's row
        from hybridqcm.reports.train import write_test_outputs

        write_test_outputs(model, out_dir, tester)
        summary = {
            "task_name": cfg.get("task_name"),
            "model": type(model).__name__,
            "train": parts["train"],
            "train_seconds": train_seconds,
            "steps": trainer.global_step,
            "tested_checkpoint": checkpoint or cfg.get("ckpt_path"),
            "denoiser_ckpt": cfg.get("denoiser_ckpt"),
            "noise_sigma": getattr(datamodule, "noise_sigma", None),
            "sensor": dataclasses.asdict(datamodule.sensor)
            if getattr(datamodule, "sensor", None) is not None
            else None,
            "data_path": getattr(datamodule, "path", None) and str(datamodule.path),
            "n_test": int(len(datamodule.data_test)) if datamodule.data_test is not None else None,
            "device": str(tester.strategy.root_device),  # not model.device: test() leaves the model on the CPU
            "metrics": test_metrics,
        }
        atomic_write_text(out_dir / "test_metrics.json", json.dumps(summary, indent=2, default=str) + "\n")
    if trainer.global_rank == 0:
        runfolder.write_completion_marker(
            out_dir,
            "qcm-train",
            runfolder.task_overrides(),
            [getattr(datamodule, "path", None), cfg.get("ckpt_path"), cfg.get("denoiser_ckpt")],
        )
    return metrics
