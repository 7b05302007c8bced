"""LightningModules: parameter CNNs (labelled, physics-residual), CAE denoiser, completion U-Net.

Every module takes raw physical inputs and normalises them itself with buffers that are part
of its state_dict, so `Class.load_from_checkpoint(path, map_location="cpu")` gives a model that
accepts raw data. Network, optimizer and scheduler arrive as plain config dicts
(`_target_`, optimizer/scheduler with `_partial_: true`) and are kept in hparams.

Normalisation (the system is linear, so a trajectory scaled by c is the same system at a
rougher road): inputs are divided per sample by the RMS of one reference channel
(`scale_channel`), then standardised per channel with statistics of training samples;
time-series outputs are de-standardised and multiplied back by the same per-sample scale;
parameter outputs are log-parameters, standardised.

Inference API (used by the hybrid estimator):
    LabelledEstimator / PhysicsResidualEstimator .estimate(a3 [B,N], a2 [B,N]) -> [B, 2] (p1, p2) float64
    DenoisingAutoencoder .denoise(x [B, 2, N]) -> [B, 2, N]   channels (a3, a2)
    CompletionUNet       .complete(a3 [B,N], pu_u [B,N]) -> [B, 2, N]   channels (a2, a1)
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from hydra.utils import instantiate
from lightning import LightningModule
from omegaconf import DictConfig, ListConfig, OmegaConf
from torch import Tensor

from hybridqcm.data.datamodules import apply_noise
from hybridqcm.errors import CheckpointError
from hybridqcm.models.networks import NETWORKS
from hybridqcm.models.uncertainty import calibration_rows, clamp_log_var, gaussian_nll
from hybridqcm.models.untrusted import check_config_tree, read_stored_class

DEFAULT_OPTIMIZER = {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-3}


def _plain(value: Any) -> Any:
    """DictConfig/ListConfig -> plain containers (checkpoint hparams stay readable without OmegaConf)."""
    if isinstance(value, (DictConfig, ListConfig)):
        return OmegaConf.to_container(value, resolve=True)
    if isinstance(value, tuple):
        return list(value)
    return value


def rms(x: Tensor, dim: int = -1) -> Tensor:
    return x.pow(2).mean(dim).sqrt()


def physics_residual(p12: Tensor, aux: Tensor) -> Tensor:
    """Occupant equation residual r = a3 - ã3 [B, N], ã3 = -p1 (v3 - v2) - p2 (q3 - q2).

    p12: [B, 2] (p1, p2); aux: [B, 5, N] channels (a3, v3, v2, q3, q2). Zero for the true p
    on clean data (the stored triple satisfies the equation of motion at every step).
    """
    a3, v3, v2, q3, q2 = aux.unbind(1)
    return a3 + p12[:, :1] * (v3 - v2) + p12[:, 1:2] * (q3 - q2)


def physics_residual_loss(p12: Tensor, aux: Tensor, eps: float = 1e-30) -> Tensor:
    """Per-sample relative residual energy sum_k r_k^2 / sum_k a3_k^2 [B].

    Dividing by the sample's own a3 energy makes samples of every road class (amplitudes
    differ by 4x per class) count alike; the minimiser per sample is unchanged.
    """
    r = physics_residual(p12, aux)
    return r.pow(2).sum(-1) / aux[:, 0].pow(2).sum(-1).clamp_min(eps)


def balanced_residual_loss(p12: Tensor, aux: Tensor, eps: float = 1e-30) -> Tensor:
    """The residual in preconditioned parameter coordinates [B] (no labels needed).

    On clean data the residual is linear in p: r(p̂) = -sum_j A_j (p̂_j - p*_j) with columns
    A_1 = -(v3 - v2), A_2 = -(q3 - q2) and p* the per-sample least-squares minimiser (computed
    from the same a3, v, q). Writing it in relative deviations eps_j = p̂_j / p*_j - 1 with
    each term's column scaled to unit energy,

        r_bal = sum_j eps_j (A_j p*_j) / ||A_j p*_j||,    loss = sum_k r_bal,k^2,

    removes the ~20x imbalance between the damping term (p1) and the spring term (p2) of the
    plain residual energy, so p1 trains as fast as p2. Same minimiser as physics_residual_loss.
    """
    aux = aux.double()
    a3, v3, v2, q3, q2 = aux.unbind(1)
    design = torch.stack([-(v3 - v2), -(q3 - q2)], -1)  # [B, N, 2]
    with torch.no_grad():
        p_star = torch.linalg.lstsq(design, a3[..., None]).solution[..., 0]  # [B, 2]
        terms = design * p_star[:, None, :]  # [B, N, 2]
        unit = terms / terms.norm(dim=1, keepdim=True).clamp_min(eps**0.5)
    rel = p12.double() / p_star - 1  # [B, 2]
    return (unit * rel[:, None, :]).sum(-1).pow(2).sum(-1)


def least_squares_p12(aux: Tensor) -> Tensor:
    """Per-sample minimiser of the residual (no labels): [B, 2] float64. Exact on clean data."""
    aux = aux.double()
    a3, v3, v2, q3, q2 = aux.unbind(1)
    design = torch.stack([-(v3 - v2), -(q3 - q2)], -1)  # [B, N, 2]
    return torch.linalg.lstsq(design, a3[..., None]).solution[..., 0]


def one_cycle_lr(
    progress: float, max_lr: float, pct_start: float = 0.25, div_factor: float = 25.0, final_div_factor: float = 1e4
) -> float:
    """Cosine one-cycle learning rate at training progress in [0, 1]."""
    progress = min(max(progress, 0.0), 1.0)
    start, end = max_lr / div_factor, max_lr / (div_factor * final_div_factor)
    if progress < pct_start:
        f = progress / max(pct_start, 1e-12)
        return start + (max_lr - start) * 0.5 * (1 - math.cos(math.pi * f))
    f = (progress - pct_start) / max(1 - pct_start, 1e-12)
    return end + (max_lr - end) * 0.5 * (1 + math.cos(math.pi * f))


class CheckpointMismatch(CheckpointError):
    """A checkpoint of another model class, or one that does not fit the requested use (a CheckpointError)."""


def stored_model_class(path: str) -> str | None:
    """The hybridqcm model class a checkpoint file holds (None for a foreign checkpoint); read as data.

    Raises FileNotFoundError for a missing file and CheckpointMismatch for an unreadable or refused one."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: checkpoint file does not exist")
    try:
        return read_stored_class(path)
    except CheckpointError as error:
        raise CheckpointMismatch(str(error)) from None


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
    """Shared plumbing: configurable net/optimizer, normalisation buffers, lr schedule, data requirements."""

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
        """Channels and window the datamodule must provide (inputs, targets, aux, window, targets_optional)."""
        raise NotImplementedError

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

    def _progress(self) -> float:
        """Fraction of the run done: the larger of steps/max steps and elapsed/max_time."""
        trainer = self.trainer
        progress = 0.0
        total = trainer.estimated_stepping_batches
        if total and math.isfinite(total) and total > 0:
            progress = trainer.global_step / total
        from lightning.pytorch.callbacks import Timer

        timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
        duration = getattr(timer, "_duration", None) if timer is not None else None
        if duration and self._train_start_time is not None:
            progress = max(progress, (time.monotonic() - self._train_start_time) / duration)
        return progress

    def on_train_start(self) -> None:
        self._train_start_time = time.monotonic()

    def on_train_batch_start(self, batch: Any, batch_idx: int) -> None:
        schedule = self.hparams.get("lr_schedule")
        if schedule:
            lr = one_cycle_lr(self._progress(), **schedule)
            for optimizer in self.trainer.optimizers:
                for group in optimizer.param_groups:
                    group["lr"] = lr
            self.log("lr", lr, on_step=True, on_epoch=False)

    # -- checkpoints ----------------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict) -> None:
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
        from lightning.pytorch.loggers import TensorBoardLogger

        for logger in self.loggers:
            if isinstance(logger, TensorBoardLogger):
                return logger.experiment
        return None

    def _add_figure(self, tag: str, fig) -> None:
        from hybridqcm.plots import close

        writer = self._tensorboard()
        if writer is not None:
            writer.add_figure(tag, fig, global_step=self.global_step)
        close(fig)


