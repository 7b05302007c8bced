"""The parameter CNNs: raw (a3, a2) [B, 2, window] -> (p1, p2), labelled, Gaussian or label-free.

    ParameterEstimator           the shared part: output transform, noise augmentation, denoiser
                                 hook, inference API, validation/test error statistics
    LabelledEstimator            trained on labels (L1 / MSE / smooth L1 on standardised log p)
    GaussianEstimator            the same backbone with a variance head: models/gaussian_estimator.py
    PhysicsResidualEstimator     trained without labels on the occupant equation's residual

Inference API (used by the hybrid estimator):
    .estimate(a3 [B, N], a2 [B, N]) -> [B, 2] (p1, p2) float64   (GaussianEstimator: the median)
    GaussianEstimator.estimate_distribution(a3, a2) -> (median p [B, P], std of log p [B, P])

Validation/test statistics per parameter over the epoch (relative error e = |p̂ - p| / |p|,
metrics.ErrorDistribution): `{stage}/{p}/mean_rel_err`, `max_rel_err`, `over_25pct` and
`{stage}/mean_rel_err` over all parameters; logged only where the data has labels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F
from torch import Tensor

from hybridqcm.data.batches import apply_noise
from hybridqcm.errors import CheckpointError
from hybridqcm.metrics import ErrorDistribution
from hybridqcm.models.base import QCMModule, _plain
from hybridqcm.models.physics_losses import balanced_residual_loss, least_squares_p12, physics_residual_loss

if TYPE_CHECKING:
    from hybridqcm.models.signal_models import DenoisingAutoencoder

STAGES = ("val", "test")


class ParameterEstimator(QCMModule):
    """Shared by the three CNN estimators: raw (a3, a2) -> (p1, p2), metrics, denoiser hook, inference API."""

    kind = "estimator"
    default_net = {"_target_": "hybridqcm.models.networks.ParameterCNN"}
    # No class-level `denoiser` attribute: it would shadow the submodule nn.Module keeps in _modules.

    def _init_estimator(
        self, input_channels, target_channels, window, target_transform, train_noise_max, net, outputs_per_target=1
    ) -> None:
        """Checks, network (outputs_per_target x P outputs: 2 for means and log-variances), buffers, metrics."""
        if target_transform not in ("log", "standard"):
            raise ValueError(f"target_transform must be 'log' or 'standard', got {target_transform!r}")
        if train_noise_max < 0:
            raise ValueError(f"train_noise_max must be >= 0, got {train_noise_max}")
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        n_out = outputs_per_target * len(target_channels)
        self._setup_common(
            net,
            len(input_channels),
            len(target_channels),
            {"in_channels": len(input_channels), "window": window, "out_features": n_out},
        )
        self.denoiser = None
        # Fed with the records' CPU float64 tensors, so the logged numbers are those of the test
        # artefacts' error table; not a submodule (nothing in the state_dict or the model summary).
        # Per process like the rest of the epoch logs (no sync_dist), so no cross-rank gather.
        self._errors = {s: ErrorDistribution(target_channels, sync_on_compute=False) for s in STAGES}

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
            raise CheckpointError(
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

    def _update_statistics(self, record: dict, stage: str) -> None:
        if "true" in record:
            self._errors[stage].update(record["pred"], record["true"])

    def _reset_statistics(self, stage: str) -> None:
        self._errors[stage].reset()

    def _summarise(self, records: list[dict], stage: str) -> dict[str, Tensor]:
        """The epoch's records concatenated (pred, true, index [n, ...]); error statistics logged."""
        keys = records[0].keys() if records else ()
        results = {k: torch.cat([r[k] for r in records]) for k in keys if all(k in r for r in records)}
        self._log_errors(results, stage)
        return results

    def _log_errors(self, results: Mapping[str, Tensor], stage: str) -> None:
        metric = self._errors[stage]
        if metric.update_count == 0:
            return
        for row in metric.compute():
            self.log(f"{stage}/{row['param']}/mean_rel_err", row["mean_err"])
            self.log(f"{stage}/{row['param']}/max_rel_err", row["max_err"])
            self.log(f"{stage}/{row['param']}/over_25pct", row["over_25pct"])
        self.log(f"{stage}/mean_rel_err", metric.mean_error(), prog_bar=True)
        metric.reset()

    def _plot_validation(self, summary: Mapping[str, Any]) -> None:
        if "true" not in summary:
            return
        from hybridqcm.plots import plot_sorted_predictions  # matplotlib only when a figure is drawn

        for j, name in enumerate(self.hparams.target_channels):
            fig = plot_sorted_predictions(
                summary["pred"][:, j].numpy(),
                summary["true"][:, j].numpy(),
                name,
                title=f"{name}, validation, epoch {self.current_epoch}",
            )
            self._add_figure(f"val/sorted_{name}", fig)


class LabelledEstimator(ParameterEstimator):
    """ParameterCNN trained on labels: (a3, a2) [B, 2, window] -> (p1, p2).

    target_transform "log": the net predicts standardised log p (relative errors weigh alike
    across the prior's range); "standard": standardised p; loss on those ("l1", "mse", "smooth_l1").
    train_noise_max > 0: each training sample gets multiplicative noise with sigma ~ U[0, max]
    (on top of the datamodule's), which is what makes the estimates robust to sensor noise.
    """

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
        """Labels only where the data has them (metrics); the clean aux channels drive the loss."""
        return self._requirements(self.hparams.input_channels, ["p1", "p2"], self.AUX, targets_optional=True)

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


__all__ = ["ParameterEstimator", "LabelledEstimator", "PhysicsResidualEstimator"]
