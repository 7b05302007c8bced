"""Gauss-Newton behind the networks: the callback that solves every predict/test batch's problem.

:class:`GaussNewtonRefinement` runs the solver stages (window continuation, noise-model passes,
restarts) on the problem :class:`~hybridqcm.estimation.front.HybridEstimator` returns for each
batch, collects per-sample results and writes per-iteration losses to TensorBoard. Used together::

    trainer.predict(HybridEstimator(cnn_ckpt=...), loader, callbacks=[GaussNewtonRefinement(stages)])
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from lightning.pytorch import Callback
from torch import Tensor

from hybridqcm.data.sensor import keyed_normals

from .front import CHANNELS, HybridEstimator
from .initial_state import X0_STARTS, project_initial_state
from .noise import SpectralNoise, estimate_variances, frequency_response, input_noise_log_std, spectral_leverage
from .response import EulerResponse, PreparedInputs, ResponseModel
from .solver import LeastSquaresProblem, NonlinearLeastSquares, SolverResult, SolverStatus, torch_threads

# A noise model is consistent with a fit when the whitened loss is within this factor of its expectation
# (white noise of 500 samples leaves it within a few per cent; a misfit's variance is off by orders).
_NOISE_CONSISTENCY = 2.0


@dataclass
class GaussNewtonStage:
    """One solver pass: which channels enter the residual and with which solver.

    channels: "all" = every channel GN has data for (observed + completed), "observed" = only
    measured ones (e.g. a3 in exp 8/10), or an explicit list like ["a3"].
    """

    name: str
    solver: NonlinearLeastSquares
    channels: Any = "all"
    n_steps: int | None = None  # residual on the first n_steps only (window continuation); None: all
    # For stages on network-completed channels: keep the result only where it fits the *measured*
    # channels better than its start, and skip the stage in restarts (a poor completion must not
    # drag every attempt away from the measurement).
    guard: bool = False


@dataclass
class RefinementResult:
    """Concatenated per-sample results of all batches, in batch order."""

    index: Tensor
    init: Tensor
    result: SolverResult
    stage_loss: dict = field(default_factory=dict)  # stage -> mean loss per iteration (list)
    stage_status: dict = field(default_factory=dict)  # stage -> status counts
    restarts: Tensor | None = None  # [batch] restarts run per sample
    relative_loss: Tensor | None = None  # [batch] final L / ½Σa² (observed channels)


class GaussNewtonRefinement(Callback):
    """Runs the GN stages on every predict/test batch of a :class:`HybridEstimator`.

    known [10] bool: parameters held fixed; pu_known: the wheel forcing p_u u is data (scaled road,
    p9/p10 only through S), else it depends on p9, p10 through p_u = p10 - p9.
    response: the model GN fits (default: the Euler recursion with ``h`` and ``pu_known``); with an
    unknown initial state its θ is (p1..p10, x0), estimated together. x0_start: where x0 starts —
    "rest" (0); "least_squares": x0*(p0), the linear least-squares x0 at the start p over the
    first stage's window, channels and weights (estimation/initial_state.py), for the first
    attempt and every restart; "alternate": x0*(p0) first, then restarts alternately from rest and
    from x0*(p0) — at a start p far off, x0*(p0) absorbs part of p's error and is no better than rest.
    Per-iteration mean losses go to TensorBoard under ``gn/<stage>/mean_loss`` when ``log_dir``.
    """

    def __init__(
        self,
        stages: Sequence[GaussNewtonStage],
        known: Tensor | None = None,
        pu_known: bool = False,
        h: float = 0.01,
        log_dir: str | os.PathLike | None = None,
        restarts: int = 0,
        restart_threshold: float = 1e-10,
        restart_sigma: float = 0.1,
        seed: int = 0,
        observed: Sequence[str] = CHANNELS,
        restart_mass_factors: Sequence[float] = (),
        response: ResponseModel | None = None,
        reweight: bool | str = False,
        noise_passes: int = 1,
        ml_guard: float | None = 4.0,
        min_input_noise: float = 1e-3,
        peer_factor: float | None = 10.0,
        peer_min_batch: int = 20,
        restart_batch: int = 64,
        restarts_failed: int = 0,
        x0_start: str = "rest",
        restart_far: float | None = None,
        param_prior: tuple[Tensor, Tensor] | None = None,
        noise_refits: int = 2,
        restart_center: Tensor | None = None,
        noise_leverage: bool = False,
    ):
        super().__init__()
        if not stages:
            raise ValueError("GaussNewtonRefinement needs at least one stage")
        if x0_start not in X0_STARTS:
            raise ValueError(f"x0_start={x0_start!r}: choose one of {list(X0_STARTS)}")
        self.x0_start = x0_start
        self.stages = list(stages)
        self.pu_known = bool(pu_known)
        self.h = float(h)
        self.response = response if response is not None else EulerResponse(self.h, self.pu_known)
        n_params = self.response.n_params
        known_p = torch.zeros(n_params, dtype=torch.bool) if known is None else torch.as_tensor(known, dtype=torch.bool)
        if known_p.shape != (n_params,):
            raise ValueError(f"known must be a [{n_params}] mask over {self.response.theta_names[:n_params]}")
        # θ = (p, x0): initial states are never known.
        self.known = torch.cat([known_p, torch.zeros(self.response.n_theta - n_params, dtype=torch.bool)])
        # The quarter car's outputs are (a3, a2, a1) and its input the road; a base-excitation
        # model (road-free) has its own outputs, all of them measured.
        self.quarter_car = tuple(self.response.output_names) == CHANNELS
        # Noise-aware weighting when nobody knows the noise, before the last stage:
        #   True / "channels": each channel's residual weighted by 1/σ̂_c, σ̂_c its RMS residual at
        #                      the previous stage's estimate;
        #   "spectral": the frequency-domain noise model of estimation/noise.py — output noise per
        #               channel and, for base-excitation models, the measured driving channel's noise
        #               through H(p) (errors in variables), variances fitted to the residual; the last
        #               stage runs ``noise_passes`` times with the noise spectrum held at the previous
        #               estimate (reweighted least squares), then once as the errors-in-variables maximum
        #               likelihood (spectrum a function of p), guarded by ``ml_guard`` (below).
        if reweight not in (False, True, "channels", "spectral"):
            raise ValueError(f"reweight={reweight!r}: choose false, true/'channels' or 'spectral'")
        self.reweight = "channels" if reweight is True else reweight
        self.noise_passes = max(1, int(noise_passes))
        # Each pass fits the noise variances to the residual at its start. Where that start was far from
        # the data (the window continuation's short-window fit seen over the whole window), the variance
        # is the misfit's, up to 10^5 times the noise: the data then weigh next to nothing against a prior
        # and the intervals are as wide. A sample whose whitened loss at the end of the stage is not what
        # its noise model predicts (within a factor _NOISE_CONSISTENCY) gets up to ``noise_refits`` more
        # maximum-likelihood passes with the variances fitted again at its estimate (_refit_noise).
        if int(noise_refits) < 0:
            raise ValueError(f"noise_refits must be >= 0, got {noise_refits!r}")
        self.noise_refits = int(noise_refits)
        # The noise variances fitted to a residual at the fit are short by the fit's leverage, most where
        # the input's noise shows (estimate_variances): with ``noise_leverage`` the restricted fit corrects it.
        self.noise_leverage = bool(noise_leverage)
        self.ml_guard = None if ml_guard is None else float(ml_guard)
        self.min_input_noise = float(min_input_noise)  # relative to the input's RMS (see _noise_model)
        self.peer_factor = None if peer_factor is None else float(peer_factor)
        self.peer_min_batch = int(peer_min_batch)
        self.log_dir = log_dir
        self.observed = tuple(observed)  # used when refine() is called without a HybridEstimator
        # Multi-start: samples left `misfit` (structured residual: a local minimum) or diverged,
        # and — for the Euler model on its own data — samples whose final loss stays above
        # restart_threshold x ½Σa² (noise-free fits end near 1e-15, local minima at >= 1e-8), run
        # all stages again from init (1 + restart_sigma δ'); the lower loss wins. Seeded, so runs
        # repeat exactly. (With the exact model the noise-free floor is the hold's model error, so
        # a loss threshold means nothing there: pass restart_threshold=inf.)
        self.restarts = int(restarts)
        # After the ``restarts``, up to ``restarts_failed`` more attempts for the recordings still
        # misfit or diverged (a wrong basin the first attempts did not leave), nothing else retried.
        if int(restarts_failed) < 0:
            raise ValueError(f"restarts_failed must be >= 0, got {restarts_failed!r}")
        self.restarts_failed = int(restarts_failed)
        self.restart_threshold = float(restart_threshold)
        self.restart_sigma = float(restart_sigma)
        # Attempts run together while retried samples x attempts <= restart_batch: a solver call on a
        # few samples costs its fixed per-step overhead; on more, attempts that are not needed cost more.
        self.restart_batch = int(restart_batch)
        # Restart draws come from one stream per (seed, recording, attempt) (_restart_draws): a
        # recording's restarts do not depend on which others share its batch or are retried with it.
        self.seed = int(seed)
        # Restart k (k < len) also rescales the start of p1, p2 by restart_mass_factors[k]: both are
        # (C3, K3)/m3, and a wrong occupant mass puts the seat mode's phase off by whole cycles,
        # which a 10 % perturbation cannot undo. E.g. [0.6, 1.6, 0.4, 2.5] walks m3 over the prior.
        self.restart_mass_factors = [float(f) for f in restart_mass_factors]
        # restart_center [n_params] (a vehicle, e.g. the reference one), or None: restarts draw the
        # vehicle's parameters (all but the occupant's p1, p2, which keep the first start and the mass
        # ladder) around it instead of around the first start. A random start that ended in a wrong
        # minimum is a bad centre for the next ones: draws around it land in the same basin.
        if restart_center is not None:
            restart_center = torch.as_tensor(restart_center, dtype=torch.float64)
            positive = self.response.positive[:n_params]
            if restart_center.shape != (n_params,) or not bool((restart_center[positive] > 0).all()):
                raise ValueError(f"restart_center must be [{n_params}] positive parameters, got {restart_center}")
        self.restart_center = restart_center
        # A fit that fits but ends with p1 or p2 more than restart_far (relative) away from a start
        # the networks gave is retried too: under noise a one-channel loss can hold several minima of
        # nearly equal depth, and the lowest-loss attempt wins (the same rule as above). None: off.
        if restart_far is not None and not float(restart_far) > 0:
            raise ValueError(f"restart_far must be None or > 0, got {restart_far!r}")
        self.restart_far = None if restart_far is None else float(restart_far)
        # (mean [n_params], std [n_params]) of a Gaussian prior on p (std inf: none on that entry), used
        # where the loss is in units of the noise (a spectral pass: its whitened residual makes the MAP a
        # posterior; in raw m/s² a prior's weight would depend on the signal's scale), on recordings with a
        # sensor noise floor (_noise_floor).
        self.param_prior = None
        if param_prior is not None:
            mean, std = (torch.as_tensor(t, dtype=torch.float64) for t in param_prior)
            if mean.shape != (n_params,) or std.shape != (n_params,) or not bool((std > 0).all()):
                raise ValueError(f"param_prior must be (mean, std > 0), each [{n_params}]")
            pad = torch.zeros(self.response.n_theta - n_params, dtype=torch.float64)
            precision = torch.where(known_p, 0.0, std.pow(-2))
            self.param_prior = (torch.cat([torch.where(precision > 0, mean, 0.0), pad]), torch.cat([precision, pad]))
        self._batches: list[dict] = []

    def _channels(self, stage: GaussNewtonStage, module: HybridEstimator) -> tuple[bool, ...]:
        if not self.quarter_car:
            return (True,) * len(self.response.output_names)
        available = module.gn_channels() if isinstance(module, HybridEstimator) else (True, True, True)
        if stage.channels == "all":
            return available
        if stage.channels == "observed":
            observed = module.observed if isinstance(module, HybridEstimator) else self.observed
            return tuple(c in observed for c in CHANNELS)
        names = list(stage.channels)
        wanted = tuple(c in names for c in CHANNELS)
        missing = [c for c, w, a in zip(CHANNELS, wanted, available) if w and not a]
        if missing:
            raise ValueError(f"stage {stage.name!r} uses channels {missing} that are neither observed nor completed")
        return wanted

    def _run_stages(
        self, outputs, init: Tensor, module, restart: bool = False, x0_at_rest: Tensor | None = None
    ) -> tuple[dict, SolverResult, Tensor, Tensor]:
        """All stages from ``init`` (restarts skip guarded stages: they start from the networks'
        guess directly, in case the completed channels were what misled the first attempt);
        ``x0_at_rest`` [batch] bool: rows whose initial state starts at rest whatever x0_start says.
        Returns (per-stage results, last result, params, relative loss, score: lower is the better attempt)."""
        params = self._theta(init)
        road = outputs["road"].double()
        if self.pu_known and self.quarter_car:
            road = outputs["pu"].double()[:, None] * road
        per_stage = {}
        result = None
        weights = outputs.get("weights")
        offset = int(outputs.get("input_offset", 0))
        skip_guarded = restart and not all(stage.guard for stage in self.stages)
        stages = [stage for stage in self.stages if not (skip_guarded and stage.guard)]
        if self.x0_start != "rest":  # variable-projection start: x0*(p0) on the first stage's problem
            first = stages[0]
            window = (
                outputs["targets"].shape[1]
                if first.n_steps is None
                else min(int(first.n_steps), outputs["targets"].shape[1])
            )
            params = project_initial_state(
                self.response,
                params,
                road,
                outputs["targets"][:, :window].double(),
                self._channels(first, module),
                weights,
                offset,
                chunk_size=first.solver.config.chunk_size,
            )
            if x0_at_rest is not None:
                params[x0_at_rest, self.response.n_params :] = 0.0
        for number, stage in enumerate(stages):
            observed = self._channels(stage, module)
            last = number == len(stages) - 1
            noise = None
            if self.reweight == "channels" and last and number > 0:
                weights = self._residual_weights(outputs["targets"].double(), road, params, observed, offset)
            window = (
                outputs["targets"].shape[1]
                if stage.n_steps is None
                else min(int(stage.n_steps), outputs["targets"].shape[1])
            )
            spectral = self.reweight == "spectral" and last and number > 0
            prior = self._prior(outputs, params, last, None)
            passes = self.noise_passes + 1 if spectral else 1
            # The window's inputs as the model evaluates them, held once for all its solves and noise fits.
            stage_road = self.response.prepare(road, offset, window) if spectral else road
            previous = None
            for number_pass in range(passes):
                if spectral:
                    ml = number_pass == passes - 1
                    targets = outputs["targets"][:, :window].double()
                    residual = self._residual(targets, stage_road, params, observed, offset)
                    noise = self._noise_model(targets, stage_road, params, observed, offset, not ml, residual)
                    weights = None
                    # Judged again at every pass's start: a first pass that began at a poor fit may have
                    # taken the misfit for noise; the next one sees the noise floor (or none) it left.
                    noisy = None if self.param_prior is None else self._noise_floor(residual, targets, observed)
                    prior = self._prior(outputs, params, last, noisy)
                problem = LeastSquaresProblem(
                    outputs["targets"][:, :window].double(),
                    stage_road,
                    self.h,
                    scaled_road=self.pu_known,
                    observed=observed,
                    known=self.known,
                    weights=weights,
                    model=self.response,
                    input_offset=offset,
                    noise=noise,
                    **prior,
                )
                result = stage.solver.solve(problem, params)
                if spectral and previous is not None and self.ml_guard is not None:
                    # Both passes estimate the same p; the ML one is the more efficient, but with
                    # variances fitted to a poor residual it can run to a spurious optimum (a rigid or
                    # very resonant seat that blames the fit on input noise). Keep the reweighted
                    # estimate where the two disagree beyond ml_guard of its standard deviations.
                    n_p = self.response.n_params
                    # (judged on the model-based std, so the reported interval never moves the estimate)
                    spread = previous.std if previous.model_std is None else previous.model_std
                    moved = (result.params[:, :n_p] - previous.params[:, :n_p]).abs() > self.ml_guard * spread[
                        :, :n_p
                    ].clamp_min(1e-300)
                    _take(result, previous, moved.any(1) | (result.status == SolverStatus.DIVERGED))
                if spectral:  # the next pass re-fits the variances at this estimate
                    previous = result
                    params = torch.where((result.status == SolverStatus.DIVERGED)[:, None], params, result.params)
            if spectral and self.noise_refits:
                self._refit_noise(outputs, stage, stage_road, params, observed, offset, window, last, problem, result)
            per_stage[stage.name] = result
            # A stage that diverged keeps its input for the next stage rather than garbage.
            keep_input = result.status == SolverStatus.DIVERGED
            if stage.guard:
                measured = tuple(
                    c in (module.observed if isinstance(module, HybridEstimator) else self.observed) for c in CHANNELS
                )
                before = self._measured_loss(outputs, road, params, measured)
                after = self._measured_loss(outputs, road, result.params, measured)
                keep_input |= ~(after <= before)
            params = torch.where(keep_input[:, None], params, result.params)
        channels = [i for i, o in enumerate(problem.observed) if o]
        if noise is not None:  # whitened losses of different attempts have different variances
            full = problem.inputs if window == outputs["targets"].shape[1] else road
            relative = self._measured_loss(
                {**outputs, "weights": None}, full, result.params, problem.observed, demean=True
            ) / (0.5 * outputs["targets"].double()[:, :, channels].square().sum((1, 2))).clamp_min(1e-300)
        else:
            weighted = outputs["targets"].double()
            if weights is not None:
                weighted = weighted * weights.double()[:, None, :]
            energy = 0.5 * weighted[:, :, channels].square().sum((1, 2))
            relative = result.loss / energy.clamp_min(1e-300)
        relative = torch.where(
            result.status == SolverStatus.DIVERGED, torch.full_like(relative, float("inf")), relative
        )
        n_terms = outputs["targets"].shape[1] * len(channels) if noise is not None else None
        return per_stage, result, params, relative, self._attempt_score(relative, n_terms, problem, result.params)

    def final_problem(
        self,
        outputs: Mapping,
        params: Tensor,
        known: Tensor | None = None,
        variances: tuple[Tensor, Tensor | None] | None = None,
    ) -> LeastSquaresProblem:
        """The last stage's maximum-likelihood problem at θ ``params`` [batch, n_theta] of ``outputs``' batch:
        its window and channels, the noise model fitted to the residual there (errors in variables: the
        spectrum a function of p) and the prior that stage applies (recordings with a sensor noise floor).
        What weighs, compares and profiles a finished fit (estimation/occupant.py, estimation/profile.py).
        ``known`` [n_theta] bool: entries held fixed (default: the refinement's own); ``variances``
        (v_out [batch, n_out], v_in [batch, n_in] or None): the noise model's variances, given instead of
        fitted (a comparison of several models of one recording under one noise level)."""
        if self.reweight != "spectral":
            raise ValueError("final_problem needs the spectral noise model (reweight='spectral')")
        stage = self.stages[-1]
        observed = self._channels(stage, None)
        road = outputs["road"].double()
        if self.pu_known and self.quarter_car:
            road = outputs["pu"].double()[:, None] * road
        offset = int(outputs.get("input_offset", 0))
        n_steps = outputs["targets"].shape[1]
        window = n_steps if stage.n_steps is None else min(int(stage.n_steps), n_steps)
        targets = outputs["targets"][:, :window].double()
        prepared = self.response.prepare(road, offset, window)
        params = params.double()
        residual = self._residual(targets, prepared, params, observed, offset)
        if variances is None:
            noise = self._noise_model(targets, prepared, params, observed, offset, False, residual)
        else:
            v_out, v_in = variances
            linear = None if v_in is None else self.response.model
            noise = SpectralNoise(v_out, v_in, linear, None if v_in is None else self.h)
        noisy = None if self.param_prior is None else self._noise_floor(residual, targets, observed)
        return LeastSquaresProblem(
            targets,
            prepared,
            self.h,
            scaled_road=self.pu_known,
            observed=observed,
            known=self.known if known is None else known,
            weights=None,
            model=self.response,
            input_offset=offset,
            noise=noise,
            **self._prior(outputs, params, True, noisy),
        )

    @staticmethod
    def _attempt_score(relative: Tensor, n_terms: int | None, problem, params: Tensor) -> Tensor:
        """[batch] what the last stage minimised, comparable across attempts (lower is better). With the
        noise variance profiled out (each attempt fitted its own), -log posterior = ½ n log(residual
        power) + ½ Σ λ (θ - μ)² of ``problem``'s prior, n = ``n_terms`` residual terms: a vehicle far
        outside the prior that matches the data only as well as the noise allows must not win by a
        hair of misfit. ``n_terms`` None (no noise model): log of the relative loss, the same order."""
        score = relative.clamp_min(1e-300).log()
        if n_terms is None:
            return score
        score = 0.5 * n_terms * score
        if getattr(problem, "prior_mean", None) is not None:
            deviation = params.double() - problem.prior_mean
            score = score + 0.5 * (problem.prior_precision * deviation.square()).sum(1)
        return score

    def _noise_consistent(self, problem: LeastSquaresProblem, result: SolverResult, n_steps: int) -> Tensor:
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

    def _refit_noise(
        self,
        outputs,
        stage: GaussNewtonStage,
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
        residual (_noise_consistent) and whose residual has a sensor-noise floor (_noise_floor) get
        maximum-likelihood passes with the variances fitted again at their estimate, up to
        ``noise_refits`` times; a pass is kept where it lowers the -log posterior (_profiled_score)
        and does not diverge."""
        consistent = self._noise_consistent(problem, result, window)
        for _ in range(self.noise_refits):
            redo = (~consistent & (result.status != SolverStatus.DIVERGED)).nonzero().squeeze(1)
            if redo.numel() == 0:
                return
            targets = outputs["targets"][redo, :window].double()
            residual = self._residual(targets, inputs[redo], params[redo], observed, offset)
            # Only a residual with a sensor-noise floor has a noise level to fit again. Without one it is
            # the model's error, whose variance (~1e-10 of the signal's) makes the ML pass ill-posed.
            floor = self._noise_floor(residual, targets, observed)
            consistent[redo[~floor]] = True
            redo, targets, residual = redo[floor], targets[floor], residual[floor]
            if redo.numel() == 0:
                return
            sub = {
                k: (v[redo] if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == params.shape[0] else v)
                for k, v in outputs.items()
            }
            sub_inputs, start = inputs[redo], params[redo]
            noisy = None if self.param_prior is None else torch.ones(redo.numel(), dtype=torch.bool)
            sub_problem = LeastSquaresProblem(
                targets,
                sub_inputs,
                self.h,
                scaled_road=self.pu_known,
                observed=observed,
                known=self.known,
                weights=None,
                model=self.response,
                input_offset=offset,
                noise=self._noise_model(targets, sub_inputs, start, observed, offset, False, residual),
                **self._prior(sub, start, last, noisy),
            )
            refit = stage.solver.solve(sub_problem, start)
            # A refit is a new attempt at the same posterior: kept only where it lowers the -log posterior
            # with each channel's noise level profiled out (_profiled_score), so that it can never leave
            # a better fit for a worse one.
            before = _profiled_score(residual, sub_problem, start)
            after = _profiled_score(
                self._residual(targets, sub_inputs, refit.params, observed, offset), sub_problem, refit.params
            )
            take = (refit.status != SolverStatus.DIVERGED) & (after <= before)
            _take(result, refit, take, redo[take])
            params[redo[take]] = refit.params[take]
            consistent[redo] = ~take | self._noise_consistent(sub_problem, refit, window)

    def _residual(self, targets: Tensor, inputs, params: Tensor, observed, offset: int) -> Tensor:
        """Prediction minus data on the observed channels, [b, T, n_observed] (non-finite entries 0)."""
        channels = [i for i, o in enumerate(observed) if o]
        predicted = self.response.outputs(params.double(), inputs, offset, targets.shape[1])
        residual = predicted[:, :, channels] - targets[:, :, channels]
        return torch.where(torch.isfinite(residual), residual, torch.zeros_like(residual))

    def _noise_floor(self, residual: Tensor, targets: Tensor, observed) -> Tensor:
        """[batch] bool: the first observed output (a3 where measured: the one the vehicle filters most)
        has a noise floor above ``min_input_noise`` of its RMS, measured on its ``residual`` (_residual)
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
        return floor > self.min_input_noise**2 * power

    def _prior(self, outputs, params: Tensor, last: bool, noisy: Tensor | None) -> dict:
        """The stage's Gaussian prior on θ as LeastSquaresProblem's prior_mean, prior_precision ({} for
        none): the networks' p1, p2 in the last stage, and ``param_prior`` in a spectral pass (``noisy``
        [batch] given: its loss is in units of the noise, which makes the MAP a posterior) for the
        recordings with a sensor noise floor (``_noise_floor``); where both cover a parameter they combine
        by precision."""
        mean = torch.zeros_like(params)
        precision = torch.zeros_like(params)
        if noisy is not None and self.param_prior is not None:
            mean += self.param_prior[0]
            precision += torch.where(noisy[:, None], self.param_prior[1], 0.0)
        if "prior_p12" in outputs and last:
            p12 = outputs["prior_p12"].double()
            lam = torch.where(self.known[:2], 0.0, outputs["prior_p12_std"].double().clamp_min(1e-12) ** -2)
            total = precision[:, :2] + lam
            mean[:, :2] = torch.where(total > 0, (precision[:, :2] * mean[:, :2] + lam * p12) / total, 0.0)
            precision[:, :2] = total
        if not bool((precision > 0).any()):
            return {}
        return {"prior_mean": mean, "prior_precision": precision}

    def _restart_draws(self, index: Tensor, attempt: int, width: int) -> Tensor:
        """[len(index), width] float64 standard normal draws for restart ``attempt`` of the recordings
        ``index``, each from its own generator seeded by (seed, recording, attempt)."""
        keys = [[self.seed % 2**63, int(i) % 2**63, int(attempt), 2] for i in index.tolist()]
        return keyed_normals(keys, (width,))

    def _far_from_start(self, params: Tensor, init: Tensor) -> Tensor:
        """[batch] bool: free p1 or p2 of ``params`` more than restart_far (relative, either way) from ``init``."""
        if self.restart_far is None:
            return torch.zeros(params.shape[0], dtype=torch.bool)
        ratio = params[:, :2].double() / init[:, :2].double()
        far = ~(ratio.abs().log().abs() <= math.log1p(self.restart_far))  # a non-positive ratio is far
        return (far & ~self.known[:2]).any(1)

    def _theta(self, init: Tensor) -> Tensor:
        """θ0 [batch, n_theta] from p0 [batch, 10]: initial states (if estimated) start at rest."""
        extra = self.response.n_theta - self.response.n_params
        return (
            torch.cat([init.double(), init.new_zeros(init.shape[0], extra, dtype=torch.float64)], 1) if extra else init
        )

    def _residual_weights(self, targets: Tensor, road: Tensor, params: Tensor, observed, offset: int = 0) -> Tensor:
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

    def _noise_model(
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
        (``residual``: that of _residual, when the caller has it): output noise per observed channel, and for
        a base-excitation model its driving inputs' noise (``frozen``: its spectrum held at ``params``)."""
        channels = [i for i, o in enumerate(observed) if o]
        if residual is None:
            residual = self._residual(targets, road, params, observed, offset)
        reference = targets[:, :, channels].square().mean(1)
        v_alone, _ = estimate_variances(residual, None, 0, reference)  # the residual's power, output noise only
        linear = getattr(self.response, "model", None)
        if self.quarter_car or linear is None or len(channels) != linear.n_output:
            return SpectralNoise(v_alone)
        omega = 2 * math.pi * torch.fft.rfftfreq(targets.shape[1], d=self.h, dtype=torch.float64)
        # the linear model's own parameters (a delay after them changes the phase, not the noise's power)
        H, _ = frequency_response(linear, params[:, : linear.n_params].double(), omega)
        leverage = None
        if self.noise_leverage:  # the fit's leverage under the white output noise just fitted
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
        input_power = (window if window.ndim == 3 else window[..., None]).square().mean(1)  # [b, m]
        negligible = (v_in < self.min_input_noise**2 * input_power).all(1)
        v_out = torch.where(negligible[:, None], v_alone, v_out)
        v_in = torch.where(negligible[:, None], torch.zeros_like(v_in), v_in)
        noise = SpectralNoise(v_out, v_in, linear, self.h, frozen_at=params.double() if frozen else None)
        if self.noise_leverage:
            log_std = input_noise_log_std(H, v_out, v_in.clamp_min(1e-300), targets.shape[1], leverage)
            noise.v_in_log_std = torch.where(negligible[:, None], torch.zeros_like(log_std), log_std)
        return noise

    def _measured_loss(self, outputs, road: Tensor, params: Tensor, measured, demean: bool = False) -> Tensor:
        """½ Σ (weighted) residual² on the measured channels over the full window [batch] (inf if not finite);
        ``demean``: without each channel's mean (sensor offsets are outside the spectral noise model)."""
        channels = [i for i, m in enumerate(measured) if m]
        targets = outputs["targets"]
        accel = self.response.outputs(params.double(), road, int(outputs.get("input_offset", 0)), targets.shape[1])[
            :, :, channels
        ]
        residual = accel - outputs["targets"].double()[:, :, channels]
        if demean:
            residual = residual - residual.mean(1, keepdim=True)
        if outputs.get("weights") is not None:
            residual = residual * outputs["weights"].double()[:, None, channels]
        loss = 0.5 * residual.square().sum((1, 2))
        return torch.where(torch.isfinite(loss), loss, torch.full_like(loss, float("inf")))

    def refine(self, outputs: Mapping[str, Tensor], module: Any = None) -> dict:
        """Run every stage (and restarts) on one prepared batch; returns per-sample results. The noise
        model and the tests between solves run at the solver's thread count too (torch_threads)."""
        with torch_threads(self.stages[0].solver.config.num_threads):
            return self._refine(outputs, module)

    def _refine(self, outputs: Mapping[str, Tensor], module: Any = None) -> dict:
        init = outputs["init"].double()
        per_stage, result, params, relative, score = self._run_stages(outputs, init, module)
        restarted = torch.zeros(init.shape[0], dtype=torch.int64)
        typical = self._flag_outliers(result)
        attempt = 0
        while attempt < self.restarts + self.restarts_failed:
            failed = (result.status == SolverStatus.MISFIT) | (result.status == SolverStatus.DIVERGED)
            if attempt < self.restarts:
                retry = (relative > self.restart_threshold) | failed | self._far_from_start(params, init)
                tier_end = self.restarts
            else:  # the extra attempts: failed recordings only
                retry, tier_end = failed, self.restarts + self.restarts_failed
            retry = retry.nonzero().squeeze(1)
            if retry.numel() == 0:
                if attempt >= self.restarts:
                    break
                attempt = self.restarts  # nothing to retry in the first tier; the failed tier may still run
                continue
            # A few retried samples: run several attempts in one solver call (a small batch costs
            # the solver's fixed per-step overhead, not its size); many: one attempt at a time, so
            # samples that succeed are not retried again.
            group = min(tier_end - attempt, max(1, self.restart_batch // retry.numel()))
            starts = []
            for number in range(attempt, attempt + group):
                delta = self._restart_draws(outputs["index"][retry], number, init.shape[1])
                centre = init[retry].clone()
                if self.restart_center is not None:
                    n_p = self.restart_center.numel()
                    centre[:, 2:n_p] = self.restart_center[2:].to(centre)
                new_init = centre * (1.0 + self.restart_sigma * delta)
                if number < len(self.restart_mass_factors):
                    new_init[:, :2] = new_init[:, :2] * self.restart_mass_factors[number]
                starts.append(torch.where(self.known[: init.shape[1]] | (new_init <= 0), init[retry], new_init))
            rows = retry.repeat(group)
            sub = {
                k: (v[rows] if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == init.shape[0] else v)
                for k, v in outputs.items()
            }
            # x0_start="alternate": restarts 1, 3, 5, ... start x0 at rest, the others projected.
            at_rest = torch.tensor(
                [self.x0_start == "alternate" and number % 2 == 0 for number in range(attempt, attempt + group)]
            ).repeat_interleave(retry.numel())
            _, sub_result, sub_params, sub_relative, sub_score = self._run_stages(
                sub, torch.cat(starts), module, restart=True, x0_at_rest=at_rest
            )
            # In attempt order: an attempt replaces a sample's current fit if it fits (not misfit or
            # diverged) where the current does not, or fits as well and has the lower score; a lower
            # loss at a misfit is a structured residual, not a better fit. Candidates are judged by
            # the same peer test as the first fits.
            self._flag_outliers(sub_result, typical)
            fits = sub_result.status.ne(SolverStatus.MISFIT) & sub_result.status.ne(SolverStatus.DIVERGED)
            for number in range(group):
                mask = torch.zeros(rows.numel(), dtype=torch.bool)
                part = slice(number * retry.numel(), (number + 1) * retry.numel())
                current = result.status[retry]
                current_fits = current.ne(SolverStatus.MISFIT) & current.ne(SolverStatus.DIVERGED)
                better = (fits[part] & ~current_fits) | (
                    (fits[part] == current_fits) & (sub_score[part] < score[retry])
                )
                mask[part] = better
                take = retry[better]
                params[take] = sub_params[part][better]
                relative[take] = sub_relative[part][better]
                score[take] = sub_score[part][better]
                _take(result, sub_result, mask, take)
            restarted[retry] += group
            self._flag_outliers(result, typical)
            attempt += group
        record = {
            "index": outputs["index"].cpu(),
            "init": init.cpu(),
            "stages": per_stage,
            "final": result,
            "params": params,
            "restarts": restarted,
            "relative_loss": relative,
        }
        self._batches.append(record)
        return record

    def _flag_outliers(self, result: SolverResult, typical: Tensor | None = None) -> Tensor | None:
        """Peer test for the misfit status, in place: among recordings of one batch, a structured
        residual (whiteness > 1) more than ``peer_factor`` x the batch's median relative residual is
        `misfit` even below the solver's absolute floor. Noise-free data are where it matters: a
        correct exact-model fit leaves the hold's model error (~1e-5 of a3), a wrong local minimum
        that mimics the signal leaves ~1e-3 — both far below any absolute floor. With sensor noise
        every residual is noise, white, and nothing is flagged. Returns the batch's median (kept
        from the first pass, so restarts on a subset are judged against the whole batch)."""
        if self.peer_factor is None or (typical is None and result.status.numel() < self.peer_min_batch):
            return typical
        settled = result.status != SolverStatus.DIVERGED
        rel = result.relative_residual
        if typical is None:
            ok = settled & torch.isfinite(rel)
            if not bool(ok.any()):
                return None
            typical = rel[ok].median()
        outlier = settled & (result.whiteness > 1) & (rel > self.peer_factor * typical)
        result.status[outlier] = SolverStatus.MISFIT
        return typical

    # Lightning hooks ------------------------------------------------------------------------------
    def on_predict_epoch_start(self, trainer, pl_module) -> None:
        self._batches = []

    def on_test_epoch_start(self, trainer, pl_module) -> None:
        self._batches = []

    def on_predict_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self.refine(outputs, pl_module)

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self.refine(outputs, pl_module)

    def on_predict_epoch_end(self, trainer, pl_module) -> None:
        self._log_tensorboard()

    def on_test_epoch_end(self, trainer, pl_module) -> None:
        self._log_tensorboard()

    # Results ----------------------------------------------------------------------------------------
    def collect(self) -> RefinementResult:
        """All batches concatenated (final stage), plus mean loss per iteration of every stage."""
        if not self._batches:
            raise RuntimeError("GaussNewtonRefinement has no results: run trainer.predict/test first")
        b = self._batches
        final = [r["final"] for r in b]
        history_len = max(f.loss_history.shape[0] for f in final)
        n_free_max = max(f.singular_values.shape[1] for f in final)

        def pad_history(h: Tensor) -> Tensor:  # finished samples carry their last loss
            return torch.cat([h, h[-1:].expand(history_len - h.shape[0], -1)]) if h.shape[0] < history_len else h

        merged = SolverResult(
            params=torch.cat([r["params"] for r in b]),
            status=torch.cat([f.status for f in final]),
            iterations=torch.cat([f.iterations for f in final]),
            loss=torch.cat([f.loss for f in final]),
            loss_history=torch.cat([pad_history(f.loss_history) for f in final], 1),
            std=torch.cat([f.std for f in final]),
            covariance=torch.cat([f.covariance for f in final]),
            singular_values=torch.cat(
                [
                    torch.nn.functional.pad(f.singular_values, (0, n_free_max - f.singular_values.shape[1]))
                    for f in final
                ]
            ),
            residual_variance=torch.cat([f.residual_variance for f in final]),
            seconds=[s for f in final for s in f.seconds],
            relative_residual=torch.cat([f.relative_residual for f in final]),
            whiteness=torch.cat([f.whiteness for f in final]),
            model_std=None if any(f.model_std is None for f in final) else torch.cat([f.model_std for f in final]),
        )
        stage_loss, stage_status = {}, {}
        for stage in self.stages:
            results = [r["stages"][stage.name] for r in b]
            length = max(x.loss_history.shape[0] for x in results)
            total = torch.zeros(length, dtype=torch.float64)
            count = 0
            for x in results:
                h = x.loss_history
                h = torch.cat([h, h[-1:].expand(length - h.shape[0], -1)]) if h.shape[0] < length else h
                total += h.sum(1)
                count += h.shape[1]
            stage_loss[stage.name] = (total / max(count, 1)).tolist()
            counts: dict[str, int] = {}
            for x in results:
                for k, v in x.status_counts().items():
                    counts[k] = counts.get(k, 0) + v
            stage_status[stage.name] = counts
            stage_status[stage.name + "_iterations_mean"] = float(
                torch.cat([x.iterations for x in results]).double().mean()
            )
        return RefinementResult(
            index=torch.cat([r["index"] for r in b]),
            init=torch.cat([r["init"] for r in b]),
            result=merged,
            stage_loss=stage_loss,
            stage_status=stage_status,
            restarts=torch.cat([r["restarts"] for r in b]),
            relative_loss=torch.cat([r["relative_loss"] for r in b]),
        )

    def _log_tensorboard(self) -> None:
        if self.log_dir is None or not self._batches:
            return
        from torch.utils.tensorboard import SummaryWriter

        collected = self.collect()
        writer = SummaryWriter(log_dir=str(self.log_dir))
        try:
            for name, losses in collected.stage_loss.items():
                for iteration, value in enumerate(losses):
                    writer.add_scalar(f"gn/{name}/mean_loss", value, iteration)
        finally:
            writer.close()


_PER_SAMPLE = (
    "params",
    "status",
    "iterations",
    "loss",
    "std",
    "covariance",
    "singular_values",
    "residual_variance",
    "relative_residual",
    "whiteness",
)


def _profiled_score(residual: Tensor, problem: LeastSquaresProblem, params: Tensor) -> Tensor:
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


def _take(into: SolverResult, other: SolverResult, mask: Tensor, rows: Tensor | None = None) -> None:
    """In place: the samples ``rows`` of ``into`` (default: where ``mask``) take ``other``'s per-sample
    results at ``mask`` (``other`` may hold a subset of ``into``'s samples)."""
    rows = mask.nonzero().squeeze(1) if rows is None else rows
    for name in _PER_SAMPLE:
        getattr(into, name)[rows] = getattr(other, name)[mask]
    if into.model_std is not None and other.model_std is not None:
        into.model_std[rows] = other.model_std[mask]
