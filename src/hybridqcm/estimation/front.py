"""The network front of the hybrid estimator (SPEC §7 exps 6-10): checkpoints in, the GN problem out.

    (â3, â2) --CAE?--> (a3, a2) --U-Net?--> completed (a2, a1) from (a3, p_u u)
             --CNN--> (p1, p2) initial values --> the batch's Gauss-Newton problem

:class:`HybridEstimator` is a LightningModule composed from checkpoint paths (read through the safe
loader); its predict/test step runs the networks and returns the GN problem of the batch, which the
callback of :mod:`hybridqcm.estimation.refinement` solves.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping, Sequence

import torch
from lightning.pytorch import LightningModule
from torch import Tensor

from hybridqcm.errors import CheckpointError
from hybridqcm.models.checkpoint import load_checkpoint
from hybridqcm.physics.parameters import CHANNELS

from .fusion import check_cnn_prior, network_prior
from .sensitivity import N_PARAMS

# Road-free (base-excitation) models: the measured channel that drives the model, the channels it
# predicts, and how many of p1.. it holds (SPEC §9; physics.linear_models).
BASE_EXCITATION = {"seat": ("a2", ("a3",), 2), "sprung": ("a1", ("a3", "a2"), 6)}


def check_networks(cnn=None, unet=None, cae=None, h: float | None = None) -> None:
    """What each network predicts must be what the estimator uses it for; CheckpointError otherwise.

    CNN: inputs (a3, a2) -> targets (p1, p2); U-Net: (a3, pu_u) -> (a2, a1); CAE: (a3, a2).
    All: trained at the data's step h (when given) under Euler physics the GN model shares."""
    if cae is not None and list(cae.hparams.channels) != ["a3", "a2"]:
        raise CheckpointError(f"cae_ckpt: denoiser channels {list(cae.hparams.channels)}, expected ['a3', 'a2']")
    if unet is not None and (
        list(unet.hparams.input_channels) != ["a3", "pu_u"] or list(unet.hparams.target_channels) != ["a2", "a1"]
    ):
        raise CheckpointError(
            "unet_ckpt: completion U-Net must map (a3, pu_u) -> (a2, a1), got "
            f"{list(unet.hparams.input_channels)} -> {list(unet.hparams.target_channels)}"
        )
    if cnn is not None and list(cnn.hparams.input_channels) != ["a3", "a2"]:
        raise CheckpointError(f"cnn_ckpt: estimator inputs {list(cnn.hparams.input_channels)}, expected ['a3', 'a2']")
    if cnn is not None and list(cnn.hparams.target_channels) != ["p1", "p2"]:
        raise CheckpointError(
            f"cnn_ckpt: estimator targets {list(cnn.hparams.target_channels)}, but the initialiser needs ['p1', 'p2']"
        )
    for key, net in (("cnn_ckpt", cnn), ("unet_ckpt", unet), ("cae_ckpt", cae)):
        if net is None:
            continue
        physics = net.hparams.get("physics", "euler")
        if physics != "euler":
            raise CheckpointError(f"{key}: trained under physics = {physics!r}, but GN fits the Euler model (euler)")
        if h is not None and abs(float(net.hparams.get("h", 0.01)) - float(h)) > 1e-9 * float(h):
            raise CheckpointError(f"{key}: trained at h = {net.hparams.get('h', 0.01)} s, but the data have h = {h} s")


