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

Training: estimation/sbi_training.py; evaluation: estimation/sbi_evaluation.py.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from hybridqcm.atomic import replacing
from hybridqcm.errors import CheckpointError, ConfigError
from hybridqcm.models.networks import ParameterCNN
from hybridqcm.physics.parameters import CHANNELS, PARAM_NAMES

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
        with replacing(path) as tmp:  # the folder made if missing
            torch.save(self.checkpoint(), tmp)
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


__all__ = ["SBIPeer", "PeerSettings", "Embedding", "import_sbi", "FLOWS"]
