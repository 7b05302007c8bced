"""Noise weighting of the refinement's last stage when nobody knows the sensor noise
(:class:`NoiseWeighting`, the settings; :class:`NoiseFit`, the noise model fitted to a residual).

``mode``: False: unweighted; "channels" (or True): each channel's residual weighted by 1/σ̂_c, σ̂_c its RMS
residual at the previous stage's estimate; "spectral": the frequency-domain noise model of
estimation/noise.py — output noise per channel and, for base-excitation models, the measured driving
channel's noise through H(p) (errors in variables), variances fitted to the residual; the last stage runs
``passes`` times with the noise spectrum held at the previous estimate (reweighted least squares), then
once as the errors-in-variables maximum likelihood (spectrum a function of p), guarded by ``ml_guard``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .noise import SpectralNoise, estimate_variances, frequency_response, input_noise_log_std, spectral_leverage
from .problems import LeastSquaresProblem
from .response import PreparedInputs, ResponseModel
from .restarts import take_samples
from .solver import SolverResult, SolverStatus

if TYPE_CHECKING:
    from .refinement import GaussNewtonRefinement

# A noise model is consistent with a fit when the whitened loss is within this factor of its expectation
# (white noise of 500 samples leaves it within a few per cent; a misfit's variance is off by orders).
_NOISE_CONSISTENCY = 2.0
MODES = (False, True, "channels", "spectral")


@dataclass
class NoiseWeighting:
    """How the last stage weighs its residual (module docstring).

    passes: reweighted passes before the maximum-likelihood one (spectral). ml_guard: the maximum-likelihood
    estimate is kept only where it stays within ml_guard of the reweighted one's standard deviations (None:
    always): with variances fitted to a poor residual it can run to a spurious optimum (a rigid or very
    resonant seat that blames the fit on input noise). refits: each pass fits the noise variances to the
    residual at its start; where that start was far from the data (the window continuation's short-window
    fit seen over the whole window), the variance is the misfit's, up to 10^5 times the noise: the data then
    weigh next to nothing against a prior and the intervals are as wide. A sample whose whitened loss at the
    end of the stage is not what its noise model predicts (within a factor _NOISE_CONSISTENCY) gets up to
    ``refits`` more maximum-likelihood passes with the variances fitted again at its estimate.
    min_input_noise: relative to the input's RMS, the floor below which an input "noise" is the hold's
    interpolation error (NoiseFit.noise_model), and the sensor-noise floor of NoiseFit.noise_floor.
    leverage: the noise variances fitted to a residual at the fit are short by the fit's leverage, most
    where the input's noise shows (estimate_variances): the restricted fit corrects it.
    band_cap: a measured input's noise variance is at most its own power in the upper half of the spectrum
    (input_band_power): white sensor noise fills that band, anything else there (vibration) only adds, so
    the bound holds for any recording and needs no model. The Whittle fit reads the input's noise from the
    residual's excess where |H| is large — the resonance, exactly where a fit in a wrong basin leaves its
    misfit — and there gave 2–5 times the true variance; with it the errors-in-variables cost, whose
    per-frequency weight 1 / (v_out + |H|² v_in) then undercounts the resonance, prefers that wrong basin
    (docs/measurements/persons.md).
    """

    mode: bool | str = False
    passes: int = 1
    ml_guard: float | None = 4.0
    min_input_noise: float = 1e-3
    refits: int = 2
    leverage: bool = False
    # False: the driving inputs are known exactly (a road-driven vehicle: its road is simulated or given),
    # so the spectral noise model is white output noise per channel only; the base-excitation models'
    # errors-in-variables term is for a *measured* driving channel.
    input_noise: bool = True
    band_cap: bool = False

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"reweight={self.mode!r}: choose false, true/'channels' or 'spectral'")
        self.mode = "channels" if self.mode is True else self.mode
        self.passes = max(1, int(self.passes))
        if int(self.refits) < 0:
            raise ValueError(f"noise_refits must be >= 0, got {self.refits!r}")
        self.refits = int(self.refits)
        self.leverage = bool(self.leverage)
        self.band_cap = bool(self.band_cap)
        self.ml_guard = None if self.ml_guard is None else float(self.ml_guard)
        self.min_input_noise = float(self.min_input_noise)


class NoiseFit:
    """Residuals and noise models of ``response``'s fits (sample interval ``h``; ``known`` [n_theta] bool,
    the entries held fixed; ``quarter_car``: outputs (a3, a2, a1) driven by the road, output noise only)."""

    def __init__(self, response: ResponseModel, h: float, known: Tensor, settings: NoiseWeighting, quarter_car: bool):
        self.response = response
        self.h = h
        self.known = known
        self.settings = settings
        self.quarter_car = quarter_car

    def residual(self, targets: Tensor, inputs, params: Tensor, observed, offset: int) -> Tensor:
        """Prediction minus data on the observed channels, [b, T, n_observed] (non-finite entries 0)."""
        channels = [i for i, o in enumerate(observed) if o]
        predicted = self.response.outputs(params.double(), inputs, offset, targets.shape[1])
        residual = predicted[:, :, channels] - targets[:, :, channels]
        return torch.where(torch.isfinite(residual), residual, torch.zeros_like(residual))

    def noise_floor(self, residual: Tensor, targets: Tensor, observed) -> Tensor:
        """[batch] bool: the first observed output (a3 where measured: the one the vehicle filters most)
        has a noise floor above ``min_input_noise`` of its RMS, measured on its ``residual`` (NoiseFit.residual)
        in the upper half of the spectrum (a quarter of the sampling rate to Nyquist). An accelerometer's
        noise is white and fills that band; the seat's response to the road has next to nothing there,
        so neither a poor fit's misfit (at the resonances; the wheel's, driven by the road up to its
        band edge, would leak there) nor the hold's model error (1e-5 to 1e-4 of the RMS) reads as noise."""
        channel = [i for i, o in enumerate(observed) if o][0]
        # Hann taper: a misfit at the resonances must not leak into the band through the window's edges.
        taper = torch.hann_window(residual.shape[1], periodic=False, dtype=torch.float64)
        spectrum = torch.fft.rfft(residual[:, :, 0] * taper, dim=1).abs().square()  # white: E = σ² Σ taper²
        floor = spectrum[:, spectrum.shape[1] // 2 :].mean(1) / taper.square().sum()
        power = targets[:, :, channel].square().mean(1).clamp_min(1e-300)
        return floor > self.settings.min_input_noise**2 * power

    def residual_weights(self, targets: Tensor, road: Tensor, params: Tensor, observed, offset: int = 0) -> Tensor:
        """[batch, n_out] weights 1/σ̂_c from each observed channel's RMS residual at ``params`` over the
        window (floored at 1e-6 of the channel's RMS, so an exact fit cannot give infinite weight);
        unobserved channels get 1."""
        channels = [i for i, o in enumerate(observed) if o]
        predicted = self.response.outputs(params.double(), road, offset, targets.shape[1])
        residual = predicted[:, :, channels] - targets[:, :, channels]
        sigma = residual.square().mean(1).sqrt()
        floor = 1e-6 * targets[:, :, channels].square().mean(1).sqrt().clamp_min(1e-300)
        sigma = torch.where(torch.isfinite(sigma), torch.maximum(sigma, floor), floor)
        weights = torch.ones(targets.shape[0], targets.shape[2], dtype=torch.float64)
        weights[:, channels] = 1.0 / sigma
        return weights

    def noise_model(
        self,
        targets: Tensor,
        road: Tensor,
        params: Tensor,
        observed,
        offset: int = 0,
        frozen: bool = False,
        residual: Tensor | None = None,
    ) -> SpectralNoise:
        """The spectral noise model (estimation/noise.py) with variances fitted to the residual at ``params``
        (``residual``: that of residual(), when the caller has it): output noise per observed channel, and for
        a base-excitation model its driving inputs' noise (``frozen``: its spectrum held at ``params``)."""
        channels = [i for i, o in enumerate(observed) if o]
        if residual is None:
            residual = self.residual(targets, road, params, observed, offset)
        reference = targets[:, :, channels].square().mean(1)
        v_alone, _ = estimate_variances(residual, None, 0, reference)  # the residual's power, output noise only
        linear = getattr(self.response, "model", None)
        if self.quarter_car or not self.settings.input_noise or linear is None or len(channels) != linear.n_output:
            return SpectralNoise(v_alone)
        omega = 2 * math.pi * torch.fft.rfftfreq(targets.shape[1], d=self.h, dtype=torch.float64)
        # the linear model's own parameters (a delay after them changes the phase, not the noise's power)
        H, _ = frequency_response(linear, params[:, : linear.n_params].double(), omega)
        leverage = None
        if self.settings.leverage:  # the fit's leverage under the white output noise just fitted
            columns = 1 + (~self.known).nonzero().squeeze(1)
            jacobian = self.response.sensitivities(params.double(), road, offset, targets.shape[1])
            jacobian = jacobian[:, :, channels][..., columns]
            leverage = spectral_leverage(jacobian, None, params)
            v_out, v_in = estimate_variances(residual, H, linear.n_input, reference, leverage=leverage)
            if bool((v_out > 0).all()) and bool(torch.isfinite(v_in).all()):  # once more, whitened by that fit
                first = SpectralNoise(v_out, v_in.clamp_min(0.0), linear, self.h)
                leverage = spectral_leverage(jacobian, first, params.double())
        v_out, v_in = estimate_variances(residual, H, linear.n_input, reference, leverage=leverage)
        # An input "noise" far below any accelerometer's floor is the hold's interpolation error
        # between samples (deterministic, concentrated near Nyquist), not noise: modelling it as
        # white input noise biases the weakly identified p3 of the sprung model on noise-free data
        # (docs/design/noise_and_intervals.md). Such samples get the output-noise model.
        samples = road.samples if isinstance(road, PreparedInputs) else road
        window = samples[:, offset : offset + targets.shape[1]]
        channels = window if window.ndim == 3 else window[..., None]  # [b, T, m]
        input_power = channels.square().mean(1)  # [b, m]
        if self.settings.band_cap:
            v_in = torch.minimum(v_in, input_band_power(channels))
        negligible = (v_in < self.settings.min_input_noise**2 * input_power).all(1)
        v_out = torch.where(negligible[:, None], v_alone, v_out)
        v_in = torch.where(negligible[:, None], torch.zeros_like(v_in), v_in)
        noise = SpectralNoise(v_out, v_in, linear, self.h, frozen_at=params.double() if frozen else None)
        if self.settings.leverage:
            log_std = input_noise_log_std(H, v_out, v_in.clamp_min(1e-300), targets.shape[1], leverage)
            noise.v_in_log_std = torch.where(negligible[:, None], torch.zeros_like(log_std), log_std)
        return noise

    @staticmethod
    def consistent(problem: LeastSquaresProblem, result: SolverResult, n_steps: int) -> Tensor:
        """[batch] bool: the whitened data loss at ``result`` (its loss less the prior's term) is within a
        factor _NOISE_CONSISTENCY of what white noise of the fitted variances gives, ½ n_out (T - 1)
        (the Parseval weights of T samples without DC sum to T - 1; the few fitted parameters take
        less than a factor 2 off it for any window a spectral stage runs on)."""
        loss = result.loss.double()
        if problem.prior_mean is not None:
            loss = loss - 0.5 * (problem.prior_precision * (result.params.double() - problem.prior_mean).square()).sum(
                1
            )
        ratio = loss / (0.5 * sum(problem.observed) * (n_steps - 1))
        return (ratio > 1.0 / _NOISE_CONSISTENCY) & (ratio < _NOISE_CONSISTENCY)


def input_band_power(signal: Tensor) -> Tensor:
    """[b, m] the mean power per sample of ``signal`` [b, T, m] in the upper half of its spectrum (a quarter of
    the sampling rate to Nyquist; Hann taper, so that the band's lower content does not leak in): the white
    noise variance where the band holds noise only, an upper bound of it otherwise (NoiseWeighting.band_cap);
    from one 512-sample window it scatters by about ±15 % (10th to 90th percentile) around its expectation."""
    taper = torch.hann_window(signal.shape[1], periodic=False, dtype=torch.float64)
    x = signal.double() - signal.double().mean(1, keepdim=True)
    spectrum = torch.fft.rfft(x * taper[None, :, None], dim=1).abs().square()  # [b, K, m]
    return spectrum[:, spectrum.shape[1] // 2 :].mean(1) / taper.square().sum()


def profiled_score(residual: Tensor, problem: LeastSquaresProblem, params: Tensor) -> Tensor:
    """[batch] -log posterior of a fit with each output channel's white-noise variance profiled out:
    ½ T Σ_c log(Σ_t r_c²) + ½ Σ λ (θ - μ)² of ``problem``'s prior (constants dropped), from the residual
    [batch, T, channels] less each channel's mean (offsets are outside the noise model). Per channel,
    because the channels' scales differ by orders of magnitude: a summed residual would let the wheel's
    trade the occupant's away."""
    power = (residual - residual.mean(1, keepdim=True)).square().sum(1).clamp_min(1e-300)  # [batch, channels]
    score = 0.5 * residual.shape[1] * power.log().sum(1)
    if problem.prior_mean is not None:
        score = score + 0.5 * (problem.prior_precision * (params.double() - problem.prior_mean).square()).sum(1)
    return score


def refit_noise(
    refinement: GaussNewtonRefinement,
    outputs,
    stage,
    inputs,
    params: Tensor,
    observed,
    offset: int,
    window: int,
    last: bool,
    problem: LeastSquaresProblem,
    result: SolverResult,
) -> None:
    """In place (``result``, ``params``): the stage's samples whose noise model disagrees with their
    residual (NoiseFit.consistent) and whose residual has a sensor-noise floor (NoiseFit.noise_floor) get
    maximum-likelihood passes with the variances fitted again at their estimate, up to
    ``noise_refits`` times; a pass is kept where it lowers the -log posterior (profiled_score)
    and does not diverge."""
    fit = refinement.noise_fit
    consistent = NoiseFit.consistent(problem, result, window)
    for _ in range(refinement.weighting.refits):
        redo = (~consistent & (result.status != SolverStatus.DIVERGED)).nonzero().squeeze(1)
        if redo.numel() == 0:
            return
        targets = outputs["targets"][redo, :window].double()
        residual = fit.residual(targets, inputs[redo], params[redo], observed, offset)
        # Only a residual with a sensor-noise floor has a noise level to fit again. Without one it is
        # the model's error, whose variance (~1e-10 of the signal's) makes the ML pass ill-posed.
        floor = fit.noise_floor(residual, targets, observed)
        consistent[redo[~floor]] = True
        redo, targets, residual = redo[floor], targets[floor], residual[floor]
        if redo.numel() == 0:
            return
        sub = {
            k: (v[redo] if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == params.shape[0] else v)
            for k, v in outputs.items()
        }
        sub_inputs, start = inputs[redo], params[redo]
        noisy = None if refinement.param_prior is None else torch.ones(redo.numel(), dtype=torch.bool)
        sub_problem = LeastSquaresProblem(
            targets,
            sub_inputs,
            refinement.h,
            scaled_road=refinement.pu_known,
            observed=observed,
            known=refinement.known,
            weights=None,
            model=refinement.response,
            input_offset=offset,
            noise=fit.noise_model(targets, sub_inputs, start, observed, offset, False, residual),
            **refinement.stage_prior(sub, start, last, noisy),
        )
        refit = stage.solver.solve(sub_problem, start)
        # A refit is a new attempt at the same posterior: kept only where it lowers the -log posterior
        # with each channel's noise level profiled out (profiled_score), so that it can never leave
        # a better fit for a worse one.
        before = profiled_score(residual, sub_problem, start)
        after = profiled_score(
            fit.residual(targets, sub_inputs, refit.params, observed, offset), sub_problem, refit.params
        )
        take = (refit.status != SolverStatus.DIVERGED) & (after <= before)
        take_samples(result, refit, take, redo[take])
        params[redo[take]] = refit.params[take]
        consistent[redo] = ~take | NoiseFit.consistent(sub_problem, refit, window)
