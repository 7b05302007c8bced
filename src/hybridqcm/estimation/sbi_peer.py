"""The SBI peer: an amortised posterior p(θ | a3, a2) by neural posterior estimation (NPE).

A conditional normalising flow q(u | x) (sbi's zuko / nflows builders) is trained on pairs
(θ, x) of simulated recordings by maximising log q(u(θ) | x) — the NPE loss, whose minimiser over
an expressive enough family is the true posterior under the training prior and noise model. Our
ParameterCNN is the embedding net (its last layer widened to `features` summaries instead of 2
parameters), trained jointly with the flow.

Parameter spaces (all float64 buffers, fitted once on the training set):

    z = (log p − μ) / σ                      normalised parameter space [..., P]   (p > 0 always)
    u = (z V_K) / s_K                        flow space [..., K], unit variance on the prior
    z = (u s_K) V_Kᵀ                         back (exact on the prior's support)

V_K, s_K: the K leading right singular vectors / singular values (÷ √M) of the training z.
Directions with s_k ≤ `degenerate_tol` · s_1 are constant on the prior and dropped: under the
thesis prior p1 = C3/m3 and p2 = K3/m3 with C3, K3 fixed, so log p1 − log p2 is the same for
every sample; a flow asked to model that direction spends its capacity shrinking a width that is
exactly zero. The posterior lives on the prior's support, so nothing is lost.

Inputs: raw accelerations x [B, C, window] in m/s² (C = channels, default (a3, a2)); the
embedding divides each sample by the RMS of its `scale_channel` (a linear system: the road's
amplitude carries no information on p) and standardises each channel with training statistics.

Training noise: additive white noise per channel, std = s · RMS of the sample's channel with
s ~ log-uniform[noise_min, noise_max] drawn per sample and fresh every epoch, so one posterior
serves every noise level in that range (it reads the level from the data).

Saving: `save` writes only tensors and plain data (state_dict, hyper-parameters, buffers);
`load` reads them with weights_only=True (models.untrusted.read_raw), checks the
hyper-parameters are plain data of known keys, rebuilds the flow and loads the state strictly.

The `sbi` package is an optional extra (`pip install -e '.[sbi]'`); it is imported lazily and
its absence is a one-line ConfigError naming the extra.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from hybridqcm.errors import CheckpointError, ConfigError
from hybridqcm.models.networks import ParameterCNN

PARAM_NAMES = tuple(f"p{i}" for i in range(1, 11))
CHANNELS = ("a3", "a2", "a1")
EXTRA = "sbi"
CLASS_NAME = "SBIPeer"
# sbi's builders by our name: zuko flows (autoregressive, sbi's current default family) and nflows ones.
FLOWS = {
    "nsf": "build_zuko_nsf",
    "maf": "build_zuko_maf",
    "nflows_nsf": "build_nsf",
    "nflows_maf": "build_maf",
}


def import_sbi():
    """The `sbi` package, or a one-line ConfigError naming the optional extra that installs it."""
    try:
        import sbi  # noqa: F401
        from sbi.neural_nets.net_builders import flow  # noqa: F401
    except ImportError:
        raise ConfigError(
            f"the SBI peer needs the optional extra '{EXTRA}' (sbi==0.27.0), which is not installed: "
            f"pip install -e '.[{EXTRA}]'"
        ) from None
    return sbi


class Embedding(nn.Module):
    """Raw x [B, C, window] (m/s²) -> summaries [B, features]: per-sample scale, per-channel
    standardisation (buffers), then ParameterCNN; with `noise_features`, the last C summaries are
    log10(RMS of the second difference / RMS) per channel instead of CNN outputs.

    Why the noise summaries: white noise of std σ has a second difference of RMS √6 σ, while the
    100 Hz response is smooth, so this ratio reads the noise level almost directly. Without it
    the CNN's posterior width did not follow the noise level (measured, docs/measurements/sbi.md).
    """

    def __init__(
        self,
        in_channels: int,
        window: int,
        features: int,
        channels: Sequence[int] = (100, 100),
        kernels: Sequence[int] = (50, 10),
        strides: Sequence[int] = (2, 2),
        hidden: Sequence[int] = (100,),
        scale_channel: int = 1,
        noise_features: bool = False,
    ) -> None:
        super().__init__()
        learned = features - (in_channels if noise_features else 0)
        if learned < 1:
            raise ConfigError(f"sbi.features={features} leaves no CNN summaries beside {in_channels} noise summaries")
        self.cnn = ParameterCNN(in_channels, window, channels, kernels, strides, hidden, out_features=learned)
        self.noise_features = bool(noise_features)
        self.scale_channel = int(scale_channel)
        self.register_buffer("in_mean", torch.zeros(in_channels))
        self.register_buffer("in_std", torch.ones(in_channels))

    def scaled(self, x: Tensor) -> Tensor:
        """x [B, C, N] divided by each sample's RMS of the scale channel."""
        scale = x[:, self.scale_channel].pow(2).mean(-1).sqrt().clamp_min(1e-12)
        return x / scale[:, None, None]

    def forward(self, x: Tensor) -> Tensor:
        scaled = self.scaled(x)
        z = (scaled - self.in_mean[:, None]) / self.in_std[:, None]
        if not self.noise_features:
            return self.cnn(z)
        rough = scaled.diff(n=2, dim=-1).pow(2).mean(-1).sqrt() / scaled.pow(2).mean(-1).sqrt().clamp_min(1e-12)
        return torch.cat([self.cnn(z), rough.clamp_min(1e-12).log10()], -1)


