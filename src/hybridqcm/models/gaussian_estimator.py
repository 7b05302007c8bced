"""GaussianEstimator: the parameter CNN with a variance head, (a3, a2) [B, 2, window] -> p and its uncertainty.

    GaussianEstimator                    the ParameterEstimator backbone, beta-NLL, interval calibration
    .estimate(a3, a2) -> [B, 2]          the median (p1, p2) float64
    .estimate_distribution(a3, a2)       (median p [B, P], std of log p [B, P])

The shared part (output transform, noise augmentation, denoiser hook, statistics) is models/estimators.py's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from hybridqcm.errors import CheckpointError
from hybridqcm.models.base import _plain
from hybridqcm.models.estimators import ParameterEstimator
from hybridqcm.models.uncertainty import calibration_rows, clamp_log_var, gaussian_nll
from hybridqcm.physics.parameters import REFERENCE_VEHICLE


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
        K3: float = REFERENCE_VEHICLE.K3,
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
        self._init_estimator(input_channels, target_channels, window, target_transform, train_noise_max, net, 2)

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
            raise CheckpointError(
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
                raise CheckpointError(f"model.init_from={path}: network layer {key} does not match this model's")
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


__all__ = ["GaussianEstimator"]
