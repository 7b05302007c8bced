"""The signal models: time series in, time series out, MSE in normalised units.

    DenoisingAutoencoder   CAE: noisy (â3, â2) [B, 2, N] -> clean (a3, a2) [B, 2, N]
    CompletionUNet         U-Net: (a3, p_u u) [B, 2, N] -> (a2, a1) [B, 2, N]

Outputs are de-standardised and multiplied back by the input's per-sample scale (the RMS of the
reference channel), so a rougher road gives proportionally larger outputs (the system is linear).

Inference API (used by the hybrid estimator):
    DenoisingAutoencoder .denoise(x [B, 2, N]) -> [B, 2, N]   channels (a3, a2)
    CompletionUNet       .complete(a3 [B, N], pu_u [B, N]) -> [B, 2, N]   channels (a2, a1)

Validation/test statistics per target channel: `{stage}/{c}/mse` (physical units^2),
`{stage}/{c}/rel_mse` (MSE / mean square of the target), and `{stage}/mse`, `{stage}/rel_mse`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from hybridqcm.models.base import QCMModule, _plain


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

    def _plot_validation(self, summary: Mapping[str, Any]) -> None:
        if "examples" in summary:
            self._add_figure("val/examples", self.example_figure(summary["examples"]))

    def example_figure(self, examples: tuple[Tensor, Tensor, Tensor], path=None):
        from hybridqcm.plots import plot_overlays  # matplotlib only when a figure is drawn

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
        """Noisy channels in, the same clean channels as targets."""
        return self._requirements(self.hparams.channels, self.hparams.channels)

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


__all__ = ["DenoisingAutoencoder", "CompletionUNet"]