@dataclass(frozen=True)
class PeerSettings:
    """Hyper-parameters of the peer (plain data; stored in the checkpoint)."""

    params: tuple[str, ...] = ("p1", "p2")
    channels: tuple[str, ...] = ("a3", "a2")
    window: int = 500
    features: int = 20  # embedding summaries handed to the flow
    noise_features: bool = True  # the last len(channels) summaries read the noise level (see Embedding)
    cnn_channels: tuple[int, ...] = (100, 100)
    cnn_kernels: tuple[int, ...] = (50, 10)
    cnn_strides: tuple[int, ...] = (2, 2)
    cnn_hidden: tuple[int, ...] = (100,)
    flow: str = "nsf"
    hidden_features: int = 50
    num_transforms: int = 5
    degenerate_tol: float = 1e-6
    latent_dim: int = 0  # K, set from the training data (0 = not fitted yet)

    def validate(self) -> PeerSettings:
        bad = [p for p in self.params if p not in PARAM_NAMES]
        if bad or not self.params or len(set(self.params)) != len(self.params):
            raise ConfigError(f"sbi.params={list(self.params)}: choose distinct names from {list(PARAM_NAMES)}")
        bad = [c for c in self.channels if c not in CHANNELS]
        if bad or not self.channels:
            raise ConfigError(f"sbi.channels={list(self.channels)}: choose from {list(CHANNELS)}")
        if self.flow not in FLOWS:
            raise ConfigError(f"sbi.flow={self.flow!r}: choose one of {sorted(FLOWS)}")
        for key in ("window", "features", "hidden_features", "num_transforms"):
            if int(getattr(self, key)) < 1:
                raise ConfigError(f"sbi.{key}={getattr(self, key)!r} must be >= 1")
        return self

    @classmethod
    def from_mapping(cls, data: Mapping) -> PeerSettings:
        unknown = sorted(set(data) - set(cls.__dataclass_fields__))
        if unknown:
            raise ConfigError(f"sbi: unknown setting(s) {unknown}; known: {sorted(cls.__dataclass_fields__)}")
        values = {k: tuple(v) if isinstance(v, (list, tuple)) else v for k, v in dict(data).items()}
        return cls(**values).validate()