# ----------------------------------------------------------------------------------------------
def equation_error_params(
    accel: Tensor, road: Tensor, h: float, fallback: Tensor, known: Tensor, scaled_road: bool = False
) -> Tensor:
    """Parameters from accelerations of all three bodies by linear least squares ("equation error").

    Integrating the accelerations with the model's own Euler recursion (from rest) gives v_k, q_k
    exactly for noise-free data, and a_k = D v_k + S q_k + b_k is linear in p, row by row. With
    noisy or network-completed accelerations the states drift, so this is an initialiser for GN.
    accel [batch, time, 3], road [batch, time] (u, or p_u u if ``scaled_road``), fallback [batch, 10]
    (used for known parameters and wherever the fit is not positive/finite) -> p [batch, 10].
    """
    accel = accel.double()
    road = road.double()
    batch, n_steps, _ = accel.shape
    vel = torch.zeros_like(accel)
    disp = torch.zeros_like(accel)
    v = torch.zeros(batch, 3, dtype=torch.float64, device=accel.device)
    q = torch.zeros_like(v)
    for k in range(n_steps):  # v_k, q_k as recorded at step k (same convention as the generator)
        vel[:, k], disp[:, k] = v, q
        v = v + h * accel[:, k]
        q = q + h * v
    v3, v2, v1 = vel.unbind(-1)
    q3, q2, q1 = disp.unbind(-1)
    a3, a2, a1 = accel.unbind(-1)
    p = fallback.double().clone()
    zeros = torch.zeros_like(road)
    forcing_known = road if scaled_road else zeros
    u = zeros if scaled_road else road
    rows = [  # (parameter indices, regressors c_j [batch, time], target)
        ((0, 1), (v2 - v3, q2 - q3), a3),
        ((2, 3, 4, 5), (v3 - v2, v1 - v2, q3 - q2, q1 - q2), a2),
        ((6, 7, 8, 9), (v2, -v1, q2 - u, u - q1), a1 - forcing_known),
    ]
    for index, regressors, target in rows:
        free = [j for j, i in enumerate(index) if not bool(known[i])]
        if not free:
            continue
        design = torch.stack(regressors, -1)  # [batch, time, n]
        rhs = target.clone()
        for j, i in enumerate(index):
            if bool(known[i]):
                rhs = rhs - p[:, i, None] * design[..., j]
        design = design[..., free]
        scale = design.square().sum(1).sqrt().clamp_min(1e-300)  # column scaling, as in GN
        solution = torch.linalg.lstsq(design / scale[:, None, :], rhs.unsqueeze(-1)).solution.squeeze(-1) / scale
        cols = [index[j] for j in free]
        ok = torch.isfinite(solution).all(1) & (solution > 0).all(1)
        p[:, cols] = torch.where(ok[:, None], solution, p[:, cols])
    return p


@contextlib.contextmanager
def full_fp32_convolutions() -> Iterator[None]:
    """cuDNN convolutions in full float32 inside the block; torch's default lets them use TF32."""
    before = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32 = before