# ----------------------------------------------------------------------------------------------------
class ParameterEstimator(QCMModule):
    """Shared by the two CNN estimators: raw (a3, a2) -> (p1, p2), metrics, denoiser hook, inference API."""

    kind = "estimator"
    default_net = {"_target_": "hybridqcm.models.networks.ParameterCNN"}
    # No class-level `denoiser` attribute: it would shadow the submodule nn.Module keeps in _modules.

    def _init_estimator(self, input_channels, target_channels, window, target_transform, train_noise_max, net) -> None:
        if target_transform not in ("log", "standard"):
            raise ValueError(f"target_transform must be 'log' or 'standard', got {target_transform!r}")
        if train_noise_max < 0:
            raise ValueError(f"train_noise_max must be >= 0, got {train_noise_max}")
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self._setup_common(
            net,
            len(input_channels),
            len(target_channels),
            {"in_channels": len(input_channels), "window": window, "out_features": len(target_channels)},
        )
        self.denoiser = None

    def _window(self, x: Tensor) -> int:
        return int(self.hparams.window)

    def _fit_output_normalisation(self, batch: Mapping[str, Tensor], scale: Tensor) -> None:
        y = batch["y"].to(self.out_mean.device, torch.float64)
        y = y.log() if self.hparams.target_transform == "log" else y
        self.out_mean.copy_(y.mean(0))
        self.out_std.copy_(y.std(0).clamp_min(1e-8))

    def encode_targets(self, p: Tensor) -> Tensor:
        y = p.double().log() if self.hparams.target_transform == "log" else p.double()
        return ((y - self.out_mean.double()) / self.out_std.double()).float()

    def decode_outputs(self, z: Tensor) -> Tensor:
        y = z.double() * self.out_std.double() + self.out_mean.double()
        return y.exp() if self.hparams.target_transform == "log" else y

    def attach_denoiser(self, denoiser: DenoisingAutoencoder) -> None:
        """Use a CAE on the inputs before estimating (inference only; never saved with this model)."""
        if list(denoiser.hparams.channels) != list(self.hparams.input_channels):
            raise CheckpointMismatch(
                f"denoiser channels {list(denoiser.hparams.channels)} differ from the estimator's "
                f"inputs {list(self.hparams.input_channels)}"
            )
        self.denoiser = denoiser

    def forward(self, x: Tensor) -> Tensor:
        """Raw inputs [B, C, >= window] -> normalised outputs [B, P]."""
        window = int(self.hparams.window)
        if self.denoiser is not None:
            x = self.denoiser.denoise(x)
        x = x[..., :window].float()
        return self.net(self._standardise_in(x, self._scale(x)))

    def predict_params(self, x: Tensor) -> Tensor:
        """Raw inputs [B, C, >= window] -> physical parameters [B, P] float64."""
        return self.decode_outputs(self(x))

    @torch.no_grad()
    def estimate(self, a3: Tensor, a2: Tensor) -> Tensor:
        """(p1, p2) [B, 2] float64 from raw accelerations a3, a2 [B, N], N >= window (first window steps used)."""
        a3, a2 = torch.as_tensor(a3), torch.as_tensor(a2)
        if a3.ndim == 1:
            a3, a2 = a3[None], a2[None]
        if a3.shape != a2.shape or a3.ndim != 2:
            raise ValueError(f"estimate: a3 and a2 must both be [B, N]; got {tuple(a3.shape)} and {tuple(a2.shape)}")
        if a3.shape[-1] < int(self.hparams.window):
            raise ValueError(f"estimate: need N >= window = {self.hparams.window} steps, got {a3.shape[-1]}")
        was_training = self.training
        self.eval()
        try:
            x = torch.stack([a3, a2], 1).to(self.in_mean.device, torch.float32)
            return self.predict_params(x).double()
        finally:
            self.train(was_training)

    def _loss(self, z: Tensor, target: Tensor) -> Tensor:
        if self.hparams.loss == "l1":
            return F.l1_loss(z, target)
        if self.hparams.loss == "mse":
            return F.mse_loss(z, target)
        return F.smooth_l1_loss(z, target, beta=0.1)

    def _augment(self, x: Tensor) -> Tensor:
        high = float(self.hparams.train_noise_max)
        if high > 0:
            sigma = torch.rand(x.shape[0], device=x.device) * high
            x = apply_noise(x, sigma)
        return x

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        z = self(self._augment(batch["x"]))
        loss = self._loss(z, self.encode_targets(batch["y"]))
        self.log("train/loss", loss, on_step=True, on_epoch=True, prog_bar=True, batch_size=z.shape[0])
        return loss

    def _eval_step(self, batch: Mapping[str, Tensor], stage: str) -> dict:
        z = self(batch["x"])
        pred = self.decode_outputs(z)
        record = {"pred": pred.detach().cpu(), "index": batch["index"].detach().cpu()}
        if "y" in batch:
            loss = self._loss(z, self.encode_targets(batch["y"]))
            self.log(
                f"{stage}/loss", loss, on_step=False, on_epoch=True, prog_bar=stage == "val", batch_size=z.shape[0]
            )
            record["true"] = batch["y"].detach().cpu().double()
        return record

    def validation_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> None:
        self._val_records.append(self._eval_step(batch, "val"))

    def test_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> None:
        self._test_records.append(self._eval_step(batch, "test"))

    def _collect(self, records: list[dict]) -> dict[str, Tensor]:
        keys = records[0].keys() if records else ()
        return {k: torch.cat([r[k] for r in records]) for k in keys if all(k in r for r in records)}

    def _log_errors(self, results: Mapping[str, Tensor], stage: str) -> None:
        if "true" not in results:
            return
        e = (results["pred"] - results["true"]).abs() / results["true"].abs()
        for j, name in enumerate(self.hparams.target_channels):
            self.log(f"{stage}/{name}/mean_rel_err", e[:, j].mean().item())
            self.log(f"{stage}/{name}/max_rel_err", e[:, j].max().item())
            self.log(f"{stage}/{name}/over_25pct", (e[:, j] > 0.25).double().mean().item())
        self.log(f"{stage}/mean_rel_err", e.mean().item(), prog_bar=True)

    def on_validation_epoch_end(self) -> None:
        results = self._collect(self._val_records)
        self._val_records = []
        if not results:
            return
        self._log_errors(results, "val")
        every = int(self.hparams.get("plot_every_n_epochs") or 0)
        if (
            "true" in results
            and every > 0
            and not self.trainer.sanity_checking
            and self.current_epoch % every == 0
            and self._tensorboard() is not None
        ):
            from hybridqcm.plots import plot_sorted_predictions

            for j, name in enumerate(self.hparams.target_channels):
                fig = plot_sorted_predictions(
                    results["pred"][:, j].numpy(),
                    results["true"][:, j].numpy(),
                    name,
                    title=f"{name}, validation, epoch {self.current_epoch}",
                )
                self._add_figure(f"val/sorted_{name}", fig)

    def on_test_epoch_start(self) -> None:
        self._test_records = []

    def on_test_epoch_end(self) -> None:
        self.test_results = self._collect(self._test_records)
        self._test_records = []
        self._log_errors(self.test_results, "test")


