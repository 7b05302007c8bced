"""QCMModule: what every LightningModule of ours shares, and the checkpoint facts below the loader.

Every module takes raw physical inputs and normalises them itself with buffers that are part
of its state_dict, so a loaded checkpoint gives a model that accepts raw data. Network,
optimizer and scheduler arrive as plain config dicts (`_target_`, optimizer/scheduler with
`_partial_: true`) and are kept in hparams (plain containers: the safe loader reads them as data).

Normalisation (the system is linear, so a trajectory scaled by c is the same system at a
rougher road): inputs are divided per sample by the RMS of one reference channel
(`scale_channel`), then standardised per channel with statistics of training samples
(buffers in_mean/in_std [C_in]); outputs are de-standardised with out_mean/out_std [C_out].

Validation and test share one loop: `_eval_step(batch, stage)` gives a per-batch record,
`_update_statistics` accumulates the epoch's statistics, `_summarise(records, stage)` logs them
and returns the epoch's results (kept as `test_results` after a test run, for the artefacts).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from hydra.utils import instantiate
from lightning import LightningModule
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, ListConfig, OmegaConf
from torch import Tensor

from hybridqcm.errors import CheckpointError
from hybridqcm.models.networks import NETWORKS
from hybridqcm.models.physics_losses import rms
from hybridqcm.models.schedule import one_cycle_lr, run_progress
from hybridqcm.models.untrusted import check_config_tree

DEFAULT_OPTIMIZER = {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-3}


def _plain(value: Any) -> Any:
    """DictConfig/ListConfig -> plain containers (checkpoint hparams stay readable without OmegaConf)."""
    if isinstance(value, (DictConfig, ListConfig)):
        return OmegaConf.to_container(value, resolve=True)
    if isinstance(value, tuple):
        return list(value)
    return value


def build_network(net_cfg: Mapping, overrides: Mapping | None = None) -> torch.nn.Module:
    """The network of a module from its config {_target_: one of networks.NETWORKS, **kwargs}.

    Built without Hydra: the target must name one of our network classes and no value may hold
    another `_target_`, so hyper-parameters read from a checkpoint can never construct anything else."""

    cfg = dict(net_cfg)
    target = cfg.pop("_target_", None)
    if target not in NETWORKS:
        raise CheckpointError(f"net._target_ = {target!r} is not one of our networks {sorted(NETWORKS)}")
    check_config_tree(cfg, "net", "net")
    if "_partial_" in cfg:
        raise CheckpointError("net._partial_ is not allowed: the network is built once, with its sizes")
    cfg.update(dict(overrides or {}))
    return NETWORKS[target](**cfg)


class QCMModule(LightningModule):
    """Shared plumbing: configurable net/optimizer, normalisation buffers, lr schedule, eval loop, checkpoints."""

    default_net: dict = {}
    kind = "base"

    def _setup_common(self, net: Mapping | None, n_in: int, n_out: int, net_overrides: Mapping | None = None) -> None:
        net_cfg = dict(self.default_net)
        net_cfg.update(dict(net or {}))
        self.net = build_network(net_cfg, net_overrides)
        self.register_buffer("in_mean", torch.zeros(n_in))
        self.register_buffer("in_std", torch.ones(n_in))
        self.register_buffer("out_mean", torch.zeros(n_out))
        self.register_buffer("out_std", torch.ones(n_out))
        self.register_buffer("norm_fitted", torch.tensor(False))
        self._train_start_time: float | None = None
        self._val_records: list[dict] = []
        self._test_records: list[dict] = []
        self.test_results: dict[str, Tensor] | None = None

    # -- data contract ----------------------------------------------------------------------------
    def data_requirements(self) -> dict:
        """Channels and window the datamodule must provide (inputs, targets, aux, window, targets_optional).

        By default hparams input_channels -> target_channels, labels required, no aux channels."""
        return self._requirements(self.hparams.input_channels, self.hparams.target_channels)

    def _requirements(
        self, inputs: Sequence[str], targets: Sequence[str], aux: Sequence[str] = (), targets_optional: bool = False
    ) -> dict:
        return {
            "inputs": list(inputs),
            "targets": list(targets),
            "aux": list(aux),
            "window": int(self.hparams.window),
            "targets_optional": targets_optional,
        }

    # -- normalisation ------------------------------------------------------------------------------
    def _scale(self, x: Tensor) -> Tensor:
        """Per-sample scale [B, 1, 1] (RMS of the reference channel), or ones."""
        c = self.hparams.get("scale_channel")
        if c is None:
            return torch.ones(x.shape[0], 1, 1, dtype=x.dtype, device=x.device)
        return rms(x[:, c]).clamp_min(1e-12)[:, None, None]

    def _standardise_in(self, x: Tensor, scale: Tensor) -> Tensor:
        return (x / scale - self.in_mean[:, None]) / self.in_std[:, None]

    @torch.no_grad()
    def fit_normalisation(self, batch: Mapping[str, Tensor]) -> None:
        """Set the normalisation buffers from a batch of clean training samples (raw units)."""
        x = batch["x"][..., : self._window(batch["x"])].to(self.in_mean.device, torch.float64)
        xs = x / self._scale(x)
        self.in_mean.copy_(xs.mean((0, 2)))
        self.in_std.copy_(xs.std((0, 2)).clamp_min(1e-8))
        self._fit_output_normalisation(batch, self._scale(x))
        self.norm_fitted.fill_(True)

    def _fit_output_normalisation(self, batch: Mapping[str, Tensor], scale: Tensor) -> None:
        raise NotImplementedError

    def _window(self, x: Tensor) -> int:
        return x.shape[-1]

    def on_fit_start(self) -> None:
        if not bool(self.norm_fitted):
            datamodule = getattr(self.trainer, "datamodule", None)
            if datamodule is None or not hasattr(datamodule, "stats_batch"):
                raise RuntimeError(
                    f"{type(self).__name__}: normalisation not fitted and no datamodule with stats_batch()"
                )
            self.fit_normalisation(datamodule.stats_batch())

    # -- optimisation -------------------------------------------------------------------------------
    def configure_optimizers(self) -> Any:

        # hparams may come from a checkpoint: only torch optimizers / schedulers are instantiated.
        check_config_tree({k: self.hparams.get(k) for k in ("optimizer", "scheduler")}, type(self).__name__)
        optimizer = instantiate(self.hparams.get("optimizer") or DEFAULT_OPTIMIZER)(params=self.parameters())
        schedule = self.hparams.get("lr_schedule")
        if schedule:
            for group in optimizer.param_groups:
                group["lr"] = one_cycle_lr(0.0, **schedule)
        scheduler_cfg = self.hparams.get("scheduler")
        if not scheduler_cfg or schedule:
            return optimizer
        factory = instantiate(scheduler_cfg)
        func = getattr(factory, "func", factory)
        if func is torch.optim.lr_scheduler.OneCycleLR:
            scheduler = factory(optimizer=optimizer, total_steps=int(self.trainer.estimated_stepping_batches))
            return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
        scheduler = factory(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "monitor": "val/loss", "interval": "epoch"},
        }

    def on_train_start(self) -> None:
        self._train_start_time = time.monotonic()

    def on_train_batch_start(self, batch: Any, batch_idx: int) -> None:
        schedule = self.hparams.get("lr_schedule")
        if schedule:
            lr = one_cycle_lr(run_progress(self.trainer, self._train_start_time), **schedule)
            for optimizer in self.trainer.optimizers:
                for group in optimizer.param_groups:
                    group["lr"] = lr
            self.log("lr", lr, on_step=True, on_epoch=False)

    # -- validation and test: per-batch records, summarised once per epoch ----------------------------
    def _eval_step(self, batch: Mapping[str, Tensor], stage: str) -> dict:
        """One batch's record (tensors on the CPU); logs the batch loss under `{stage}/loss`."""
        raise NotImplementedError

    def _summarise(self, records: list[dict], stage: str) -> dict[str, Any]:
        """Log the epoch's statistics under `{stage}/...` and return the epoch's results."""
        raise NotImplementedError

    def _update_statistics(self, record: dict, stage: str) -> None:
        """Accumulate epoch statistics from one batch's record (none by default)."""

    def _reset_statistics(self, stage: str) -> None:
        """Forget the statistics accumulated for ``stage`` (none by default)."""

    def _plot_validation(self, summary: Mapping[str, Any]) -> None:
        """Figures of a validation epoch for TensorBoard (none by default)."""

    def _record(self, batch: Mapping[str, Tensor], stage: str) -> dict:
        record = self._eval_step(batch, stage)
        self._update_statistics(record, stage)
        return record

    def validation_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> None:
        self._val_records.append(self._record(batch, "val"))

    def test_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> None:
        self._test_records.append(self._record(batch, "test"))

    def on_validation_epoch_end(self) -> None:
        summary = self._summarise(self._val_records, "val")
        self._val_records = []
        every = int(self.hparams.get("plot_every_n_epochs") or 0)
        if (
            summary
            and every > 0
            and not self.trainer.sanity_checking
            and self.current_epoch % every == 0
            and self._tensorboard() is not None
        ):
            self._plot_validation(summary)

    def on_test_epoch_start(self) -> None:
        self._test_records = []
        self._reset_statistics("test")

    def on_test_epoch_end(self) -> None:
        self.test_results = self._summarise(self._test_records, "test")
        self._test_records = []

    # -- checkpoints ----------------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # The class name, not its module path: files stay loadable when the code moves.
        checkpoint["hybridqcm_class"] = type(self).__name__
        # An attached (inference-only) denoiser is not part of this model.
        for key in [k for k in checkpoint.get("state_dict", {}) if k.startswith("denoiser.")]:
            del checkpoint["state_dict"][key]

    def check_physics(self) -> None:
        if self.hparams.get("physics", "euler") not in ("euler", "continuous"):
            raise ValueError(f"physics must be 'euler' or 'continuous', got {self.hparams.get('physics')!r}")
        if not float(self.hparams.get("h", 0.01)) > 0:
            raise ValueError(f"h must be > 0, got {self.hparams.get('h')!r}")

    # -- logging helpers --------------------------------------------------------------------------------
    def _tensorboard(self):
        for logger in self.loggers:
            if isinstance(logger, TensorBoardLogger):
                return logger.experiment
        return None

    def _add_figure(self, tag: str, fig) -> None:
        from hybridqcm.plots import close  # matplotlib is imported only when a figure is drawn

        writer = self._tensorboard()
        if writer is not None:
            writer.add_figure(tag, fig, global_step=self.global_step)
        close(fig)


__all__ = [
    "DEFAULT_OPTIMIZER",
    "QCMModule",
    "build_network",
]