# ----------------------------------------------------------------------------------------------
class HybridEstimator(LightningModule):
    """Networks in front of Gauss-Newton, composed from checkpoint paths (each optional).

    Batch contract (dict): ``accel`` [batch, time, 3] (a3, a2, a1; unobserved channels are never
    read), ``road`` [batch, time] u in metres, ``pu`` [batch] p_u (needed by the U-Net),
    ``init`` [batch, 10] initial parameters (known ones already at their values), ``index``.
    ``time`` may exceed ``n_steps``: the networks see the whole window they need, GN the first
    ``n_steps``. predict_step returns the GN problem of the batch: ``targets`` [batch, n_steps, 3]
    (observed channels, completed ones where the U-Net filled them in), ``road``, ``pu``, ``init``.
    """

    def __init__(
        self,
        cnn_ckpt: str | None = None,
        unet_ckpt: str | None = None,
        cae_ckpt: str | None = None,
        observed: Sequence[str] = CHANNELS,
        n_steps: int = 100,
        h: float = 0.01,
        cnn_init: bool = True,
        equation_error_init: bool = False,
        known: Sequence[str] = (),
        pu_known: bool = True,
        cnn_a2_from_data: bool = False,
        base_excitation: str | None = None,
        input_margin: Sequence[int] = (0, 0),
        cnn_prior_rel_std: float | None = None,
        cnn_prior: str | None = None,
        cnn_prior_scale: float = 1.0,
    ):
        super().__init__()
        # (before, after): input samples around the GN window handed to the model with it — the
        # exact model interpolates the road through them, so its window edges are as accurate as
        # its interior. The window then starts `before` samples into the recording.
        self.input_margin = tuple(int(m) for m in input_margin)
        if len(self.input_margin) != 2 or min(self.input_margin) < 0:
            raise ValueError(f"input_margin must be two sample counts >= 0 (before, after), got {list(input_margin)}")
        if base_excitation is not None and base_excitation not in BASE_EXCITATION:
            raise ValueError(f"base_excitation={base_excitation!r}: choose one of {sorted(BASE_EXCITATION)} (or none)")
        self.base_excitation = base_excitation
        self.observed = tuple(observed)
        unknown = [c for c in self.observed if c not in CHANNELS]
        if unknown or not self.observed:
            raise ValueError(f"observed channels must be a non-empty subset of {CHANNELS}, got {list(observed)}")
        self.n_steps, self.h = int(n_steps), float(h)
        self.cnn = load_checkpoint(cnn_ckpt, "cnn", "cnn_ckpt") if cnn_ckpt else None
        self.unet = load_checkpoint(unet_ckpt, "unet", "unet_ckpt") if unet_ckpt else None
        self.cae = load_checkpoint(cae_ckpt, "cae", "cae_ckpt") if cae_ckpt else None
        self.cnn_init = bool(cnn_init) and self.cnn is not None
        self.equation_error_init = bool(equation_error_init)
        self.pu_known = bool(pu_known)
        # a2 unobserved and not completed: may the CNN initialiser still read the batch's a2?
        self.cnn_a2_from_data = bool(cnn_a2_from_data)
        # Fusion (MAP): the CNN's p1, p2 also enter the last GN stage as a Gaussian prior with this
        # relative std (None: the CNN only starts GN). The residuals must be in noise units for
        # the balance to mean anything: use it with residual re-weighting.
        self.cnn_prior_rel_std = None if cnn_prior_rel_std is None else float(cnn_prior_rel_std)
        # Fusion with the network's own variance (estimation/fusion.py): cnn_prior="network".
        check_cnn_prior(cnn_prior, self.cnn if self.cnn_init else None, self.cnn_prior_rel_std)
        self.cnn_prior, self.cnn_prior_scale = cnn_prior, float(cnn_prior_scale)
        known_mask = torch.zeros(N_PARAMS, dtype=torch.bool)
        for name in known:
            known_mask[int(str(name).lstrip("p")) - 1] = True
        self.register_buffer("known_mask", known_mask, persistent=False)
        check_networks(self.cnn, self.unet, self.cae, self.h)

    # -- what the pipeline needs ---------------------------------------------------------------
    @property
    def completes(self) -> bool:
        """True when unobserved a2/a1 are filled in by the U-Net."""
        return self.unet is not None and not {"a2", "a1"} <= set(self.observed)

    def required_steps(self) -> int:
        """Steps of input the networks and GN need (the CNN reads ``window`` steps)."""
        need = self.input_margin[0] + self.n_steps
        if self.cnn_init:
            need = max(need, int(self.cnn.hparams.window))
        return need

    def gn_channels(self) -> tuple[bool, bool, bool]:
        """Channels with data for GN: observed ones plus completed ones."""
        return tuple((c in self.observed) or (self.completes and c in ("a2", "a1")) for c in CHANNELS)

    # -- the network part -----------------------------------------------------------------------
    def prepare(self, batch: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """The batch's GN problem (class docstring). The networks run in full float32 on a GPU too:
        TF32 convolutions moved their outputs ~1e-4 from the CPU's on an H100, and GN's path (restarts,
        noise model, intervals) with them; float32 made it ~2e-7 (docs/measurements/scaling.md)."""
        with full_fp32_convolutions():
            return self._prepare(batch)

    @torch.no_grad()
    def _prepare(self, batch: Mapping[str, Tensor]) -> dict[str, Tensor]:
        accel = batch["accel"].double().clone()
        road = (
            batch["road"].double()
            if batch.get("road") is not None
            else torch.zeros(accel.shape[:2], dtype=torch.float64, device=accel.device)
        )
        pu = batch["pu"].double()
        init = batch["init"].double().clone()
        if accel.shape[1] < self.required_steps():
            raise ValueError(
                f"the pipeline needs {self.required_steps()} steps of input, the batch has {accel.shape[1]}"
            )
        a2_observed = "a2" in self.observed
        if self.completes:
            accel[:, :, 1:] = (
                self.unet.complete(accel[:, :, 0].float(), (pu[:, None] * road).float()).double().transpose(1, 2)
            )
        if self.cae is not None:
            if not a2_observed and not self.completes:
                raise ValueError("the CAE denoises (a3, a2): a2 must be observed or completed by the U-Net")
            denoised = self.cae.denoise(accel[:, :, :2].transpose(1, 2).float()).double().transpose(1, 2)
            accel[:, :, 0] = denoised[:, :, 0]
            if a2_observed:
                accel[:, :, 1] = denoised[:, :, 1]
            if self.completes:  # complete again from the denoised a3
                accel[:, :, 1:] = (
                    self.unet.complete(accel[:, :, 0].float(), (pu[:, None] * road).float()).double().transpose(1, 2)
                )
        if self.cnn_init:
            if not a2_observed and not self.completes and not self.cnn_a2_from_data:
                raise ValueError("the CNN initialiser reads a2: observe a2 or give a U-Net (unet_ckpt) to complete it")
            p12 = self.cnn.estimate(accel[:, :, 0].float(), accel[:, :, 1].float()).double()
            keep = self.known_mask[:2]
            init[:, :2] = torch.where(keep, init[:, :2], p12)
            cnn_p12 = p12
            if self.cnn_prior == "network":
                network = network_prior(self.cnn, accel[:, :, 0], accel[:, :, 1], self.cnn_prior_scale)
        if not self.cnn_init:
            cnn_p12 = None
        before, after = self.input_margin
        stop = min(accel.shape[1], before + self.n_steps + after)
        signals, road_in = accel[:, :stop], road[:, :stop]  # the model's inputs, margins included
        accel = accel[:, before : before + self.n_steps]
        road = road[:, before : before + self.n_steps]
        if self.equation_error_init:
            if not all(self.gn_channels()):
                raise ValueError("equation-error initialisation needs all three accelerations (observed or completed)")
            # p_u known: the forcing is data (scaled road); otherwise p9, p10 carry it.
            forcing = pu[:, None] * road if self.pu_known else road
            init = equation_error_params(accel, forcing, self.h, init, self.known_mask, scaled_road=self.pu_known)
        prepared = {
            "targets": accel,
            "road": road_in,
            "pu": pu,
            "init": init,
            "index": batch["index"],
            "input_offset": before,
        }
        if cnn_p12 is not None and self.cnn_prior_rel_std:
            prepared["prior_p12"] = cnn_p12
            prepared["prior_p12_std"] = self.cnn_prior_rel_std * cnn_p12.abs()
        if self.cnn_init and self.cnn_prior == "network":
            prepared.update(network)
        if batch.get("noise_sigma") is not None and float(batch["noise_sigma"].max()) > 0:
            # Noise-aware weighting for multiplicative noise a(1 + η): a channel's noise std is
            # σ·rms(a_c), so weights 1/(σ rms_c) standardise every channel (completed ones too,
            # whose error is unknown: they get the same rule, which only balances their scale).
            rms = accel.square().mean(1).sqrt().clamp_min(1e-12)  # [batch, 3]
            prepared["weights"] = 1.0 / (batch["noise_sigma"].double()[:, None] * rms)
        if batch.get("noise_std") is not None:  # a known sensor noise floor per channel [batch, 3]
            prepared["weights"] = 1.0 / batch["noise_std"].double()
        if self.base_excitation is not None:
            # The measured driving channel becomes the model's input, the rest its targets.
            driver, outputs, n_params = BASE_EXCITATION[self.base_excitation]
            columns = [CHANNELS.index(c) for c in outputs]
            prepared.update(
                targets=accel[:, :, columns], road=signals[:, :, CHANNELS.index(driver)], init=init[:, :n_params]
            )
            if "weights" in prepared:
                prepared["weights"] = prepared["weights"][:, columns]
        return prepared

    def forward(self, batch: Mapping[str, Tensor]) -> dict[str, Tensor]:
        return self.prepare(batch)

    def predict_step(self, batch: Mapping[str, Tensor], batch_idx: int = 0) -> dict[str, Tensor]:
        return self.prepare(batch)

    def test_step(self, batch: Mapping[str, Tensor], batch_idx: int = 0) -> dict[str, Tensor]:
        return self.prepare(batch)
