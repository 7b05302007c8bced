"""Gauss-Newton behind the networks: the callback that solves every predict/test batch's problem.

:class:`GaussNewtonRefinement` runs the solver stages (window continuation, noise-model passes,
restarts) on the problem :class:`~hybridqcm.estimation.front.HybridEstimator` returns for each
batch, collects per-sample results and writes per-iteration losses to TensorBoard. Its settings:
:class:`RefinementSettings` (what is fitted), :class:`~hybridqcm.estimation.weighting.NoiseWeighting`
and :class:`~hybridqcm.estimation.restarts.Restarts`. Used together::

    trainer.predict(HybridEstimator(cnn_ckpt=...), loader, callbacks=[GaussNewtonRefinement(stages)])
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from lightning.pytorch import Callback
from torch import Tensor

from hybridqcm.physics.parameters import CHANNELS

from ._blas import op_threads, torch_threads
from .front import HybridEstimator
from .initial_state import X0_STARTS, project_initial_state
from .noise import SpectralNoise
from .problems import LeastSquaresProblem
from .refinement_result import RefinementResult, merge_records
from .response import EulerResponse, ResponseModel
from .restarts import BatchFit, Restarts, far_from_start, flag_outliers, restart, take_samples
from .solver import NonlinearLeastSquares, SolverResult, SolverStatus
from .weighting import NoiseFit, NoiseWeighting, refit_noise


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
class RefinementSettings:
    """What a refinement fits, besides its stages, noise weighting and restarts.

    known [n_params] bool: parameters held fixed; pu_known: the wheel forcing p_u u is data (scaled road,
    p9/p10 only through S), else it depends on p9, p10 through p_u = p10 - p9. response: the model GN fits
    (default: the Euler recursion with ``h`` and ``pu_known``); with an unknown initial state its θ is
    (p1..p10, x0), estimated together. observed: the measured channels, used when refine() is called
    without a HybridEstimator. x0_start: where x0 starts — "rest" (0); "least_squares": x0*(p0), the linear
    least-squares x0 at the start p over the first stage's window, channels and weights
    (estimation/initial_state.py), for the first attempt and every restart; "alternate": x0*(p0) first,
    then restarts alternately from rest and from x0*(p0) — at a start p far off, x0*(p0) absorbs part of
    p's error and is no better than rest. param_prior: (mean [n_params], std [n_params]) of a Gaussian prior
    on p (std inf: none on that entry), used where the loss is in units of the noise (a spectral pass: its
    whitened residual makes the MAP a posterior; in raw m/s² a prior's weight would depend on the signal's
    scale), on recordings with a sensor noise floor (NoiseFit.noise_floor). peer_factor, peer_min_batch:
    the peer test for the misfit status (restarts.flag_outliers; None: off). log_dir: per-iteration mean
    losses go to TensorBoard under ``gn/<stage>/mean_loss``.
    """

    known: Tensor | None = None
    pu_known: bool = False
    h: float = 0.01
    response: ResponseModel | None = None
    observed: Sequence[str] = CHANNELS
    x0_start: str = "rest"
    param_prior: tuple[Tensor, Tensor] | None = None
    peer_factor: float | None = 10.0
    peer_min_batch: int = 20
    log_dir: str | os.PathLike | None = None

    def __post_init__(self):
        if self.x0_start not in X0_STARTS:
            raise ValueError(f"x0_start={self.x0_start!r}: choose one of {list(X0_STARTS)}")


class GaussNewtonRefinement(Callback):
    """Runs the GN stages on every predict/test batch of a :class:`HybridEstimator`, with ``settings``
    (:class:`RefinementSettings`), the last stage's ``noise`` weighting (:class:`NoiseWeighting`) and the
    multi-start ``restarts`` (:class:`Restarts`); each None: its defaults."""

    def __init__(
        self,
        stages: Sequence[GaussNewtonStage],
        settings: RefinementSettings | None = None,
        noise: NoiseWeighting | None = None,
        restarts: Restarts | None = None,
    ):
        super().__init__()
        if not stages:
            raise ValueError("GaussNewtonRefinement needs at least one stage")
        s = settings if settings is not None else RefinementSettings()
        self.settings = s
        self.weighting = noise if noise is not None else NoiseWeighting()
        self.restarts = restarts if restarts is not None else Restarts()
        self.x0_start = s.x0_start
        self.stages = list(stages)
        self.pu_known = bool(s.pu_known)
        self.h = float(s.h)
        self.response = s.response if s.response is not None else EulerResponse(self.h, self.pu_known)
        n_params = self.response.n_params
        known = s.known
        known_p = torch.zeros(n_params, dtype=torch.bool) if known is None else torch.as_tensor(known, dtype=torch.bool)
        if known_p.shape != (n_params,):
            raise ValueError(f"known must be a [{n_params}] mask over {self.response.theta_names[:n_params]}")
        # θ = (p, x0): initial states are never known.
        self.known = torch.cat([known_p, torch.zeros(self.response.n_theta - n_params, dtype=torch.bool)])
        # The quarter car's outputs are (a3, a2, a1) and its input the road; a base-excitation
        # model (road-free) has its own outputs, all of them measured.
        self.quarter_car = tuple(self.response.output_names) == CHANNELS
        self.noise_fit = NoiseFit(self.response, self.h, self.known, self.weighting, self.quarter_car)
        self.peer_factor = None if s.peer_factor is None else float(s.peer_factor)
        self.peer_min_batch = int(s.peer_min_batch)
        self.log_dir = s.log_dir
        self.observed = tuple(s.observed)
        center = self.restarts.center
        if center is not None:
            positive = self.response.positive[:n_params]
            if center.shape != (n_params,) or not bool((center[positive] > 0).all()):
                raise ValueError(f"restart_center must be [{n_params}] positive parameters, got {center}")
        self.param_prior = self._param_prior(s.param_prior, known_p)
        self._batches: list[dict] = []

    def _param_prior(self, param_prior, known_p: Tensor) -> tuple[Tensor, Tensor] | None:
        """(mean, precision) [n_theta] of the settings' (mean, std) prior on p (none on known entries)."""
        if param_prior is None:
            return None
        n_params = self.response.n_params
        mean, std = (torch.as_tensor(t, dtype=torch.float64) for t in param_prior)
        if mean.shape != (n_params,) or std.shape != (n_params,) or not bool((std > 0).all()):
            raise ValueError(f"param_prior must be (mean, std > 0), each [{n_params}]")
        pad = torch.zeros(self.response.n_theta - n_params, dtype=torch.float64)
        precision = torch.where(known_p, 0.0, std.pow(-2))
        return (torch.cat([torch.where(precision > 0, mean, 0.0), pad]), torch.cat([precision, pad]))

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

    def _road(self, outputs) -> Tensor:
        """The model's inputs [batch, time_in(, n_in)] of a batch (the road, scaled by p_u where that is data)."""
        road = outputs["road"].double()
        if self.pu_known and self.quarter_car:
            road = outputs["pu"].double()[:, None] * road
        return road

    def run_stages(
        self, outputs, init: Tensor, module, restart: bool = False, x0_at_rest: Tensor | None = None
    ) -> tuple[dict, SolverResult, Tensor, Tensor, Tensor]:
        """All stages from ``init`` (restarts skip guarded stages: they start from the networks'
        guess directly, in case the completed channels were what misled the first attempt);
        ``x0_at_rest`` [batch] bool: rows whose initial state starts at rest whatever x0_start says.
        Returns (per-stage results, last result, params, relative loss, score: lower is the better attempt)."""
        params = self._theta(init)
        road = self._road(outputs)
        weights = outputs.get("weights")
        offset = int(outputs.get("input_offset", 0))
        skip_guarded = restart and not all(stage.guard for stage in self.stages)
        stages = [stage for stage in self.stages if not (skip_guarded and stage.guard)]
        if self.x0_start != "rest":  # variable-projection start: x0*(p0) on the first stage's problem
            first = stages[0]
            window = _window(first, outputs)
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
        per_stage = {}
        for number, stage in enumerate(stages):
            observed = self._channels(stage, module)
            last = number == len(stages) - 1
            if self.weighting.mode == "channels" and last and number > 0:
                weights = self.noise_fit.residual_weights(outputs["targets"].double(), road, params, observed, offset)
            spectral = self.weighting.mode == "spectral" and last and number > 0
            problem, result, params = self._stage(
                outputs, stage, params, road, observed, weights, offset, spectral, last
            )
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
        relative, score = self._relative_loss(outputs, road, weights, problem, result)
        return per_stage, result, params, relative, score

    def _stage(self, outputs, stage, params, road, observed, weights, offset: int, spectral: bool, last: bool):
        """One stage's solves: once, or (``spectral``) its noise-model passes and refits. Returns (the last
        problem, its result, θ after the passes [batch, n_theta])."""
        window = _window(stage, outputs)
        prior = self.stage_prior(outputs, params, last, None)
        passes = self.weighting.passes + 1 if spectral else 1
        # The window's inputs as the model evaluates them, held once for all its solves and noise fits.
        stage_road = self.response.prepare(road, offset, window) if spectral else road
        noise, previous = None, None
        for number_pass in range(passes):
            if spectral:
                ml = number_pass == passes - 1
                targets = outputs["targets"][:, :window].double()
                residual = self.noise_fit.residual(targets, stage_road, params, observed, offset)
                noise = self.noise_fit.noise_model(targets, stage_road, params, observed, offset, not ml, residual)
                weights = None
                # Judged again at every pass's start: a first pass that began at a poor fit may have
                # taken the misfit for noise; the next one sees the noise floor (or none) it left.
                noisy = None if self.param_prior is None else self.noise_fit.noise_floor(residual, targets, observed)
                prior = self.stage_prior(outputs, params, last, noisy)
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
            if spectral and previous is not None and self.weighting.ml_guard is not None:
                # Both passes estimate the same p; the ML one is the more efficient, but with
                # variances fitted to a poor residual it can run to a spurious optimum (a rigid or
                # very resonant seat that blames the fit on input noise). Keep the reweighted
                # estimate where the two disagree beyond ml_guard of its standard deviations.
                n_p = self.response.n_params
                # (judged on the model-based std, so the reported interval never moves the estimate)
                spread = previous.std if previous.model_std is None else previous.model_std
                moved = (result.params[:, :n_p] - previous.params[:, :n_p]).abs() > self.weighting.ml_guard * spread[
                    :, :n_p
                ].clamp_min(1e-300)
                take_samples(result, previous, moved.any(1) | (result.status == SolverStatus.DIVERGED))
            if spectral:  # the next pass re-fits the variances at this estimate
                previous = result
                params = torch.where((result.status == SolverStatus.DIVERGED)[:, None], params, result.params)
        if spectral and self.weighting.refits:
            refit_noise(self, outputs, stage, stage_road, params, observed, offset, window, last, problem, result)
        return problem, result, params

    def _relative_loss(self, outputs, road, weights, problem, result) -> tuple[Tensor, Tensor]:
        """The last stage's relative loss [batch] (inf where diverged) and the attempt's score [batch]."""
        noise, window = problem.noise, problem.targets.shape[1]
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
        return relative, self._attempt_score(relative, n_terms, problem, result.params)

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
        if self.weighting.mode != "spectral":
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
        residual = self.noise_fit.residual(targets, prepared, params, observed, offset)
        if variances is None:
            noise = self.noise_fit.noise_model(targets, prepared, params, observed, offset, False, residual)
        else:
            v_out, v_in = variances
            linear = None if v_in is None else self.response.model
            noise = SpectralNoise(v_out, v_in, linear, None if v_in is None else self.h)
        noisy = None if self.param_prior is None else self.noise_fit.noise_floor(residual, targets, observed)
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
            **self.stage_prior(outputs, params, True, noisy),
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

    def stage_prior(self, outputs, params: Tensor, last: bool, noisy: Tensor | None) -> dict:
        """The stage's Gaussian prior on θ as LeastSquaresProblem's prior_mean, prior_precision ({} for
        none): the networks' p1, p2 in the last stage, and ``param_prior`` in a spectral pass (``noisy``
        [batch] given: its loss is in units of the noise, which makes the MAP a posterior) for the
        recordings with a sensor noise floor (``NoiseFit.noise_floor``); where both cover a parameter they combine
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

    def _theta(self, init: Tensor) -> Tensor:
        """θ0 [batch, n_theta] from p0 [batch, 10]: initial states (if estimated) start at rest."""
        extra = self.response.n_theta - self.response.n_params
        return (
            torch.cat([init.double(), init.new_zeros(init.shape[0], extra, dtype=torch.float64)], 1) if extra else init
        )

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
        model and the tests between solves run at the solves' own torch thread count (op_threads: one where
        the solves' chunks run on threads), so with thread_chunks (the default) a batch's numbers do not depend
        on SolverConfig.num_threads."""
        with torch_threads(op_threads(self.stages[0].solver.config)):
            return self._refine(outputs, module)

    def _refine(self, outputs: Mapping[str, Tensor], module: Any = None) -> dict:
        init = outputs["init"].double()
        per_stage, result, params, relative, score = self.run_stages(outputs, init, module)
        typical = flag_outliers(result, self.peer_factor, self.peer_min_batch)
        restarted = restart(self, outputs, module, init, BatchFit(result, params, relative, score, typical))
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

    def far_from_start(self, params: Tensor, init: Tensor) -> Tensor:
        """[batch] bool: free p1 or p2 of ``params`` more than the restarts' far_from_start (relative, either
        way) from ``init``."""
        return far_from_start(self.restarts.far_from_start, self.known, params, init)

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
        return merge_records(self._batches, [stage.name for stage in self.stages])

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


def _window(stage: GaussNewtonStage, outputs: Mapping) -> int:
    """The number of samples a stage fits: its n_steps, at most the batch's."""
    n_steps = outputs["targets"].shape[1]
    return n_steps if stage.n_steps is None else min(int(stage.n_steps), n_steps)
