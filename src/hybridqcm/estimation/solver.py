"""Batched nonlinear least squares for the quarter-car parameters (SPEC §8).

One base class, :class:`NonlinearLeastSquares`, owns the loop: Jacobian passes over the
*active* samples in chunks, per-sample Armijo backtracking, convergence tests, per-sample
status and the final uncertainty report. A concrete method supplies only its step from the
column-scaled normal equations (:class:`GaussNewton`, :class:`LevenbergMarquardt`), in the
spirit of theseus' optimizer/linear-solver split.

Loss per sample: L(θ) = ½ Σ_k Σ_{i observed} w_i² (y_{k,i}(θ) − a_{k,i})², y from a
:class:`~hybridqcm.estimation.response.ResponseModel` — the source's Euler recursion (θ = p) or
the exact discretisation of the continuous-time model (θ = p and the initial state x0). Armijo test: L(p − αg) ≤ L(p) − c α gᵀJᵀR with a
sufficient-decrease constant c (default 1e-4). Note that the literal c = 1 of SPEC §8 rejects
every full Gauss-Newton step on a quadratic model (there L(p − g) = L(p) − ½ gᵀJᵀR), which is one
reason the source needed so many iterations; c is configurable so the literal form can be run.

Honest status: the final residual of every sample is tested (:mod:`~hybridqcm.estimation.diagnostics`); a
sample whose residual shows the model does not fit is `misfit`, whatever the iteration said.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

import torch
from torch import Tensor

from hybridqcm.interrupt import check_stop

from ._blas import chunk_workers, even_slices, op_threads, parallel_map, torch_threads
from ._linalg import pseudo_inverse_solve
from .boundary import applies, boundary_test, initial_held, without_held
from .line_search import line_search
from .problems import LeastSquaresProblem, ProblemEvaluation
from .uncertainty import final_uncertainty, unevaluated_uncertainty


class SolverStatus(IntEnum):
    """Per-sample outcome. Values are stable (they go into CSV files)."""

    CONVERGED = 0  # a step, loss or decrease tolerance was met
    MAX_ITERATIONS = 1  # still improving when the iteration budget ran out
    SINGULAR = 2  # the column-scaled Jacobian is rank deficient at the estimate (not identifiable)
    DIVERGED = 3  # non-finite model at the start, or the estimate left the domain p > 0
    STALLED = 4  # no Armijo step found although the gradient test was not met
    MISFIT = 5  # stopped, but the residual is structured and above the floor: the model does not fit

    @property
    def label(self) -> str:
        return self.name.lower()


STATUS_LABELS = {s.value: s.label for s in SolverStatus}
COVARIANCES = ("model", "sandwich", "jackknife", "robust_sandwich", "robust_jackknife")  # SolverConfig.covariance
# The step's per-sample solves go to the chunk threads in parts of at least this many samples (below it a part's
# fixed cost is the solve's)
_STEP_PART = 1024


@dataclass
class SolverConfig:
    """Settings shared by all methods (also the Hydra ``solver`` group's fields)."""

    max_iterations: int = 30
    initial_step: float = 1.0  # α0 of the Armijo backtracking
    armijo_c: float = 1e-4  # sufficient-decrease constant; 1.0 is SPEC §8 read literally
    max_backtracks: int = 30  # at most this many backtracks (α ≥ α0 2^-30)
    # How the line search finds α = α0 2^-e: "halve" (e = 0, 1, 2, ...) or "interpolate" (the fitted parabola's
    # minimum, then bisection: the same α where the Armijo test is monotone in e, in fewer loss evaluations where
    # GN steps overshoot by orders of magnitude, as a weakly identified body mode's do; the occupant fit uses it).
    backtrack: str = "halve"
    # Convergence is judged on the *full* step (α = 1), never on an accepted, backtracked one
    # (a tiny α says nothing about being at a minimum):
    step_tol: float = 1e-9  # converged when max_j |δ_j| / p_j ≤ step_tol
    decrease_tol: float = 1e-12  # ... or when the predicted decrease δᵀJᵀR ≤ decrease_tol · L
    loss_tol: float = 1e-26  # ... or when L ≤ loss_tol · ½ Σ a² (noise-free exact fit)
    # ... or, when the residual is whitened by a noise model (its loss in units of the noise
    # variance), when the GN decrement δᵀJᵀR = δᵀFδ ≤ decrement_tol: the full step moves θ by
    # less than sqrt(decrement_tol) of a standard deviation in every direction (1e-6: 0.001 σ),
    # well below what the data can resolve. None: off.
    decrement_tol: float | None = 1e-6
    # ... and, in those fits, stopped as DIVERGED where the iterate lies outside the domain p > 0 and so does the
    # full step's landing point, itself within sqrt(outside_tol) σ (its decrement δᵀJᵀR ≤ outside_tol): the path
    # converges to an optimum outside the domain, where it would end DIVERGED after the iterations to decrement_tol
    # (a path that is still far from its optimum keeps going, and may come back). None: off.
    outside_tol: float | None = None
    # Nested models at a boundary (noise-whitened fits; estimation/boundary.py): a parameter whose zero is a
    # smaller model (a body mode's mass ratio) is held at 0 where a full step heads there and the loss rises by
    # less than this many nats with it at 0. None: off.
    boundary_test: float | None = None
    rcond: float = 1e-7  # singular values of the scaled J below rcond·s_max count as zero
    chunk_size: int = 512  # samples per Jacobian pass (keeps the per-step working set in cache)
    # Threads for torch inside solve(); the per-step ops are small, and with 2 threads on a busy
    # 2-core machine each op waited milliseconds for the second thread (measured). None: leave as is.
    num_threads: int | None = 1
    thread_chunks: bool = True  # num_threads > 1: chunks on that many threads, ops on one (_blas.chunk_workers)
    # How a step is applied (with column scaling all three give the same direction):
    #   "unconstrained": p <- p - αδ; iterates may leave p > 0 on the way, a final estimate
    #                    with any p_j <= 0 gets status DIVERGED (default: see docs/design/estimation.md,
    #                    ~75 % of exp-5 paths cross p3/p5/p7 <= 0 and most come back to the truth);
    #   "linear": p <- p - αδ, trials with any p <= 0 count as Armijo failures (SPEC/issue wording);
    #   "log": p <- p exp(-αδ/p), a step in log p (positivity by construction).
    parametrization: str = "unconstrained"
    # Trust cap: the first trial α is cut so that no free parameter changes by more than this
    # fraction (|αδ_j| ≤ cap·p_j) in one iteration; null/0 disables it. Weakly identified
    # parameters (p3, p5) otherwise take huge early steps that Armijo accepts (the other
    # parameters reduce the loss) and land near zero, where they get stuck.
    max_relative_step: float | None = None
    # Misfit test (module docstring): structured residual (Ljung-Box over misfit_lags lags above the
    # chi² quantile at misfit_alpha) larger than misfit_floor x the channel RMS. 0 lags: no test.
    # Noise-free, right fits leave the exact model's hold error (relative RMS <= 2e-4 on two simulators'
    # recordings) and wrong basins >= 3e-3: the floor sits between, so that a file too small for the
    # peer test (restarts.flag_outliers) still gets a wrong basin flagged.
    misfit_floor: float = 0.001
    misfit_lags: int = 5
    misfit_alpha: float = 1e-4
    # Standard deviations at the estimate (see estimation/uncertainty.py):
    #   "model":    σ̂² (JᵀJ)⁺ times the AR(1) inflation — exact when the whitened residual is white noise;
    #   "sandwich": (JᵀJ)⁺ (Σ_g s_g s_gᵀ) (JᵀJ)⁺ from the score s_g = J_gᵀ e_g of each group g of
    #               ``covariance_band`` adjacent frequencies (spectral noise model) or time steps
    #               (time-domain loss) — Huber-White, band-averaged so that model error coherent
    #               over neighbouring frequencies is seen;
    #   "jackknife": the delete-a-group jackknife over the same groups (the sandwich with leverage
    #               correction), at the Student-t quantile of its effective degrees of freedom (its
    #               Efron–Stein excess divided out where ``jackknife_test`` passes);
    #   "robust_sandwich" / "robust_jackknife": per parameter the larger of "model" and that variance
    #               (correlations of "model"). The app chooses per model (intervals.covariance: auto in
    #               configs/estimate.yaml; estimation/plan_settings.resolve_covariance).
    covariance: str = "model"
    # False: skip the final Jacobian pass (standard deviations, covariance, misfit test) — for a stage whose
    # result only starts the next one (window continuation); its std is then inf and its residual tests
    # unevaluated (inf), never a status it did not earn.
    uncertainty: bool = True
    covariance_band: int = 1
    covariance_dof: bool = True  # jackknife: Student-t quantile at its Satterthwaite degrees of freedom
    # jackknife: the level α of the test under which a parameter's jackknife variance is consistent with the
    # working model, and then divided by its Efron–Stein excess (uncertainty.robust_covariance); None: never
    jackknife_test: float | None = 0.05
    lm_initial_damping: float = 1e-3  # Levenberg-Marquardt only
    lm_min_damping: float = 1e-12
    lm_max_damping: float = 1e8


@dataclass
class SolverResult:
    """Everything per sample; never NaN (non-identifiable standard deviations are +inf).

    params = θ [batch, n_theta] (p1..p10 for the Euler model), status [batch] (SolverStatus values),
    iterations [batch], loss [batch] (final ½ RSS), loss_history [max_iterations + 1, batch]
    (finished samples carry their last loss), std [batch, n_theta] (0 for known entries),
    covariance [batch, n_theta, n_theta] (by SolverConfig.covariance; "model": σ̂² (JᵀJ)⁺ times the AR(1) inflation; zero rows/cols for known), singular_values [batch, n_free] of the column-scaled J
    (descending), residual_variance [batch] σ̂², seconds: wall time per iteration.
    """

    params: Tensor
    status: Tensor
    iterations: Tensor
    loss: Tensor
    loss_history: Tensor
    std: Tensor
    covariance: Tensor
    singular_values: Tensor
    residual_variance: Tensor
    seconds: list = field(default_factory=list)
    # [batch] max over observed channels of ‖R_c‖/‖a_c‖, and of the Ljung-Box statistic over its
    # χ² threshold (> 1: the residual is not white); inf where not evaluated (diverged).
    relative_residual: Tensor | None = None
    whiteness: Tensor | None = None
    # [batch, n_theta] the model-based std (config covariance = "model"), whatever ``std`` was built from
    model_std: Tensor | None = None

    def status_counts(self) -> dict[str, int]:
        return {s.label: int((self.status == s.value).sum()) for s in SolverStatus}

    @property
    def condition_number(self) -> Tensor:
        s = self.singular_values
        return torch.where(s[:, -1] > 0, s[:, 0] / s[:, -1].clamp_min(1e-300), torch.full_like(s[:, 0], math.inf))


IterationCallback = Callable[[int, Tensor, int], None]  # (iteration, loss [batch], n_active)


@dataclass
class _Run:
    """The state of one solve over a batch: the problem's evaluation, θ [batch, n_theta], the free entries'
    ids [n_free], ½ Σ a² of the (weighted) targets [batch] for the exact-fit test, per-sample status,
    accepted iterations and loss [batch], which samples still iterate [batch] bool, the loss history
    (one [batch] per iteration) and the wall time per iteration."""

    evaluation: ProblemEvaluation
    params: Tensor
    free: Tensor
    data_energy: Tensor
    status: Tensor
    iterations: Tensor
    loss: Tensor
    active: Tensor
    history: list = field(default_factory=list)
    seconds: list = field(default_factory=list)
    exponent: Tensor | None = None  # [batch] each sample's last accepted e (α = α0 2^-e): "interpolate" starts there
    held: Tensor | None = None  # [batch, n_free] bool: boundary parameters held at 0 (SolverConfig.boundary_test)


class NonlinearLeastSquares(ABC):
    """Base loop. Subclasses implement :meth:`direction` (and optionally :meth:`after_line_search`)."""

    def __init__(self, config: SolverConfig | None = None, **overrides):
        self.config = config or SolverConfig()
        for key, value in overrides.items():
            if not hasattr(self.config, key):
                raise TypeError(f"unknown solver setting {key!r}")
            setattr(self.config, key, value)
        if self.config.parametrization not in ("log", "linear", "unconstrained"):
            raise ValueError(f"solver parametrization must be 'log' or 'linear', got {self.config.parametrization!r}")
        if self.config.backtrack not in ("halve", "interpolate"):
            raise ValueError(f"solver backtrack={self.config.backtrack!r}: choose 'halve' or 'interpolate'")
        if self.config.covariance not in COVARIANCES:
            raise ValueError(f"solver covariance={self.config.covariance!r}: choose one of {list(COVARIANCES)}")
        if int(self.config.covariance_band) < 1:
            raise ValueError(f"solver covariance_band={self.config.covariance_band!r}: must be an integer >= 1")
        tol = self.config.outside_tol
        if tol is not None and (isinstance(tol, bool) or not isinstance(tol, (int, float)) or not 0 <= tol < math.inf):
            raise ValueError(f"solver outside_tol={tol!r}: a number of nats >= 0, or None")
        test = self.config.jackknife_test
        if test is not None and (isinstance(test, bool) or not isinstance(test, (int, float)) or not 0 < test < 1):
            raise ValueError(f"solver jackknife_test={test!r}: a level in (0, 1), or None")

    # --- method hooks -------------------------------------------------------------------
    def init_state(self, batch: int, dtype) -> None:  # noqa: B027 (a hook: most methods keep no state)
        """Per-sample method state (e.g. LM damping); GN has none."""

    @abstractmethod
    def direction(self, fisher_scaled: Tensor, gradient_scaled: Tensor, index: Tensor) -> Tensor:
        """Step in scaled coordinates from Fs [b, n, n] δs = gs [b, n]; ``index`` = sample ids."""

    def after_line_search(  # noqa: B027 (a hook)
        self, index: Tensor, full_step_accepted: Tensor, any_step_accepted: Tensor
    ) -> None:
        """Update method state after the line search of the samples ``index``."""

    def objective(self, problem: LeastSquaresProblem, params: Tensor) -> Tensor:
        """The loss every sample's solve minimises at θ ``params`` [batch, n_theta]: ½ Σ r² of the weighted or
        noise-whitened residual plus the prior's ½ Σ λ (θ − μ)² [batch] (inf where not finite). What a
        profile likelihood or a model comparison reads after the solve (SolverResult.loss is the data part)."""
        with torch_threads(op_threads(self.config)), torch.no_grad():
            evaluation = ProblemEvaluation(problem, self.config.chunk_size, workers=chunk_workers(self.config))
            index = torch.arange(params.shape[0])
            return evaluation.loss_at(params.detach().to(torch.float64), index)

    # --- the loop -----------------------------------------------------------------------
    def solve(
        self, problem: LeastSquaresProblem, initial_params: Tensor, callback: IterationCallback | None = None
    ) -> SolverResult:
        """Minimise every sample's loss from ``initial_params`` = θ0 [batch, n_theta] (known entries kept)."""
        with torch_threads(op_threads(self.config)), torch.no_grad():
            return self._solve(problem, initial_params, callback)

    def _solve(self, problem, initial_params, callback):
        cfg = self.config
        run = self._start(problem, initial_params)
        for iteration in range(cfg.max_iterations + 1):
            # a stop request (Ctrl-C) reaches a solve on a worker thread here, at the latest one iteration later
            check_stop()
            t0 = time.perf_counter()
            index = run.active.nonzero().squeeze(1)
            if iteration == cfg.max_iterations or index.numel() == 0:
                self._stop(run, index, iteration)
                break
            if not self._iterate(run, index, iteration):
                break
            run.history.append(run.loss.clone())
            run.seconds.append(time.perf_counter() - t0)
            if callback is not None:
                callback(iteration + 1, run.loss, int(run.active.sum()))
        return self._result(run)

    def _start(self, problem: LeastSquaresProblem, initial_params: Tensor) -> _Run:
        """Check θ0, evaluate the problem's fixed parts once, and start every sample (those outside the
        physical domain already DIVERGED)."""
        dtype = torch.float64
        params = initial_params.detach().to(dtype).clone()
        n_theta = problem.n_theta
        if params.ndim != 2 or params.shape != (problem.targets.shape[0], n_theta):
            raise ValueError(
                f"initial params must be [batch, n_theta] = [{problem.targets.shape[0]}, {n_theta}], "
                f"got {tuple(params.shape)}"
            )
        if not torch.isfinite(params).all():
            raise ValueError("initial params contain NaN/inf")
        batch = params.shape[0]
        free = torch.tensor(problem.free_index)
        # Which free entries are physical parameters (> 0, steps judged relative to them); the
        # others (initial states) have any sign.
        self._positive = problem.model.positive[free]
        jackknife = self.config.covariance.endswith("jackknife")
        evaluation = ProblemEvaluation(
            problem,
            self.config.chunk_size,
            jackknife,
            chunk_workers(self.config),
            moments=jackknife and self.config.jackknife_test is not None,  # the test's moments: only where used
        )
        targets, weights = evaluation.targets, evaluation.weights
        if problem.noise is not None:  # the targets as the loss sees them (at the start's p)
            weighted_targets = problem.noise.whiten_residual(targets, params, torch.arange(batch), frequency_rows=False)
        else:
            weighted_targets = targets if weights is None else targets * weights[:, None, :]
        data_energy = 0.5 * weighted_targets.square().sum(dim=(1, 2))  # [batch]

        self.init_state(batch, dtype)
        status = torch.full((batch,), SolverStatus.MAX_ITERATIONS, dtype=torch.int8)
        held = initial_held(self, problem, params, free)  # a boundary parameter at 0 is its nested model
        bad_start = self._outside(params[:, free], held)
        status[bad_start] = SolverStatus.DIVERGED
        return _Run(
            evaluation=evaluation,
            params=params,
            free=free,
            data_energy=data_energy,
            status=status,
            iterations=torch.zeros(batch, dtype=torch.int64),
            loss=torch.full((batch,), math.inf, dtype=dtype),
            active=~bad_start,
            exponent=torch.zeros(batch, dtype=torch.long),
            held=held,
        )

    def _stop(self, run: _Run, index: Tensor, iteration: int) -> None:
        """The end of the budget or of the active samples. No Jacobian needed to stop: the accepted losses
        are known from the line search."""
        if iteration == 0:  # max_iterations = 0: just evaluate the start
            if index.numel():  # (none: every start was outside the domain)
                run.loss[index] = run.evaluation.loss_at(run.params[index], index)
            run.history.append(torch.where(torch.isfinite(run.loss), run.loss, torch.zeros_like(run.loss)))
        exact = index[run.loss[index] <= self.config.loss_tol * run.data_energy[index]]
        run.status[exact] = SolverStatus.CONVERGED

    def _iterate(self, run: _Run, index: Tensor, iteration: int) -> bool:
        """One iteration of the active samples ``index``; False when none was left to step."""
        fisher, gradient, loss_now = run.evaluation.normal_equations(run.params, index)
        index, fisher, gradient, loss_now = self._drop_finished(run, index, iteration, fisher, gradient, loss_now)
        if index.numel() == 0:
            return False
        fisher, gradient = without_held(run.held[index], fisher, gradient)
        step, predicted, stationary = self._step(run, index, fisher, gradient, loss_now)
        lost = self._converging_outside(run, index, step, predicted) & ~stationary
        if bool(lost.any()):
            run.status[index[lost]] = SolverStatus.DIVERGED
            run.active[index[lost]] = False
            index, step, loss_now, predicted, stationary = (
                x[~lost] for x in (index, step, loss_now, predicted, stationary)
            )
        if applies(self.config, run.evaluation.problem):
            go = ~boundary_test(self, run, index, step)  # the others moved to their nested model this iteration
            run.iterations[index[~go]] += 1
            index, step, loss_now, predicted, stationary = (
                x[go] for x in (index, step, loss_now, predicted, stationary)
            )
        if index.numel():
            self._accept(run, index, step, loss_now, predicted, stationary)
        return True

    def _drop_finished(self, run: _Run, index, iteration, fisher, gradient, loss_now):
        """Record the losses at the iterate; stop the samples whose model overflowed (DIVERGED) or that fit
        exactly already (CONVERGED). Returns (index, fisher, gradient, loss_now) of the others."""
        cfg, status, active = self.config, run.status, run.active
        finite = torch.isfinite(loss_now) & torch.isfinite(fisher).flatten(1).all(1) & torch.isfinite(gradient).all(1)
        run.loss[index] = torch.where(finite, loss_now, run.loss[index])
        if iteration == 0:
            run.history.append(torch.where(torch.isfinite(run.loss), run.loss, torch.zeros_like(run.loss)))
        # A model that overflows at an accepted point cannot be continued: stop it there.
        if not bool(finite.all()):
            blown = index[~finite]
            status[blown] = SolverStatus.DIVERGED
            active[blown] = False
            index, fisher, gradient, loss_now = index[finite], fisher[finite], gradient[finite], loss_now[finite]
        tiny = loss_now <= cfg.loss_tol * run.data_energy[index]
        if bool(tiny.any()):  # exact fit already (noise-free data): nothing left to do
            done = index[tiny]
            status[done] = SolverStatus.CONVERGED
            active[done] = False
            index, fisher, gradient, loss_now = index[~tiny], fisher[~tiny], gradient[~tiny], loss_now[~tiny]
        return index, fisher, gradient, loss_now

    def _step(self, run: _Run, index, fisher, gradient, loss_now) -> tuple[Tensor, Tensor, Tensor]:
        """The method's step δ [b, n_free] from the column-scaled normal equations, the predicted decrease
        δᵀJᵀR [b] and whether the full step is below the convergence tolerances [b]."""
        cfg = self.config

        def scaled_step(rows: slice) -> Tensor:
            f, g = fisher[rows], gradient[rows]
            scale = f.diagonal(dim1=1, dim2=2).sqrt()  # column norms of J [b, n_free]
            safe_scale = torch.where(scale > 0, scale, torch.ones_like(scale))
            step = self.direction(f / (safe_scale.unsqueeze(2) * safe_scale.unsqueeze(1)), g / safe_scale, index[rows])
            return torch.where(scale > 0, step / safe_scale, torch.zeros_like(step))

        workers, b = chunk_workers(cfg), index.numel()
        if workers > 1 and b >= 2 * _STEP_PART:  # per-sample work (scaling too): on the chunk threads, bit for bit
            step = torch.cat(parallel_map(scaled_step, even_slices(b, workers), workers))
        else:
            step = scaled_step(slice(None))
        predicted = (step * gradient).sum(1)  # gᵀJᵀR ≥ 0 for a descent direction
        full_rel_step = self._relative_step(step, run.params[index][:, run.free])
        stationary = (full_rel_step <= cfg.step_tol) | (predicted <= cfg.decrease_tol * loss_now)
        if run.evaluation.problem.noise is not None and cfg.decrement_tol:
            stationary |= predicted <= cfg.decrement_tol
        return step, predicted, stationary

    def _outside(self, free_params: Tensor, held: Tensor) -> Tensor:
        """[b] bool: a physical parameter of ``free_params`` [b, n_free], not ``held`` [b, n_free] at its boundary,
        is <= 0 (outside the domain)."""
        return ((free_params <= 0) & ~held)[:, self._positive].any(1)

    def _converging_outside(self, run: _Run, index, step, predicted) -> Tensor:
        """[b] bool: the samples SolverConfig.outside_tol stops (noise-whitened fits): outside the domain, and so
        is the full step's landing point, within sqrt(outside_tol) σ."""
        tol = self.config.outside_tol
        if tol is None or run.evaluation.problem.noise is None:
            return torch.zeros(index.numel(), dtype=torch.bool)
        here = run.params[index][:, run.free]
        held = run.held[index]
        small = (predicted <= tol) & self._outside(here, held)
        return small & self._outside(self._apply_step(here, step), held)

    def _accept(self, run: _Run, index, step, loss_now, predicted, stationary) -> None:
        """Line search, the accepted steps into θ, and the statuses of the samples that stop here."""
        cfg, params, free, status, active = self.config, run.params, run.free, run.status, run.active
        accepted_alpha, new_loss = self._line_search(run, index, step, loss_now, predicted)
        accepted = accepted_alpha > 0
        self.after_line_search(index, accepted_alpha == cfg.initial_step, accepted)

        # Update accepted samples (free parameters only: known ones stay bit-identical).
        acc_index = index[accepted]
        old_free = params[acc_index][:, free]
        new_free = self._apply_step(old_free, accepted_alpha[accepted].unsqueeze(1) * step[accepted])
        params[acc_index.unsqueeze(1), free.unsqueeze(0)] = new_free
        run.loss[acc_index] = new_loss[accepted]
        run.iterations[acc_index] += 1

        status[index[stationary]] = SolverStatus.CONVERGED
        active[index[stationary]] = False

        # No acceptable step: at a (numerical) minimum if the predicted decrease is at
        # rounding level of the loss, otherwise the line search genuinely stalled.
        rejected = ~accepted & ~stationary
        rej_index = index[rejected]
        at_minimum = predicted[rejected] <= 1e-10 * loss_now[rejected] + 1e-300
        status[rej_index] = torch.where(
            at_minimum,
            torch.tensor(SolverStatus.CONVERGED, dtype=torch.int8),
            torch.tensor(SolverStatus.STALLED, dtype=torch.int8),
        )
        active[rej_index] = False

    def _result(self, run: _Run) -> SolverResult:
        """The result at the end of the loop, with the final uncertainty pass unless switched off."""
        params, status, free = run.params, run.status, run.free
        # An unconstrained path may end outside the physical domain: report it, keep the numbers.
        status[self._outside(params[:, free], run.held)] = SolverStatus.DIVERGED
        history = torch.stack(run.history)
        history = torch.where(torch.isfinite(history), history, torch.zeros_like(history))
        diverged = status == SolverStatus.DIVERGED
        if self.config.uncertainty:
            report = final_uncertainty(self.config, run.evaluation, params, free, diverged, run.loss, run.held)
        else:
            report = unevaluated_uncertainty(run.evaluation.problem, params, free, run.loss)
        run.loss.copy_(report.loss)
        status[report.singular] = SolverStatus.SINGULAR
        status[report.misfit] = SolverStatus.MISFIT  # a wrong answer is never `converged`
        return SolverResult(
            params=params,
            status=status,
            iterations=run.iterations,
            loss=run.loss,
            loss_history=history,
            std=report.std,
            covariance=report.covariance,
            singular_values=report.singular_values,
            residual_variance=report.residual_variance,
            seconds=run.seconds,
            relative_residual=report.relative_residual,
            whiteness=report.whiteness,
            model_std=report.model_std,
        )

    # --- pieces -------------------------------------------------------------------------
    def _apply_step(self, free_params: Tensor, scaled_step: Tensor) -> Tensor:
        """θ - αδ, or p exp(-αδ/p) for the physical parameters in the log parametrization (same first-order step)."""
        new = free_params - scaled_step
        if self.config.parametrization == "log":
            logged = free_params * torch.exp(-scaled_step / free_params)
            new = torch.where(self._positive & (free_params != 0), logged, new)  # 0: held at a boundary
        return new

    def _relative_step(self, step: Tensor, free_params: Tensor) -> Tensor:
        """max_j |δ_j| / p_j over the physical parameters [b] (inf when only initial states are free:
        then the decrease test alone decides)."""
        if not bool(self._positive.any()):
            return torch.full((step.shape[0],), math.inf, dtype=step.dtype)
        step, free_params = step[:, self._positive], free_params[:, self._positive]
        # a parameter held at 0 (boundary_test) takes no step: 0, not 0/0
        return torch.where(step == 0, 0.0, step / free_params).abs().amax(1)

    def _line_search(self, run: _Run, index, step, loss_now, predicted):
        """Per-sample Armijo backtracking (estimation/line_search.py); returns (α [b], 0 = none found; new loss [b])."""
        return line_search(self, run, index, step, loss_now, predicted)


class GaussNewton(NonlinearLeastSquares):
    """Gauss-Newton step δ = F⁺ JᵀR on the column-scaled normal equations."""

    def direction(self, fisher_scaled, gradient_scaled, index):
        step, _ = pseudo_inverse_solve(fisher_scaled, gradient_scaled, self.config.rcond)
        return step


class LevenbergMarquardt(NonlinearLeastSquares):
    """Damped step (F + λ diag F) δ = JᵀR; λ per sample, shrunk after a full step, grown after backtracking."""

    def init_state(self, batch, dtype):
        self.damping = torch.full((batch,), self.config.lm_initial_damping, dtype=dtype)

    def direction(self, fisher_scaled, gradient_scaled, index):
        # Scaled F has unit diagonal (non-zero columns), so λ I is Marquardt's λ diag(F).
        lam = self.damping[index]
        eye = torch.eye(fisher_scaled.shape[-1], dtype=fisher_scaled.dtype)
        step, _ = pseudo_inverse_solve(fisher_scaled + lam[:, None, None] * eye, gradient_scaled, self.config.rcond)
        return step

    def after_line_search(self, index, full_step_accepted, any_step_accepted):
        cfg = self.config
        lam = self.damping[index]
        lam = torch.where(
            full_step_accepted, (lam / 3.0).clamp_min(cfg.lm_min_damping), (lam * 4.0).clamp_max(cfg.lm_max_damping)
        )
        self.damping[index] = lam


SOLVERS = {"gauss_newton": GaussNewton, "levenberg_marquardt": LevenbergMarquardt}


def build_solver(method: str = "gauss_newton", **settings) -> NonlinearLeastSquares:
    """Solver by name with :class:`SolverConfig` fields as keyword settings."""
    if method not in SOLVERS:
        raise ValueError(f"unknown solver method {method!r}; choose one of {sorted(SOLVERS)}")
    config = SolverConfig(**{k: v for k, v in settings.items()})
    return SOLVERS[method](config)
