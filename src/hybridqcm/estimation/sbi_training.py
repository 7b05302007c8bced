"""Training of the SBI peer (estimation/sbi_peer.py): the recipe (:class:`TrainSettings`), the noise the
training adds (:func:`noisy`, :func:`log_uniform`) and :func:`train_peer`, which minimises the NPE loss."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hybridqcm.errors import ConfigError

from .sbi_peer import SBIPeer


@dataclass(frozen=True)
class TrainSettings:
    epochs: int = 60
    max_seconds: float | None = 540.0  # wall-clock budget; the LR schedule follows max(epoch, time) progress
    batch_size: int = 128
    lr: float = 2e-3  # peak
    warmup: float = 0.05  # fraction of the budget
    weight_decay: float = 0.0
    noise_min: float = 0.002  # per-sample additive noise level s ~ log-uniform[noise_min, noise_max] × channel RMS
    noise_max: float = 0.10
    val_fraction: float = 0.1
    shift: bool = True  # random window start within the stored steps (windows are cut mid-drive anyway)
    flip: bool = True  # x -> −x: the same vehicle on the mirrored road (linear system, symmetric road law)
    clip_norm: float = 5.0
    seed: int = 0

    def validate(self) -> TrainSettings:
        if not (0 < self.noise_min <= self.noise_max):
            raise ConfigError(f"train.noise_min={self.noise_min}, noise_max={self.noise_max}: need 0 < min <= max")
        if self.epochs < 1 or self.batch_size < 1 or self.lr <= 0:
            raise ConfigError(f"train: epochs, batch_size must be >= 1 and lr > 0 (got {self})")
        if not (0 < self.val_fraction < 1):
            raise ConfigError(f"train.val_fraction={self.val_fraction} must be in (0, 1)")
        return self


def _schedule(progress: float, warmup: float) -> float:
    """LR factor at training progress in [0, 1]: linear from 0.04 to 1 over `warmup`, then cosine to 0."""
    if progress < warmup:
        return 0.04 + 0.96 * progress / warmup
    return 0.5 * (1 + math.cos(math.pi * min((progress - warmup) / max(1 - warmup, 1e-12), 1.0)))


def noisy(x: Tensor, level: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """x [B, C, N] plus white noise of std level[b] · RMS of each sample's channel."""
    rms = x.pow(2).mean(-1, keepdim=True).sqrt()
    noise = torch.randn(x.shape, generator=generator, dtype=x.dtype)
    return x + level.to(x.dtype)[:, None, None] * rms * noise


def log_uniform(n: int, low: float, high: float, generator: torch.Generator | None = None) -> Tensor:
    """[n] draws of s with log s ~ U[log low, log high]."""
    r = torch.rand(n, generator=generator, dtype=torch.float64)
    return (math.log(low) + r * (math.log(high) - math.log(low))).exp()


def _windows(peer: SBIPeer, accel: Tensor, starts: Tensor) -> Tensor:
    """[B, C, window] windows of accel [B, T, 3] starting at starts [B]."""
    w = peer.settings.window
    steps = starts[:, None] + torch.arange(w)[None]
    picked = torch.gather(accel, 1, steps[:, :, None].expand(-1, -1, 3))
    return peer.inputs_of(picked)


def train_peer(
    peer: SBIPeer,
    accel: Tensor,
    params: Tensor,
    settings: TrainSettings,
    log: Callable[[str], None] = print,
) -> dict:
    """Train the peer on accel [M, T, 3] (clean, m/s²), params [M, 10]; keeps the best validation state.

    The last `val_fraction` of the samples (a fixed noisy copy) is the validation set. Returns the
    history {epoch, train_loss, val_loss, seconds} and the best epoch."""
    settings = settings.validate()
    generator = torch.Generator().manual_seed(int(settings.seed))
    torch.manual_seed(int(settings.seed))
    M, T = accel.shape[0], accel.shape[1]
    w = peer.settings.window
    order = torch.randperm(M, generator=generator)
    n_val = max(1, int(round(settings.val_fraction * M)))
    train_idx, val_idx = order[n_val:], order[:n_val]
    accel = accel.float()
    u_all = peer.to_latent(peer.normalise(params)).float()
    x_val = noisy(
        peer.inputs_of(accel[val_idx]),
        log_uniform(n_val, settings.noise_min, settings.noise_max, generator),
        generator,
    )
    u_val = u_all[val_idx]
    optimiser = torch.optim.AdamW(peer.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    history, best, best_state = [], math.inf, None
    t0 = time.perf_counter()
    budget = settings.max_seconds
    for epoch in range(settings.epochs):
        peer.train()
        perm = train_idx[torch.randperm(train_idx.numel(), generator=generator)]
        total, count = 0.0, 0
        for start in range(0, perm.numel(), settings.batch_size):
            progress = max(epoch / settings.epochs, (time.perf_counter() - t0) / budget if budget else 0.0)
            for (
                group
            ) in optimiser.param_groups:  # linear warm-up, then cosine decay over the budget (epochs or seconds)
                group["lr"] = settings.lr * _schedule(progress, settings.warmup)
            idx = perm[start : start + settings.batch_size]
            b = idx.numel()
            starts = torch.randint(0, T - w + 1, (b,), generator=generator) if settings.shift else torch.zeros(b)
            x = _windows(peer, accel[idx], starts.long())
            if settings.flip:
                x = x * (torch.randint(0, 2, (b,), generator=generator) * 2 - 1).float()[:, None, None]
            x = noisy(x, log_uniform(b, settings.noise_min, settings.noise_max, generator), generator)
            loss = peer.loss(u_all[idx], x).mean()
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(peer.parameters(), settings.clip_norm)
            optimiser.step()
            total, count = total + loss.item() * b, count + b
        peer.eval()
        with torch.no_grad():
            val = float(
                torch.cat([peer.loss(u_val[i : i + 512], x_val[i : i + 512]) for i in range(0, n_val, 512)]).mean()
            )
        seconds = time.perf_counter() - t0
        history.append({"epoch": epoch, "train_loss": total / count, "val_loss": val, "seconds": seconds})
        log(f"epoch {epoch}: train {total / count:.4f}  val {val:.4f}  ({seconds:.0f} s)")
        if val < best:
            best, best_epoch = val, epoch
            best_state = {k: v.detach().clone() for k, v in peer.state_dict().items()}
        if budget and seconds >= budget:
            break
    if best_state is not None:
        peer.load_state_dict(best_state)
    peer.eval()
    return {"history": history, "best_epoch": best_epoch, "best_val_loss": best, "seconds": time.perf_counter() - t0}


__all__ = ["TrainSettings", "train_peer", "noisy", "log_uniform"]