class LabelledEstimator(ParameterEstimator):
    """ParameterCNN trained on labels: (a3, a2) [B, 2, window] -> (p1, p2).

    target_transform "log": the net predicts standardised log p (relative errors weigh alike
    across the prior's range); "standard": standardised p; loss on those ("l1", "mse", "smooth_l1").
    train_noise_max > 0: each training sample gets multiplicative noise with sigma ~ U[0, max]
    (on top of the datamodule's), which is what makes the estimates robust to sensor noise.
    """

    kind = "estimator"
    default_net = {"_target_": "hybridqcm.models.networks.ParameterCNN"}

    def __init__(
        self,
        net: Mapping | None = None,
        optimizer: Mapping | None = None,
        scheduler: Mapping | None = None,
        lr_schedule: Mapping | None = None,
        window: int = 500,
        input_channels: Sequence[str] = ("a3", "a2"),
        target_channels: Sequence[str] = ("p1", "p2"),
        scale_channel: int | None = 1,
        target_transform: str = "log",
        loss: str = "l1",
        train_noise_max: float = 0.0,
        plot_every_n_epochs: int = 5,
        h: float = 0.01,
        physics: str = "euler",
    ) -> None:
        net, optimizer, scheduler, lr_schedule = _plain(net), _plain(optimizer), _plain(scheduler), _plain(lr_schedule)
        input_channels, target_channels = list(input_channels), list(target_channels)
        super().__init__()
        if loss not in ("l1", "mse", "smooth_l1"):
            raise ValueError(f"loss must be 'l1', 'mse' or 'smooth_l1', got {loss!r}")
        self.save_hyperparameters()
        self.check_physics()
        self._init_estimator(input_channels, target_channels, window, target_transform, train_noise_max, net)

    def data_requirements(self) -> dict:
        return {
            "inputs": list(self.hparams.input_channels),
            "targets": list(self.hparams.target_channels),
            "aux": [],
            "window": int(self.hparams.window),
            "targets_optional": False,
        }