class SBIPeer(nn.Module):
    """Amortised posterior over `settings.params` given raw (a3, a2) windows [B, C, window].

    Build with `SBIPeer.fit_spaces(settings, accel, params)` (fits the parameter spaces and the
    input normalisation on training data) or `SBIPeer.load(path)`.
    """

    def __init__(self, settings: PeerSettings) -> None:
        super().__init__()
        import_sbi()
        from sbi.neural_nets.net_builders import flow as builders

        settings = settings.validate()
        if settings.latent_dim < 1:
            raise ConfigError("SBIPeer: latent_dim is not set; build it with SBIPeer.fit_spaces(...)")
        self.settings = settings
        P, K, C = len(settings.params), settings.latent_dim, len(settings.channels)
        embedding = Embedding(
            C,
            settings.window,
            settings.features,
            settings.cnn_channels,
            settings.cnn_kernels,
            settings.cnn_strides,
            settings.cnn_hidden,
            scale_channel=settings.channels.index("a2") if "a2" in settings.channels else 0,
            noise_features=settings.noise_features,
        )
        build = getattr(builders, FLOWS[settings.flow])
        # Dummy batches only give the shapes: z-scoring is ours (buffers), so the values never matter.
        self.flow = build(
            torch.randn(8, K),
            torch.randn(8, C, settings.window),
            z_score_x="none",
            z_score_y="none",
            hidden_features=settings.hidden_features,
            num_transforms=settings.num_transforms,
            embedding_net=embedding,
        )
        self.register_buffer("log_mean", torch.zeros(P, dtype=torch.float64))
        self.register_buffer("log_std", torch.ones(P, dtype=torch.float64))
        self.register_buffer("basis", torch.eye(P, K, dtype=torch.float64))  # V_K [P, K]
        self.register_buffer("basis_scale", torch.ones(K, dtype=torch.float64))  # s_K [K]
        self.columns = [PARAM_NAMES.index(p) for p in settings.params]
        self.inputs = [CHANNELS.index(c) for c in settings.channels]

    # -- spaces -----------------------------------------------------------------------------------
    @classmethod
    def fit_spaces(cls, settings: PeerSettings, accel: Tensor, params: Tensor) -> SBIPeer:
        """A fresh peer whose spaces come from training data: accel [M, T, 3] (m/s²), params [M, 10]."""
        settings = settings.validate()
        columns = [PARAM_NAMES.index(p) for p in settings.params]
        p = params.to(torch.float64)[:, columns]
        if not bool((p > 0).all()) or not bool(torch.isfinite(p).all()):
            raise ConfigError("SBIPeer.fit_spaces: training parameters must be finite and > 0")
        logs = p.log()
        mean, std = logs.mean(0), logs.std(0).clamp_min(1e-12)
        z = (logs - mean) / std
        _, s, vh = torch.linalg.svd(z - z.mean(0), full_matrices=False)
        keep = s > settings.degenerate_tol * s[0]
        K = int(keep.sum())
        peer = cls(PeerSettings(**{**asdict(settings), "latent_dim": K}))
        peer.log_mean.copy_(mean)
        peer.log_std.copy_(std)
        peer.basis.copy_(vh[:K].T)
        peer.basis_scale.copy_(s[:K] / math.sqrt(z.shape[0]))
        x = peer.inputs_of(accel)
        emb = peer.embedding
        scaled = emb.scaled(x.double())
        emb.in_mean.copy_(scaled.mean((0, 2)).float())
        emb.in_std.copy_(scaled.std((0, 2)).clamp_min(1e-12).float())
        return peer

    @property
    def embedding(self) -> Embedding:
        return self.flow.embedding_net if hasattr(self.flow, "embedding_net") else self.flow._embedding_net

    def normalise(self, params: Tensor) -> Tensor:
        """params [..., 10] (all ten) -> z [..., P] of the peer's parameters."""
        return (params.to(torch.float64)[..., self.columns].log() - self.log_mean) / self.log_std

    def to_latent(self, z: Tensor) -> Tensor:
        """z [..., P] -> u [..., K]."""
        return (z.to(torch.float64) @ self.basis) / self.basis_scale

    def from_latent(self, u: Tensor) -> Tensor:
        """u [..., K] -> z [..., P] (on the prior's support)."""
        return (u.to(torch.float64) * self.basis_scale) @ self.basis.T

    def to_params(self, z: Tensor) -> Tensor:
        """z [..., P] -> the peer's parameters p [..., P] (physical units)."""
        return (z.to(torch.float64) * self.log_std + self.log_mean).exp()

    def inputs_of(self, accel: Tensor) -> Tensor:
        """accel [B, T ≥ window, 3] -> x [B, C, window] float32 (the first `window` steps of the peer's channels)."""
        w = self.settings.window
        if accel.ndim != 3 or accel.shape[-1] != 3 or accel.shape[1] < w:
            raise ConfigError(f"SBIPeer: accel must be [B, T >= {w}, 3], got {tuple(accel.shape)}")
        return accel[:, :w, self.inputs].transpose(1, 2).float().contiguous()

    # -- training and sampling --------------------------------------------------------------------
    def loss(self, u: Tensor, x: Tensor) -> Tensor:
        """NPE loss per sample [B]: −log q(u | x), u [B, K], x [B, C, window]."""
        return self.flow.loss(u.float(), condition=x)

    @torch.no_grad()
    def sample_batched(self, sample_shape, x: Tensor, show_progress_bars: bool = False, chunk: int = 256) -> Tensor:
        """Posterior samples in normalised space z [*sample_shape, B, P] (float32) for x [B, C, window].

        Named and shaped like sbi's NeuralPosterior.sample_batched, so sbi's run_sbc / run_tarp take the peer."""
        shape = torch.Size(sample_shape)
        out = []
        for start in range(0, x.shape[0], chunk):
            u = self.flow.sample(shape, condition=x[start : start + chunk])  # [*shape, b, K]
            out.append(self.from_latent(u).float())
        return torch.cat(out, dim=len(shape))

    @torch.no_grad()
    def sample_params(self, n: int, x: Tensor, chunk: int = 256) -> Tensor:
        """Posterior samples of the peer's parameters in physical units [n, B, P] (float64)."""
        return self.to_params(self.sample_batched((n,), x, chunk=chunk).double())

    # -- saving ------------------------------------------------------------------------------------
    def checkpoint(self) -> dict:
        """Tensors and plain data only (loadable with weights_only=True)."""
        hparams = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self.settings).items()}
        return {"hybridqcm_class": CLASS_NAME, "hyper_parameters": hparams, "state_dict": self.state_dict()}

    def save(self, path: str | os.PathLike) -> Path:
        """Write the checkpoint atomically (temporary file beside it, renamed into place)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        os.close(fd)
        try:
            torch.save(self.checkpoint(), tmp)
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, config_key: str | None = None) -> SBIPeer:
        """The peer stored at `path` (eval mode); CheckpointError (one line) for anything else."""
        from hybridqcm.models.untrusted import check_config_tree, read_raw

        path = Path(path)
        where = f"{config_key}={path}" if config_key else str(path)
        raw = read_raw(path, where)
        if raw.get("hybridqcm_class") != CLASS_NAME:
            stored = raw.get("hybridqcm_class")
            raise CheckpointError(f"{where}: holds {stored or 'a non-hybridqcm'} checkpoint, not an {CLASS_NAME}")
        hparams = raw.get("hyper_parameters")
        if not isinstance(hparams, Mapping):
            raise CheckpointError(f"{where}: hyper_parameters missing or not a mapping")
        check_config_tree(dict(hparams), where)
        try:
            settings = PeerSettings.from_mapping(hparams)
        except (ConfigError, TypeError) as error:
            raise CheckpointError(f"{where}: hyper_parameters refused ({error})") from None
        peer = cls(settings)
        state = raw.get("state_dict")
        if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
            raise CheckpointError(f"{where}: state_dict is missing or holds non-tensor values")
        own = peer.state_dict()
        missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
        bad = [k for k in own if k in state and state[k].shape != own[k].shape]
        if missing or unexpected or bad:
            raise CheckpointError(
                f"{where}: state_dict does not match {CLASS_NAME}: missing {missing[:3]}, unexpected "
                f"{unexpected[:3]}, mis-shaped {bad[:3]}"
            )
        peer.load_state_dict(state, strict=True)
        return peer.eval()


# -- training -----------------------------------------------------------------------------------------
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


# -- evaluation ---------------------------------------------------------------------------------------
def central_interval(samples: Tensor, level: float = 0.95) -> tuple[Tensor, Tensor]:
    """(low, high) [B, ...] of samples [S, B, ...]: the central `level` interval of each marginal."""
    tail = (1 - level) / 2
    q = torch.quantile(samples.double(), torch.tensor([tail, 1 - tail], dtype=torch.float64), dim=0)
    return q[0], q[1]


def posterior_summary(peer: SBIPeer, x: Tensor, n_samples: int = 1000, K3: float = 98935.0, chunk: int = 256) -> dict:
    """Per recording x [B, C, window]: posterior medians, means and central 95 % intervals of the
    peer's parameters ([B, P] each) and of m3 = K3/p2 ([B]) when p2 is among them. Medians are the
    point estimates (m3 = K3/p2 is monotone, so m3's median is K3 / p2's median)."""
    out: dict[str, list] = {
        k: [] for k in ("median", "mean", "low", "high", "m3_median", "m3_mean", "m3_low", "m3_high")
    }
    j2 = peer.settings.params.index("p2") if "p2" in peer.settings.params else None
    for start in range(0, x.shape[0], chunk):
        s = peer.sample_params(n_samples, x[start : start + chunk], chunk=chunk)  # [S, b, P]
        low, high = central_interval(s)
        out["median"].append(s.median(0).values)
        out["mean"].append(s.mean(0))
        out["low"].append(low)
        out["high"].append(high)
        if j2 is not None:
            m3 = K3 / s[..., j2]
            m3_low, m3_high = central_interval(m3)
            out["m3_median"].append(m3.median(0).values)
            out["m3_mean"].append(m3.mean(0))
            out["m3_low"].append(m3_low)
            out["m3_high"].append(m3_high)
    return {k: torch.cat(v) for k, v in out.items() if v}


def evaluation_row(summary: Mapping[str, Tensor], true: Tensor, names: Sequence[str], K3: float = 98935.0) -> dict:
    """Metrics of one posterior summary against the true params [B, 10]; column names as qcm-estimate's summary.

    m3_* errors use the posterior median; coverage: fraction of truths inside the central 95 % interval;
    interval width relative to the truth (median over samples)."""
    row: dict = {"n": int(true.shape[0])}
    true = true.to(torch.float64)
    for j, name in enumerate(names):
        t = true[:, PARAM_NAMES.index(name)]
        err = (summary["median"][:, j] - t).abs() / t
        row[f"{name}_mean_rel_err"] = float(err.mean())
        row[f"{name}_coverage_95"] = float(((summary["low"][:, j] <= t) & (t <= summary["high"][:, j])).double().mean())
        row[f"{name}_interval_median_rel_width"] = float(((summary["high"][:, j] - summary["low"][:, j]) / t).median())
    if "m3_median" in summary:
        t = K3 / true[:, 1]
        err = (summary["m3_median"] - t).abs() / t
        row["m3_mean_rel_err"] = float(err.mean())
        row["m3_p95_rel_err"] = float(err.quantile(0.95))
        row["m3_within_1pct"] = float((err <= 0.01).double().mean())
        row["m3_coverage_95"] = float(((summary["m3_low"] <= t) & (t <= summary["m3_high"])).double().mean())
        row["m3_interval_median_rel_width"] = float(((summary["m3_high"] - summary["m3_low"]) / t).median())
    return row


def rank_statistics(peer: SBIPeer, x: Tensor, z_true: Tensor, n_samples: int = 500) -> dict:
    """SBC ranks [B, P] (sbi's run_sbc) and TARP (ecp, alpha) (sbi's run_tarp) on held-out (z_true [B, P], x).

    Also the checks: KS p-values of rank uniformity per parameter, C2ST of the data-averaged
    posterior vs the prior (sbi's check_sbc), and TARP's ATC and KS p-value (check_tarp)."""
    import_sbi()
    from sbi.diagnostics import check_sbc, check_tarp, run_sbc, run_tarp

    z_true = z_true.float()
    ranks, dap = run_sbc(z_true, x, peer, num_posterior_samples=n_samples, show_progress_bar=False)
    sbc = check_sbc(ranks, z_true, dap, num_posterior_samples=n_samples)
    ecp, alpha = run_tarp(z_true, x, peer, num_posterior_samples=n_samples, show_progress_bar=False)
    atc, ks = check_tarp(ecp, alpha)
    return {
        "ranks": ranks,
        "ks_pvals": sbc["ks_pvals"],
        "c2st_ranks": sbc["c2st_ranks"],
        "c2st_dap": sbc["c2st_dap"],
        "ecp": ecp,
        "alpha": alpha,
        "tarp_atc": float(atc),
        "tarp_ks_pval": float(ks),
    }


def seconds_per_1000(peer: SBIPeer, x: Tensor, n_samples: int = 1000, K3: float = 98935.0) -> float:
    """Wall time of `posterior_summary` (embedding, n_samples draws, intervals) per 1 000 recordings."""
    t0 = time.perf_counter()
    posterior_summary(peer, x, n_samples=n_samples, K3=K3)
    return (time.perf_counter() - t0) * 1000.0 / x.shape[0]


def as_numpy_rows(rows: Sequence[Mapping], columns: Sequence[str]) -> list[list]:
    """Rows for atomic_write_csv: one list per mapping in `columns` order (repr for floats)."""
    return [
        [repr(float(r[c])) if isinstance(r.get(c), (float, np.floating)) else r.get(c, "") for c in columns]
        for r in rows
    ]


__all__ = [
    "SBIPeer",
    "PeerSettings",
    "TrainSettings",
    "Embedding",
    "import_sbi",
    "train_peer",
    "noisy",
    "log_uniform",
    "central_interval",
    "posterior_summary",
    "evaluation_row",
    "rank_statistics",
    "seconds_per_1000",
    "FLOWS",
]