class GaussianEstimator(ParameterEstimator):
    """ParameterCNN with a variance head: (a3, a2) [B, 2, window] -> mean and variance of each parameter.

    The last dense layer has 2P outputs on the shared backbone: P means mu and P log-variances s
    (clamped to log_var_range) of the standardised log-parameters z; trained by the Gaussian
    negative log-likelihood (models.uncertainty.gaussian_nll, beta-NLL with `nll_beta`). In
    physical terms log p ~ N(out_mean + out_std mu, (out_std sigma)^2): `estimate` gives the median
    exp(.), `estimate_distribution` also the std of log p (what the fused estimator uses as prior).
    The test stage logs coverage and mean relative width of the 50/90/95 % intervals of each
    parameter and of m3 = K3 / p2 (`test/<q>/coverage_95`, `test/<q>/width_95`, ...).
    """

    kind = "estimator"
    default_net = {"_target_": "hybridqcm.models.networks.ParameterCNN"}

    def __init__(
        self,
        net: Mapping | None = None,
        optimizer: Mapping | None = None,
        scheduler: Mapping | None = None,
        lr_schedule: Mapping | None = None,
        window: int = 500,
        input_channels: Sequence[str] = ("a3", "a2"),
        target_channels: Sequence[str] = ("p1", "p2"),
        scale_channel: int | None = 1,
        target_transform: str = "log",
        loss: str = "gaussian_nll",
        nll_beta: float = 0.5,
        log_var_range: Sequence[float] = (-16.0, 4.0),
        K3: float = 98935.0,
        train_noise_max: float = 0.0,
        plot_every_n_epochs: int = 5,
        h: float = 0.01,
        physics: str = "euler",
        init_from: str | None = None,
        train_only_variance: bool = False,
    ) -> None:
        net, optimizer, scheduler, lr_schedule = _plain(net), _plain(optimizer), _plain(scheduler), _plain(lr_schedule)
        input_channels, target_channels = list(input_channels), list(target_channels)
        log_var_range = [float(v) for v in log_var_range]
        super().__init__()
        if loss != "gaussian_nll":
            raise ValueError(f"GaussianEstimator: loss must be 'gaussian_nll', got {loss!r}")
        if target_transform != "log":
            raise ValueError(
                f"GaussianEstimator: target_transform must be 'log' (intervals of p > 0), got {target_transform!r}"
            )
        if len(log_var_range) != 2 or not log_var_range[0] < log_var_range[1]:
            raise ValueError(
                f"GaussianEstimator: log_var_range must be [low, high] with low < high, got {log_var_range}"
            )
        if not 0 <= float(nll_beta) <= 1:
            raise ValueError(f"GaussianEstimator: nll_beta must be in [0, 1], got {nll_beta}")
        if train_noise_max < 0 or window < 1:
            raise ValueError(
                f"GaussianEstimator: need train_noise_max >= 0 and window >= 1, got {train_noise_max}, {window}"
            )
        self.save_hyperparameters()
        self.check_physics()
        # The same backbone, twice the outputs: means then log-variances.
        self._setup_common(
            net,
            len(input_channels),
            len(target_channels),
            {"in_channels": len(input_channels), "window": window, "out_features": 2 * len(target_channels)},
        )
        self.denoiser = None

    data_requirements = LabelledEstimator.data_requirements  # the same labelled (inputs, targets) stream

    def on_fit_start(self) -> None:
        if self.hparams.get("init_from") and not bool(self.norm_fitted):
            raise RuntimeError(
                f"model.init_from={self.hparams.init_from}: not applied; load the source with "
                f"models.checkpoint.warm_start(model) before fitting (qcm-train does)"
            )
        if getattr(self, "_warm_started", False):
            self._warm_started = False
            datamodule = getattr(self.trainer, "datamodule", None)
            if datamodule is not None and hasattr(datamodule, "stats_batch"):
                self.init_variance(datamodule.stats_batch())
        super().on_fit_start()
        if self.hparams.get("train_only_variance"):
            self.freeze_all_but_variance()

    @torch.no_grad()
    def init_variance(self, batch: Mapping[str, Tensor], chunk: int = 256) -> None:
        """Log-variance bias = log of the warm-started network's mean squared error (normalised units)
        on a batch of clean labelled samples: training starts at the right scale, not at sigma = out_std."""
        n = len(self.hparams.target_channels)
        x, y = batch["x"].to(self.in_mean.device), batch["y"].to(self.in_mean.device)
        errors = torch.cat(
            [
                self.split_outputs(self(x[i : i + chunk]))[0] - self.encode_targets(y[i : i + chunk])
                for i in range(0, len(x), chunk)
            ]
        )
        final = [m for m in self.net.head if isinstance(m, torch.nn.Linear)][-1]
        low, high = self.hparams.log_var_range
        final.bias[n:] = errors.square().mean(0).log().clamp(float(low), float(high))

    def freeze_all_but_variance(self) -> None:
        """Train only the log-variance rows of the final layer (on a warm-started network: the means
        stay exactly those of the source network, and the few weights left need few samples)."""
        n = len(self.hparams.target_channels)
        for parameter in self.net.parameters():
            parameter.requires_grad_(False)
        final = [m for m in self.net.head if isinstance(m, torch.nn.Linear)][-1]
        for parameter in (final.weight, final.bias):
            parameter.requires_grad_(True)
            parameter.register_hook(lambda grad: torch.cat([torch.zeros_like(grad[:n]), grad[n:]]))

    @torch.no_grad()
    def warm_start(self, source: ParameterEstimator, path: str = "source") -> None:
        """Start from a trained parameter CNN of the same architecture (LabelledEstimator or
        PhysicsResidualEstimator, loaded by models.checkpoint.warm_start): its backbone, normalisation
        and mean outputs; the log-variance rows start at zero weight (their bias is set from the
        source's error at fit start, init_variance)."""
        if list(source.hparams.target_channels) != list(self.hparams.target_channels) or int(
            source.hparams.window
        ) != int(self.hparams.window):
            raise CheckpointMismatch(
                f"model.init_from={path}: predicts {list(source.hparams.target_channels)} from {source.hparams.window} "
                f"steps; this model {list(self.hparams.target_channels)} from {self.hparams.window}"
            )
        own, theirs = self.net.state_dict(), source.net.state_dict()
        last = [k for k in own if k.startswith("head.")][-2:]  # the final Linear: weight, bias
        for key, value in theirs.items():
            if key in last:
                n = value.shape[0]
                own[key][:n] = value
                own[key][n:] = 0.0
            elif key not in own or own[key].shape != value.shape:
                raise CheckpointMismatch(f"model.init_from={path}: network layer {key} does not match this model's")
            else:
                own[key] = value
        self.net.load_state_dict(own)
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            getattr(self, name).copy_(getattr(source, name))
        self.norm_fitted.fill_(True)
        self._warm_started = True

    def split_outputs(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """Net outputs [B, 2P] -> (mu [B, P], clamped log-variance [B, P]) in normalised units."""
        n = len(self.hparams.target_channels)
        low, high = self.hparams.log_var_range
        return z[:, :n], clamp_log_var(z[:, n:], float(low), float(high))

    def predict_params(self, x: Tensor) -> Tensor:
        """Raw inputs [B, C, >= window] -> median parameters exp(E log p) [B, P] float64."""
        return self.decode_outputs(self.split_outputs(self(x))[0])

    def predict_distribution(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Raw inputs [B, C, >= window] -> (mean, std) of log p [B, P] float64."""
        mu, log_var = self.split_outputs(self(x))
        std = self.out_std.double()
        return mu.double() * std + self.out_mean.double(), (0.5 * log_var.double()).exp() * std

    @torch.no_grad()
    def estimate_distribution(self, a3: Tensor, a2: Tensor) -> tuple[Tensor, Tensor]:
        """(median p [B, P], std of log p [B, P]) float64 from raw a3, a2 [B, N], N >= window.
        For a small std s the std of p itself is about p s (delta method)."""
        a3, a2 = torch.as_tensor(a3), torch.as_tensor(a2)
        if a3.ndim == 1:
            a3, a2 = a3[None], a2[None]
        if a3.shape != a2.shape or a3.ndim != 2 or a3.shape[-1] < int(self.hparams.window):
            raise ValueError(
                f"estimate_distribution: a3, a2 must both be [B, N >= {self.hparams.window}]; "
                f"got {tuple(a3.shape)} and {tuple(a2.shape)}"
            )
        was_training = self.training
        self.eval()
        try:
            x = torch.stack([a3, a2], 1).to(self.in_mean.device, torch.float32)
            log_mean, log_std = self.predict_distribution(x)
            return log_mean.exp(), log_std
        finally:
            self.train(was_training)

    def _loss(self, z: Tensor, target: Tensor) -> Tensor:
        mu, log_var = self.split_outputs(z)
        return gaussian_nll(mu, log_var, target, float(self.hparams.nll_beta))

    def _eval_step(self, batch: Mapping[str, Tensor], stage: str) -> dict:
        z = self(batch["x"])
        mu, log_var = self.split_outputs(z)
        std = self.out_std.double()
        log_mean = mu.double() * std + self.out_mean.double()
        log_std = (0.5 * log_var.double()).exp() * std
        record = {
            "pred": log_mean.exp().detach().cpu(),
            "log_mean": log_mean.detach().cpu(),
            "log_std": log_std.detach().cpu(),
            "index": batch["index"].detach().cpu(),
        }
        if "y" in batch:
            loss = self._loss(z, self.encode_targets(batch["y"]))
            self.log(
                f"{stage}/loss", loss, on_step=False, on_epoch=True, prog_bar=stage == "val", batch_size=z.shape[0]
            )
            record["true"] = batch["y"].detach().cpu().double()
        return record

    def decode_outputs(self, z: Tensor) -> Tensor:
        if z.shape[-1] == 2 * len(self.hparams.target_channels):  # raw net outputs: their means
            z = self.split_outputs(z)[0]
        return super().decode_outputs(z)

    def _log_errors(self, results: Mapping[str, Tensor], stage: str) -> None:
        super()._log_errors(results, stage)
        if "true" not in results:
            return
        rows = calibration_rows(
            results["log_mean"],
            results["log_std"],
            results["true"].log(),
            list(self.hparams.target_channels),
            float(self.hparams.K3),
        )
        for row in rows:
            for key, value in row.items():
                if key not in ("quantity", "n"):
                    self.log(f"{stage}/{row['quantity']}/{key}", value)
        self.calibration = rows


class PhysicsResidualEstimator(ParameterEstimator):
    """The same CNN trained without labels on the occupant equation's residual.

    Loss per sample: sum_k (a3 - ã3)^2 / sum_k a3^2 with ã3 = -p̂1 (v3 - v2) - p̂2 (q3 - q2), from the
    sample's clean a3, v, q (aux channels); the net sees the (possibly noise-augmented) a3, a2.
    residual_norm="balanced" uses the same residual in preconditioned coordinates
    (balanced_residual_loss), which trains the weakly-determined p1 as fast as p2;
    residual_root=True averages the per-sample root of the loss (L1-like, robust to the noisiest samples).
    Output normalisation comes from per-sample least-squares fits of the same residual, so no
    label is touched; labels, where the data has them, only feed validation/test metrics.
    """

    AUX = ["a3", "v3", "v2", "q3", "q2"]

    def __init__(
        self,
        net: Mapping | None = None,
        optimizer: Mapping | None = None,
        scheduler: Mapping | None = None,
        lr_schedule: Mapping | None = None,
        window: int = 500,
        input_channels: Sequence[str] = ("a3", "a2"),
        target_channels: Sequence[str] = ("p1", "p2"),
        scale_channel: int | None = 1,
        target_transform: str = "log",
        loss: str = "residual",
        train_noise_max: float = 0.0,
        plot_every_n_epochs: int = 5,
        residual_norm: str = "energy",
        residual_root: bool = False,
        h: float = 0.01,
        physics: str = "euler",
    ) -> None:
        net, optimizer, scheduler, lr_schedule = _plain(net), _plain(optimizer), _plain(scheduler), _plain(lr_schedule)
        input_channels, target_channels = list(input_channels), list(target_channels)
        if list(target_channels) != ["p1", "p2"]:
            raise ValueError(
                f"PhysicsResidualEstimator estimates exactly (p1, p2), got target_channels {target_channels}"
            )
        if loss != "residual":
            raise ValueError(f"PhysicsResidualEstimator: loss must be 'residual', got {loss!r}")
        if residual_norm not in ("energy", "balanced"):
            raise ValueError(f"residual_norm must be 'energy' or 'balanced', got {residual_norm!r}")
        super().__init__()
        self.save_hyperparameters()
        self.check_physics()
        self._init_estimator(input_channels, target_channels, window, target_transform, train_noise_max, net)

    def data_requirements(self) -> dict:
        return {
            "inputs": list(self.hparams.input_channels),
            "targets": ["p1", "p2"],
            "aux": list(self.AUX),
            "window": int(self.hparams.window),
            "targets_optional": True,
        }

    def _fit_output_normalisation(self, batch: Mapping[str, Tensor], scale: Tensor) -> None:
        p = least_squares_p12(batch["aux"].to(self.out_mean.device)).clamp_min(1e-9)
        y = p.log() if self.hparams.target_transform == "log" else p
        self.out_mean.copy_(y.mean(0))
        self.out_std.copy_(y.std(0).clamp_min(1e-8))

    def residual_loss(self, pred_p12: Tensor, aux: Tensor) -> Tensor:
        if self.hparams.get("residual_norm", "energy") == "balanced":
            per_sample = balanced_residual_loss(pred_p12, aux)
        else:
            per_sample = physics_residual_loss(pred_p12.double(), aux.double())
        if self.hparams.get("residual_root", False):
            # sqrt per sample: an L1-like loss (each sample pulls with unit strength), like the labelled recipe.
            per_sample = (per_sample + 1e-12).sqrt()
        return per_sample.mean()

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        pred = self.decode_outputs(self(self._augment(batch["x"])))
        loss = self.residual_loss(pred, batch["aux"][..., : int(self.hparams.window)])
        self.log("train/loss", loss.float(), on_step=True, on_epoch=True, prog_bar=True, batch_size=pred.shape[0])
        return loss.float()

    def _eval_step(self, batch: Mapping[str, Tensor], stage: str) -> dict:
        pred = self.decode_outputs(self(batch["x"]))
        record = {"pred": pred.detach().cpu(), "index": batch["index"].detach().cpu()}
        if "aux" in batch:
            loss = self.residual_loss(pred, batch["aux"][..., : int(self.hparams.window)])
            self.log(
                f"{stage}/loss",
                loss.float(),
                on_step=False,
                on_epoch=True,
                prog_bar=stage == "val",
                batch_size=pred.shape[0],
            )
        if "y" in batch:
            record["true"] = batch["y"].detach().cpu().double()
        return record


# ----------------------------------------------------------------------------------------------------
class _SignalModule(QCMModule):
    """Shared by the CAE and the U-Net: time series in, time series out, MSE in normalised units."""

    def _fit_output_normalisation(self, batch: Mapping[str, Tensor], scale: Tensor) -> None:
        y = batch["y"].to(self.out_mean.device, torch.float64)
        ys = y / scale
        self.out_mean.copy_(ys.mean((0, 2)))
        self.out_std.copy_(ys.std((0, 2)).clamp_min(1e-8))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Raw inputs [B, C, N] -> (normalised outputs [B, C', N], per-sample scale [B, 1, 1])."""
        x = x.float()
        scale = self._scale(x)
        return self.net(self._standardise_in(x, scale)), scale

    def _physical(self, z: Tensor, scale: Tensor) -> Tensor:
        return (z * self.out_std[:, None] + self.out_mean[:, None]) * scale

    def _normalised_target(self, y: Tensor, scale: Tensor) -> Tensor:
        return (y.float() / scale - self.out_mean[:, None]) / self.out_std[:, None]

    def _run(self, x: Tensor) -> Tensor:
        was_training = self.training
        self.eval()
        try:
            with torch.no_grad():
                z, scale = self(x.to(self.in_mean.device, torch.float32))
                return self._physical(z, scale)
        finally:
            self.train(was_training)

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        z, scale = self(batch["x"])
        loss = F.mse_loss(z, self._normalised_target(batch["y"], scale))
        self.log("train/loss", loss, on_step=True, on_epoch=True, prog_bar=True, batch_size=z.shape[0])
        return loss

    def _eval_step(self, batch: Mapping[str, Tensor], stage: str) -> dict:
        z, scale = self(batch["x"])
        pred = self._physical(z, scale)
        record = {"index": batch["index"].cpu()}
        if "y" in batch:
            y = batch["y"].float()
            loss = F.mse_loss(z, self._normalised_target(y, scale))
            self.log(
                f"{stage}/loss", loss, on_step=False, on_epoch=True, prog_bar=stage == "val", batch_size=z.shape[0]
            )
            mse = (pred - y).pow(2).mean(-1)  # [B, C'] physical units^2
            record["mse"] = mse.double().cpu()
            record["rel_mse"] = (mse / y.pow(2).mean(-1).clamp_min(1e-30)).double().cpu()
            if list(self.data_requirements()["inputs"]) == list(self.data_requirements()["targets"]):
                record["input_mse"] = (batch["x"].float() - y).pow(2).mean(-1).double().cpu()
        record["examples"] = (batch["x"][:4].cpu(), batch.get("y", pred)[:4].cpu(), pred[:4].detach().cpu())
        return record

    def validation_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> None:
        self._val_records.append(self._eval_step(batch, "val"))

    def test_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> None:
        self._test_records.append(self._eval_step(batch, "test"))

    def _summarise(self, records: list[dict], stage: str) -> dict[str, Tensor]:
        out: dict[str, Any] = {}
        for key in ("index", "mse", "rel_mse", "input_mse"):
            if records and all(key in r for r in records):
                out[key] = torch.cat([r[key] for r in records])
        if records:
            out["examples"] = records[0]["examples"]
        if "mse" in out:
            names = self.data_requirements()["targets"]
            for j, name in enumerate(names):
                self.log(f"{stage}/{name}/mse", out["mse"][:, j].mean().item())
                self.log(f"{stage}/{name}/rel_mse", out["rel_mse"][:, j].mean().item())
            self.log(f"{stage}/rel_mse", out["rel_mse"].mean().item(), prog_bar=True)
            self.log(f"{stage}/mse", out["mse"].mean().item())
        return out

    def on_validation_epoch_end(self) -> None:
        out = self._summarise(self._val_records, "val")
        self._val_records = []
        every = int(self.hparams.get("plot_every_n_epochs") or 0)
        if (
            "examples" in out
            and every > 0
            and not self.trainer.sanity_checking
            and self.current_epoch % every == 0
            and self._tensorboard() is not None
        ):
            self._add_figure("val/examples", self.example_figure(out["examples"]))

    def example_figure(self, examples: tuple[Tensor, Tensor, Tensor], path=None):
        from hybridqcm.plots import plot_overlays

        x, y, pred = (t.double().numpy() for t in examples)
        req = self.data_requirements()
        h = 0.01
        time_axis = torch.arange(y.shape[-1]).double().numpy() * h
        curves = {}
        for j, name in enumerate(req["targets"]):
            if list(req["inputs"]) == list(req["targets"]):  # denoiser: show what it was given
                curves[f"{name} noisy input"] = x[:, j]
            curves[f"{name} true"] = y[:, j]
            curves[f"{name} predicted"] = pred[:, j]
        return plot_overlays(time_axis, curves, path=path, title=f"{type(self).__name__}: examples")

    def on_test_epoch_start(self) -> None:
        self._test_records = []

    def on_test_epoch_end(self) -> None:
        self.test_results = self._summarise(self._test_records, "test")
        self._test_records = []


class DenoisingAutoencoder(_SignalModule):
    """CAE: noisy (â3, â2) -> clean (a3, a2); MSE. Noise comes from the datamodule (sigma = 0.1 by default)."""

    kind = "denoiser"
    default_net = {"_target_": "hybridqcm.models.networks.DenoisingCAE"}

    def __init__(
        self,
        net: Mapping | None = None,
        optimizer: Mapping | None = None,
        scheduler: Mapping | None = None,
        lr_schedule: Mapping | None = None,
        channels: Sequence[str] = ("a3", "a2"),
        window: int = 500,
        scale_channel: int | None = 1,
        plot_every_n_epochs: int = 5,
        h: float = 0.01,
        physics: str = "euler",
    ) -> None:
        net, optimizer, scheduler, lr_schedule = _plain(net), _plain(optimizer), _plain(scheduler), _plain(lr_schedule)
        channels = list(channels)
        super().__init__()
        self.save_hyperparameters()
        self.check_physics()
        self._setup_common(net, len(channels), len(channels), {"in_channels": len(channels)})

    def data_requirements(self) -> dict:
        return {
            "inputs": list(self.hparams.channels),
            "targets": list(self.hparams.channels),
            "aux": [],
            "window": int(self.hparams.window),
            "targets_optional": False,
        }

    def denoise(self, x: Tensor) -> Tensor:
        """Noisy raw signals [B, C, N] (channels as hparams.channels, any N) -> denoised [B, C, N], same dtype."""
        x = torch.as_tensor(x)
        if x.ndim != 3 or x.shape[1] != len(self.hparams.channels):
            raise ValueError(f"denoise: expected [B, {len(self.hparams.channels)}, N], got {tuple(x.shape)}")
        return self._run(x).to(x.dtype if x.is_floating_point() else torch.float32)


class CompletionUNet(_SignalModule):
    """U-Net: (a3, p_u u) -> (a2, a1); MSE in normalised units."""

    kind = "completion"
    default_net = {"_target_": "hybridqcm.models.networks.UNet1d"}

    def __init__(
        self,
        net: Mapping | None = None,
        optimizer: Mapping | None = None,
        scheduler: Mapping | None = None,
        lr_schedule: Mapping | None = None,
        input_channels: Sequence[str] = ("a3", "pu_u"),
        target_channels: Sequence[str] = ("a2", "a1"),
        window: int = 512,
        scale_channel: int | None = 0,
        plot_every_n_epochs: int = 5,
        h: float = 0.01,
        physics: str = "euler",
    ) -> None:
        net, optimizer, scheduler, lr_schedule = _plain(net), _plain(optimizer), _plain(scheduler), _plain(lr_schedule)
        input_channels, target_channels = list(input_channels), list(target_channels)
        super().__init__()
        self.save_hyperparameters()
        self.check_physics()
        self._setup_common(
            net,
            len(input_channels),
            len(target_channels),
            {"in_channels": len(input_channels), "out_channels": len(target_channels)},
        )

    def data_requirements(self) -> dict:
        return {
            "inputs": list(self.hparams.input_channels),
            "targets": list(self.hparams.target_channels),
            "aux": [],
            "window": int(self.hparams.window),
            "targets_optional": False,
        }

    def complete(self, a3: Tensor, pu_u: Tensor) -> Tensor:
        """Raw a3, p_u u [B, N] (any N) -> completed (a2, a1) [B, 2, N] in m/s^2, same dtype as a3."""
        a3, pu_u = torch.as_tensor(a3), torch.as_tensor(pu_u)
        if a3.ndim == 1:
            a3, pu_u = a3[None], pu_u[None]
        if a3.shape != pu_u.shape or a3.ndim != 2:
            raise ValueError(
                f"complete: a3 and pu_u must both be [B, N]; got {tuple(a3.shape)} and {tuple(pu_u.shape)}"
            )
        out = self._run(torch.stack([a3, pu_u], 1))
        return out.to(a3.dtype if a3.is_floating_point() else torch.float32)


MODULES = {
    cls.__name__: cls
    for cls in (LabelledEstimator, GaussianEstimator, PhysicsResidualEstimator, DenoisingAutoencoder, CompletionUNet)
}

__all__ = [
    "LabelledEstimator",
    "GaussianEstimator",
    "PhysicsResidualEstimator",
    "DenoisingAutoencoder",
    "CompletionUNet",
    "QCMModule",
    "ParameterEstimator",
    "CheckpointMismatch",
    "build_network",
    "physics_residual",
    "physics_residual_loss",
    "balanced_residual_loss",
    "least_squares_p12",
    "one_cycle_lr",
    "MODULES",
]
