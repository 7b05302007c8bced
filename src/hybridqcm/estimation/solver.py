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

Honest status: a least-squares fit always ends somewhere, so "the iteration stopped" is not
"the answer is right". After the loop the residual of every sample is tested for whiteness
(Ljung-Box statistic over the first ``misfit_lags`` lags, per observed channel): a model that fits
leaves residuals that look like sensor noise, a wrong model or a local minimum leaves structure.
A sample whose residual is structured *and* larger than ``misfit_floor`` of the channel's RMS is
`misfit`, whatever the iteration said; no noise level needs to be known. So is one whose residual is
larger than the channel itself, white or not: such a fit explains less than predicting zero (a noise
model fitted to that residual whitens it, so whiteness alone cannot tell). Serially correlated
residuals also widen the standard deviations by the AR(1) factor (1 + ρ)/(1 − ρ), the usual
effective-sample-size correction, where ρ is their lag-1 autocorrelation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import IntEnum

import torch
from scipy.stats import chi2
from scipy.stats import t as student_t
from torch import Tensor

from ._blas import batched_matmul
from .noise import SpectralNoise
from .response import EulerResponse, PreparedInputs, ResponseModel


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


@dataclass
class SolverConfig:
    """Settings shared by all methods (also the Hydra ``solver`` group's fields)."""

    max_iterations: int = 30
    initial_step: float = 1.0  # α0 of the Armijo backtracking
    armijo_c: float = 1e-4  # sufficient-decrease constant; 1.0 is SPEC §8 read literally
    max_backtracks: int = 30  # α halves at most this often (α ≥ α0 2^-30)
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
    rcond: float = 1e-7  # singular values of the scaled J below rcond·s_max count as zero
    chunk_size: int = 512  # samples per Jacobian pass (keeps the per-step working set in cache)
    # Threads for torch inside solve(); the per-step ops are small, and with 2 threads on a busy
    # 2-core machine each op waited milliseconds for the second thread (measured). None: leave as is.
    num_threads: int | None = 1
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
    # peer test (refinement._flag_outliers) still gets a wrong basin flagged.
    misfit_floor: float = 0.001
    misfit_lags: int = 5
    misfit_alpha: float = 1e-4
    # Standard deviations at the estimate (see NonlinearLeastSquares._finish):
    #   "model":    σ̂² (JᵀJ)⁺ times the AR(1) inflation — exact when the whitened residual is white noise;
    #   "sandwich": (JᵀJ)⁺ (Σ_g s_g s_gᵀ) (JᵀJ)⁺ from the score s_g = J_gᵀ e_g of each group g of
    #               ``covariance_band`` adjacent frequencies (spectral noise model) or time steps
    #               (time-domain loss) — Huber-White, band-averaged so that model error coherent
    #               over neighbouring frequencies is seen;
    #   "jackknife": the delete-a-group jackknife over the same groups (the sandwich with leverage
    #               correction), at the Student-t quantile of its effective degrees of freedom;
    #   "robust_sandwich" / "robust_jackknife": per parameter the larger of "model" and that variance
    #               (correlations of "model"). The app chooses per model (intervals.covariance: auto in
    #               configs/estimate.yaml; apps/estimate_plan.resolve_covariance).
    covariance: str = "model"
    # False: skip the final Jacobian pass (standard deviations, covariance, misfit test) — for a stage whose
    # result only starts the next one (window continuation); its std is then inf and its residual tests
    # unevaluated (inf), never a status it did not earn.
    uncertainty: bool = True
    covariance_band: int = 1
    covariance_dof: bool = True  # jackknife: Student-t quantile at its Satterthwaite degrees of freedom
    lm_initial_damping: float = 1e-3  # Levenberg-Marquardt only
    lm_min_damping: float = 1e-12
    lm_max_damping: float = 1e8


@dataclass
class LeastSquaresProblem:
    """Observed outputs of a batch, what drives them and what is known.

    targets   [batch, time, n_out] measured outputs (a3, a2, a1 for the quarter car); unobserved
              channels are never read
    inputs    what drives the model, [batch, time_in] or [batch, time_in, n_in] (the road u in
              metres, or p_u·u when ``scaled_road``, for the default Euler model); time_in ≥
              input_offset + time: samples around the fitted window sharpen the exact model's
              interpolation of the input near the window's edges; or those inputs already
              prepared for this window (``model.prepare``), when several solves share it
    input_offset  which input sample the first target belongs to
    observed  which of the n_out outputs enter the residual
    known     [n_theta] bool, entries of θ held fixed at their initial value (masked out of J)
    model     the :class:`ResponseModel`; None = the Euler recursion with ``h`` and ``scaled_road``
    """

    targets: Tensor
    inputs: Tensor
    h: float = 0.01
    scaled_road: bool = False
    observed: Sequence[bool] = (True, True, True)
    known: Tensor | None = None
    # [batch, n_out] per-channel residual weights (noise-aware weighting: 1/σ_c of each channel's
    # measurement noise); None = 1. Rows of R and J are multiplied by them.
    weights: Tensor | None = None
    model: ResponseModel | None = None
    # Gaussian prior on θ (MAP estimation, e.g. a network's prediction and variance): loss
    # + ½ Σ_j λ_j (θ_j − μ_j)², mean [batch, n_theta], precision λ [batch, n_theta] (0 = no prior
    # on that entry), in the units of the *weighted* residual (weights = 1/σ_noise make it a
    # posterior). None = maximum likelihood.
    prior_mean: Tensor | None = None
    prior_precision: Tensor | None = None
    input_offset: int = 0
    # The residual's noise model in the frequency domain (estimation/noise.py): the loss becomes the
    # errors-in-variables likelihood ½ Σ_k c_k R_kᴴ S_k(p)⁻¹ R_k / T without the DC term (sensor
    # offsets drop out); supersedes ``weights``. None: the time-domain loss above.
    noise: SpectralNoise | None = None

    def __post_init__(self):
        if self.model is None:
            self.model = EulerResponse(self.h, self.scaled_road)
        n_out, n_theta = len(self.model.output_names), self.model.n_theta
        if self.targets.ndim != 3 or self.targets.shape[-1] != n_out:
            raise ValueError(f"targets must be [batch, time, {n_out}], got {tuple(self.targets.shape)}")
        batch, n_steps = self.targets.shape[:2]
        self.input_offset = int(self.input_offset)
        samples = self.inputs.samples if isinstance(self.inputs, PreparedInputs) else self.inputs
        if (
            samples.ndim not in (2, 3)
            or samples.shape[0] != batch
            or self.input_offset < 0
            or samples.shape[1] < self.input_offset + n_steps
        ):
            raise ValueError(
                f"inputs {tuple(samples.shape)} must be [batch, time_in(, n_in)] with batch = {batch} "
                f"and time_in >= input_offset + time = {self.input_offset} + {n_steps}"
            )
        if isinstance(self.inputs, PreparedInputs):  # prepared by the caller: for this very window
            self.model.prepare(self.inputs, self.input_offset, n_steps)
        self.observed = tuple(bool(o) for o in self.observed)
        if len(self.observed) != n_out or not any(self.observed):
            raise ValueError(f"observed must name {n_out} channel flags with at least one True, got {self.observed}")
        known = (
            torch.zeros(n_theta, dtype=torch.bool)
            if self.known is None
            else torch.as_tensor(self.known, dtype=torch.bool).cpu()
        )
        if known.shape != (n_theta,):
            raise ValueError(
                f"known must be a [{n_theta}] bool mask ({', '.join(self.model.theta_names)}), "
                f"got shape {tuple(known.shape)}"
            )
        if bool(known.all()):
            raise ValueError(f"all {n_theta} unknowns are known: nothing to estimate")
        self.known = known
        if not torch.isfinite(self.targets[..., list(self.observed_index)]).all():
            raise ValueError("observed targets contain NaN/inf")
        if not torch.isfinite(samples).all():
            raise ValueError("inputs (road) contain NaN/inf")
        if (self.prior_mean is None) != (self.prior_precision is None):
            raise ValueError("a prior needs both prior_mean and prior_precision")
        if self.prior_mean is not None:
            self.prior_mean = torch.as_tensor(self.prior_mean, dtype=torch.float64)
            self.prior_precision = torch.as_tensor(self.prior_precision, dtype=torch.float64)
            shape = (self.targets.shape[0], n_theta)
            if tuple(self.prior_mean.shape) != shape or tuple(self.prior_precision.shape) != shape:
                raise ValueError(
                    f"prior_mean and prior_precision must be [batch, n_theta] = {list(shape)}, got "
                    f"{list(self.prior_mean.shape)} and {list(self.prior_precision.shape)}"
                )
            if not (
                torch.isfinite(self.prior_mean).all()
                and torch.isfinite(self.prior_precision).all()
                and (self.prior_precision >= 0).all()
            ):
                raise ValueError("prior_mean must be finite and prior_precision finite and >= 0")
        if self.noise is not None:
            if self.weights is not None:
                raise ValueError("give either weights or a noise model, not both")
            if self.noise.v_out.shape != (self.targets.shape[0], len(self.observed_index)):
                raise ValueError(
                    f"noise model variances must be [batch, n_observed] = "
                    f"[{self.targets.shape[0]}, {len(self.observed_index)}], got {list(self.noise.v_out.shape)}"
                )
        if self.weights is not None:
            self.weights = torch.as_tensor(self.weights, dtype=torch.float64)
            if tuple(self.weights.shape) != (self.targets.shape[0], n_out):
                raise ValueError(f"weights must be [batch, {n_out}], got {tuple(self.weights.shape)}")
            w = self.weights[:, self.observed_index]
            if not (torch.isfinite(w).all() and (w > 0).all()):
                raise ValueError("weights of observed channels must be finite and > 0")

    @property
    def observed_index(self) -> list[int]:
        return [i for i, o in enumerate(self.observed) if o]

    @property
    def window(self) -> tuple[int, int]:
        """(first input sample of the fit, number of fitted samples): what the model is asked for."""
        return self.input_offset, self.targets.shape[1]

    @property
    def road(self) -> Tensor:
        """The inputs under their historical name (the road of the quarter car)."""
        return self.inputs

    @property
    def n_theta(self) -> int:
        return self.model.n_theta

    @property
    def free_index(self) -> list[int]:
        return [i for i in range(self.n_theta) if not bool(self.known[i])]

    @property
    def n_residuals(self) -> int:
        # The spectral noise model leaves out the DC term of every channel.
        return (self.targets.shape[1] - (self.noise is not None)) * len(self.observed_index)


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


@contextmanager
def torch_threads(count: int | None) -> Iterator[None]:
    """torch's intra-op threads set to ``count`` (None or 0: unchanged) inside the block. The solver's
    tensors are small ([chunk, time] per step): more threads cost more in wake-ups than they save,
    and on a loaded machine each parallel region waits for a busy core (docs/measurements/real_recordings.md)."""
    before = torch.get_num_threads()
    if count:
        torch.set_num_threads(int(count))
    try:
        yield
    finally:
        torch.set_num_threads(before)


class NonlinearLeastSquares:
    """Base loop. Subclasses implement :meth:`direction` (and optionally :meth:`after_line_search`)."""

    def __init__(self, config: SolverConfig | None = None, **overrides):
        self.config = config or SolverConfig()
        for key, value in overrides.items():
            if not hasattr(self.config, key):
                raise TypeError(f"unknown solver setting {key!r}")
            setattr(self.config, key, value)
        if self.config.parametrization not in ("log", "linear", "unconstrained"):
            raise ValueError(f"solver parametrization must be 'log' or 'linear', got {self.config.parametrization!r}")
        if self.config.covariance not in COVARIANCES:
            raise ValueError(f"solver covariance={self.config.covariance!r}: choose one of {list(COVARIANCES)}")
        if int(self.config.covariance_band) < 1:
            raise ValueError(f"solver covariance_band={self.config.covariance_band!r}: must be an integer >= 1")

    # --- method hooks -------------------------------------------------------------------
    def init_state(self, batch: int, dtype) -> None:
        """Per-sample method state (e.g. LM damping); GN has none."""

    def direction(self, fisher_scaled: Tensor, gradient_scaled: Tensor, index: Tensor) -> Tensor:
        """Step in scaled coordinates from Fs [b, n, n] δs = gs [b, n]; ``index`` = sample ids."""
        raise NotImplementedError

    def after_line_search(self, index: Tensor, full_step_accepted: Tensor, any_step_accepted: Tensor) -> None:
        """Update method state after the line search of the samples ``index``."""

    def objective(self, problem: LeastSquaresProblem, params: Tensor) -> Tensor:
        """The loss every sample's solve minimises at θ ``params`` [batch, n_theta]: ½ Σ r² of the weighted or
        noise-whitened residual plus the prior's ½ Σ λ (θ − μ)² [batch] (inf where not finite). What a
        profile likelihood or a model comparison reads after the solve (SolverResult.loss is the data part)."""
        with torch_threads(self.config.num_threads), torch.no_grad():
            obs = problem.observed_index
            targets = problem.targets.to(torch.float64)[:, :, obs].contiguous()
            inputs = problem.inputs if isinstance(problem.inputs, PreparedInputs) else problem.inputs.to(torch.float64)
            road = problem.model.prepare(inputs, *problem.window)
            self._weights = None if problem.weights is None else problem.weights[:, obs].to(torch.float64).contiguous()
            index = torch.arange(params.shape[0])
            return self._loss_at(problem, params.detach().to(torch.float64), targets, road, index)

    # --- the loop -----------------------------------------------------------------------
    def solve(
        self, problem: LeastSquaresProblem, initial_params: Tensor, callback: IterationCallback | None = None
    ) -> SolverResult:
        """Minimise every sample's loss from ``initial_params`` = θ0 [batch, n_theta] (known entries kept)."""
        with torch_threads(self.config.num_threads), torch.no_grad():
            return self._solve(problem, initial_params, callback)

    def _solve(self, problem, initial_params, callback):
        cfg = self.config
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
        obs = problem.observed_index
        targets = problem.targets.to(dtype)[:, :, obs].contiguous()
        # Which free entries are physical parameters (> 0, steps judged relative to them); the
        # others (initial states) have any sign.
        self._positive = problem.model.positive[free]
        # targets [batch, time, n_obs]: the layout the recursion writes, so residuals need no permute.
        # The window's inputs as the model evaluates them repeatedly (the exact model holds them once).
        inputs = problem.inputs if isinstance(problem.inputs, PreparedInputs) else problem.inputs.to(dtype)
        road = problem.model.prepare(inputs, *problem.window)
        self._weights = (
            None if problem.weights is None else problem.weights[:, obs].to(dtype).contiguous()
        )  # [batch, n_obs]
        if problem.noise is not None:  # the targets as the loss sees them (at the start's p)
            weighted_targets = problem.noise.whiten_residual(targets, params, torch.arange(batch))
        else:
            weighted_targets = targets if self._weights is None else targets * self._weights[:, None, :]
        data_energy = 0.5 * weighted_targets.square().sum(dim=(1, 2))  # [batch]

        self.init_state(batch, dtype)
        status = torch.full((batch,), SolverStatus.MAX_ITERATIONS, dtype=torch.int8)
        iterations = torch.zeros(batch, dtype=torch.int64)
        loss = torch.full((batch,), math.inf, dtype=dtype)
        active = torch.ones(batch, dtype=torch.bool)
        bad_start = (params[:, free][:, self._positive] <= 0).any(dim=1)
        status[bad_start] = SolverStatus.DIVERGED
        active &= ~bad_start
        history = []
        seconds = []

        for iteration in range(cfg.max_iterations + 1):
            t0 = time.perf_counter()
            index = active.nonzero().squeeze(1)
            if iteration == cfg.max_iterations or index.numel() == 0:
                # No Jacobian needed to stop: the accepted losses are known from the line search.
                if iteration == 0:  # max_iterations = 0: just evaluate the start
                    loss[index] = self._loss_at(problem, params[index], targets, road, index)
                    history.append(torch.where(torch.isfinite(loss), loss, torch.zeros_like(loss)))
                exact = index[loss[index] <= cfg.loss_tol * data_energy[index]]
                status[exact] = SolverStatus.CONVERGED
                break
            fisher, gradient, loss_now = self._normal_equations(problem, params, targets, road, index)
            finite = (
                torch.isfinite(loss_now) & torch.isfinite(fisher).flatten(1).all(1) & torch.isfinite(gradient).all(1)
            )
            loss[index] = torch.where(finite, loss_now, loss[index])
            if iteration == 0:
                history.append(torch.where(torch.isfinite(loss), loss, torch.zeros_like(loss)))
            # A model that overflows at an accepted point cannot be continued: stop it there.
            if not bool(finite.all()):
                blown = index[~finite]
                status[blown] = SolverStatus.DIVERGED
                active[blown] = False
                index, fisher, gradient, loss_now = index[finite], fisher[finite], gradient[finite], loss_now[finite]
            tiny = loss_now <= cfg.loss_tol * data_energy[index]
            if bool(tiny.any()):  # exact fit already (noise-free data): nothing left to do
                done = index[tiny]
                status[done] = SolverStatus.CONVERGED
                active[done] = False
                index, fisher, gradient, loss_now = index[~tiny], fisher[~tiny], gradient[~tiny], loss_now[~tiny]
            if index.numel() == 0:
                break

            scale = fisher.diagonal(dim1=1, dim2=2).sqrt()  # column norms of J [b, n_free]
            safe_scale = torch.where(scale > 0, scale, torch.ones_like(scale))
            fisher_scaled = fisher / (safe_scale.unsqueeze(2) * safe_scale.unsqueeze(1))
            gradient_scaled = gradient / safe_scale
            step = self.direction(fisher_scaled, gradient_scaled, index) / safe_scale
            step = torch.where(scale > 0, step, torch.zeros_like(step))
            predicted = (step * gradient).sum(1)  # gᵀJᵀR ≥ 0 for a descent direction
            full_rel_step = self._relative_step(step, params[index][:, free])
            stationary = (full_rel_step <= cfg.step_tol) | (predicted <= cfg.decrease_tol * loss_now)
            if problem.noise is not None and cfg.decrement_tol:
                stationary |= predicted <= cfg.decrement_tol

            accepted_alpha, new_loss = self._line_search(
                problem, params, targets, road, index, free, step, loss_now, predicted
            )
            accepted = accepted_alpha > 0
            self.after_line_search(index, accepted_alpha == cfg.initial_step, accepted)

            # Update accepted samples (free parameters only: known ones stay bit-identical).
            acc_index = index[accepted]
            old_free = params[acc_index][:, free]
            new_free = self._apply_step(old_free, accepted_alpha[accepted].unsqueeze(1) * step[accepted])
            params[acc_index.unsqueeze(1), free.unsqueeze(0)] = new_free
            loss[acc_index] = new_loss[accepted]
            iterations[acc_index] += 1

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

            history.append(loss.clone())
            seconds.append(time.perf_counter() - t0)
            if callback is not None:
                callback(iteration + 1, loss, int(active.sum()))

        # An unconstrained path may end outside the physical domain: report it, keep the numbers.
        outside = (params[:, free][:, self._positive] <= 0).any(1)
        status[outside] = SolverStatus.DIVERGED
        history_t = torch.stack(history)
        history_t = torch.where(torch.isfinite(history_t), history_t, torch.zeros_like(history_t))
        if not cfg.uncertainty:
            return self._unfinished(problem, params, status, iterations, loss, history_t, seconds, free)
        return self._finish(problem, params, targets, road, free, status, iterations, loss, history_t, seconds)

    @staticmethod
    def _unfinished(problem, params, status, iterations, loss, history, seconds, free) -> SolverResult:
        """The result without its final Jacobian pass (SolverConfig.uncertainty = False): std inf (not
        evaluated; 0 for known entries), no covariance, residual tests not run (inf)."""
        batch, n_theta = params.shape[0], problem.n_theta
        std = torch.full((batch, n_theta), math.inf, dtype=params.dtype)
        std[:, problem.known] = 0.0
        unknown = torch.full((batch,), math.inf, dtype=params.dtype)
        return SolverResult(
            params=params,
            status=status,
            iterations=iterations,
            loss=loss,
            loss_history=history,
            std=std,
            covariance=torch.zeros(batch, n_theta, n_theta, dtype=params.dtype),
            singular_values=torch.zeros(batch, free.numel(), dtype=params.dtype),
            residual_variance=torch.zeros(batch, dtype=params.dtype),
            seconds=seconds,
            relative_residual=unknown,
            whiteness=unknown.clone(),
            model_std=std.clone(),
        )

    # --- pieces -------------------------------------------------------------------------
    def _prior_terms(self, problem, free_params: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
        """Precision λ [b, n_free] and deviation θ − μ [b, n_free] of the prior at ``free_params``."""
        free = torch.tensor(problem.free_index)
        precision = problem.prior_precision[index][:, free]
        return precision, free_params - problem.prior_mean[index][:, free]

    def _normal_equations(self, problem, params, targets, road, index, with_prior: bool = True):
        """With the prior (MAP): F + diag λ, JᵀR + λ (θ − μ), L + ½ Σ λ (θ − μ)²."""
        fisher, gradient, loss = self._data_normal_equations(problem, params, targets, road, index)
        if with_prior and problem.prior_mean is not None:
            precision, deviation = self._prior_terms(problem, params[index][:, torch.tensor(problem.free_index)], index)
            fisher = fisher + torch.diag_embed(precision)
            gradient = gradient + precision * deviation
            loss = loss + 0.5 * (precision * deviation.square()).sum(1)
        return fisher, gradient, loss

    def _data_normal_equations(self, problem, params, targets, road, index, band: int | None = None):
        """F = JᵀJ [b, n_free, n_free], JᵀR [b, n_free], L [b] for the samples ``index``; with ``band``
        also the score matrix of :func:`_score_groups` [b, n_free, n_free] and (G, Satterthwaite degrees of
        freedom [b, n_free] or None).

        The sensitivities come batch-major as [b, T, 3, 11] = (prediction | J); subtracting the
        targets from column 0 turns it into A = (R | J) and one bmm gives AᵀA = [[RᵀR, RᵀJ], [JᵀR, JᵀJ]].
        """
        free_cols = torch.tensor(problem.free_index) + 1  # column 0 of the tangents is the primal
        cols = torch.cat([torch.zeros(1, dtype=torch.long), free_cols])
        obs = problem.observed_index
        width = problem.n_theta + 1
        fishers, grads, losses, meats, dofs = [], [], [], [], []
        n_groups = 0
        for chunk in index.split(self.config.chunk_size):
            out = problem.model.sensitivities(params[chunk], road[chunk], *problem.window)  # [b, T, n_out, 1 + n_theta]
            if len(obs) < out.shape[2]:
                out = out[:, :, obs[0] : obs[0] + 1] if len(obs) == 1 else out[:, :, obs]
            out[..., 0] -= targets[chunk]  # residual R in column 0
            if problem.noise is not None:
                out = problem.noise.whiten(out, params[chunk], chunk)
            elif self._weights is not None:
                out *= self._weights[chunk][:, None, :, None]
            b = chunk.numel()
            augmented = out.view(b, -1, width) if out.is_contiguous() else out.reshape(b, -1, width)
            # [b, width, width]; numpy's per-sample BLAS: torch.bmm is 1.7x slower at width 18 (exact model)
            gram = batched_matmul(augmented.transpose(1, 2), augmented)
            if len(cols) < width:
                gram = gram[:, cols][:, :, cols]
            losses.append(0.5 * gram[:, 0, 0])
            grads.append(gram[:, 1:, 0])
            fishers.append(gram[:, 1:, 1:])
            if band is not None:
                meat, n_groups, dof = _score_groups(
                    out[..., cols], band, problem.noise is not None, self.config.covariance.endswith("jackknife")
                )
                meats.append(meat)
                dofs.append(dof)
        if band is not None:
            dof = None if dofs[0] is None else torch.cat(dofs)
            return torch.cat(fishers), torch.cat(grads), torch.cat(losses), torch.cat(meats), (n_groups, dof)
        return torch.cat(fishers), torch.cat(grads), torch.cat(losses)

    def _apply_step(self, free_params: Tensor, scaled_step: Tensor) -> Tensor:
        """θ - αδ, or p exp(-αδ/p) for the physical parameters in the log parametrization (same first-order step)."""
        new = free_params - scaled_step
        if self.config.parametrization == "log":
            logged = free_params * torch.exp(-scaled_step / free_params)
            new = torch.where(self._positive, logged, new)
        return new

    def _relative_step(self, step: Tensor, free_params: Tensor) -> Tensor:
        """max_j |δ_j| / p_j over the physical parameters [b] (inf when only initial states are free:
        then the decrease test alone decides)."""
        if not bool(self._positive.any()):
            return torch.full((step.shape[0],), math.inf, dtype=step.dtype)
        return (step[:, self._positive] / free_params[:, self._positive]).abs().amax(1)

    def _line_search(self, problem, params, targets, road, index, free, step, loss_now, predicted):
        """Per-sample Armijo backtracking; returns (α [b] with 0 = none found, new loss [b])."""
        cfg = self.config
        b = index.numel()
        alpha = torch.full((b,), cfg.initial_step, dtype=params.dtype)
        if cfg.max_relative_step:
            relative = self._relative_step(step, params[index][:, free])
            alpha = torch.minimum(alpha, cfg.max_relative_step / relative.clamp_min(1e-300))
        accepted_alpha = torch.zeros(b, dtype=params.dtype)
        new_loss = loss_now.clone()
        searching = predicted > 0  # a zero direction cannot decrease the loss
        for _ in range(cfg.max_backtracks + 1):
            pos = searching.nonzero().squeeze(1)
            if pos.numel() == 0:
                break
            trial = params[index[pos]].clone()
            trial[:, free] = self._apply_step(trial[:, free], alpha[pos].unsqueeze(1) * step[pos])
            positive = (
                (trial[:, free][:, self._positive] > 0).all(1)
                if cfg.parametrization != "unconstrained"
                else torch.ones(pos.numel(), dtype=torch.bool)
            )
            positive &= torch.isfinite(trial).all(1)  # an overflowing step (log space) is a failed trial
            trial_loss = torch.full((pos.numel(),), math.inf, dtype=params.dtype)
            if bool(positive.any()):
                # Evaluate only positive trials; the others count as Armijo failures.
                sub = positive.nonzero().squeeze(1)
                trial_loss[sub] = self._loss_at(problem, trial[sub], targets, road, index[pos[sub]])
            ok = torch.isfinite(trial_loss) & (trial_loss <= loss_now[pos] - cfg.armijo_c * alpha[pos] * predicted[pos])
            accepted_alpha[pos[ok]] = alpha[pos[ok]]
            new_loss[pos[ok]] = trial_loss[ok]
            searching[pos[ok]] = False
            alpha[pos[~ok]] *= 0.5
        return accepted_alpha, new_loss

    def _loss_at(self, problem, trial_params, targets, road, index) -> Tensor:
        obs = problem.observed_index
        losses = []
        for start in range(0, index.numel(), self.config.chunk_size * 2):
            sl = slice(start, start + self.config.chunk_size * 2)
            chunk = index[sl]
            accel = problem.model.outputs(trial_params[sl], road[chunk], *problem.window)
            residual = accel[:, :, obs] - targets[chunk]
            if problem.noise is not None:
                residual = problem.noise.whiten_residual(residual, trial_params[sl], chunk)
            elif self._weights is not None:
                residual = residual * self._weights[chunk][:, None, :]
            loss = 0.5 * residual.square().sum((1, 2))
            losses.append(torch.where(torch.isfinite(loss), loss, torch.full_like(loss, math.inf)))
        loss = torch.cat(losses)
        if problem.prior_mean is not None:
            precision, deviation = self._prior_terms(problem, trial_params[:, torch.tensor(problem.free_index)], index)
            loss = loss + 0.5 * (precision * deviation.square()).sum(1)
        return loss

    def _finish(self, problem, params, targets, road, free, status, iterations, loss, history, seconds) -> SolverResult:
        """Uncertainty and conditioning at the final estimate (one more Jacobian pass)."""
        cfg = self.config
        batch, n_free, n_theta = params.shape[0], free.numel(), problem.n_theta
        covariance = torch.zeros(batch, n_theta, n_theta, dtype=params.dtype)
        std = torch.zeros(batch, n_theta, dtype=params.dtype)
        relative_residual = torch.full((batch,), math.inf, dtype=params.dtype)
        whiteness = torch.full((batch,), math.inf, dtype=params.dtype)
        singular_values = torch.zeros(batch, n_free, dtype=params.dtype)
        residual_variance = torch.zeros(batch, dtype=params.dtype)
        index = (status != SolverStatus.DIVERGED).nonzero().squeeze(1)
        std[status == SolverStatus.DIVERGED] = math.inf
        std[:, problem.known] = 0.0
        model_std = std.clone()
        if index.numel():
            robust = cfg.covariance != "model"
            if robust:
                fisher, _, final_loss, meat, groups = self._data_normal_equations(
                    problem, params, targets, road, index, band=int(cfg.covariance_band)
                )
            else:
                fisher, _, final_loss = self._data_normal_equations(problem, params, targets, road, index)
            ok = torch.isfinite(fisher).flatten(1).all(1) & torch.isfinite(final_loss)
            fisher = torch.where(ok[:, None, None], fisher, torch.zeros_like(fisher))
            final_loss = torch.where(ok, final_loss, loss[index])
            loss[index] = final_loss
            pinv, unidentified, singular_values[index], rank_deficient = _pseudo_inverse(fisher, cfg.rcond)
            dof = max(problem.n_residuals - n_free, 1)
            sigma2 = 2.0 * final_loss / dof
            residual_variance[index] = sigma2
            misfit, relative_residual[index], whiteness[index], inflation = self._residual_tests(
                problem, params, targets, road, index
            )
            cov_free = (inflation * sigma2)[:, None, None] * pinv
            if problem.prior_mean is not None:
                # Laplace posterior: (data information + prior precision)⁻¹; the prior identifies
                # what the data alone cannot.
                precision, _ = self._prior_terms(problem, params[index][:, free], index)
                information = fisher / (inflation * sigma2).clamp_min(1e-300)[:, None, None] + torch.diag_embed(
                    precision
                )
                cov_free, unidentified, _, rank_deficient = _pseudo_inverse(information, cfg.rcond)
            model_std_free = cov_free.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt()
            if robust:
                cov_free = self._robust_covariance(problem, params, index, free, fisher, meat, groups, cov_free)
            std_free = torch.where(
                unidentified,
                torch.full_like(sigma2[:, None], math.inf),
                cov_free.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt(),
            )
            rows = index.unsqueeze(1)
            std[rows, free.unsqueeze(0)] = std_free
            model_std[rows, free.unsqueeze(0)] = torch.where(
                unidentified, torch.full_like(model_std_free, math.inf), model_std_free
            )
            cov_full = torch.zeros(index.numel(), n_theta, n_theta, dtype=params.dtype)
            cov_full[:, free.unsqueeze(1), free.unsqueeze(0)] = cov_free
            covariance[index] = cov_full
            rank_deficient = rank_deficient | ~ok
            status[index[rank_deficient]] = SolverStatus.SINGULAR
            status[index[misfit]] = SolverStatus.MISFIT  # a wrong answer is never `converged`
        return SolverResult(
            params=params,
            status=status,
            iterations=iterations,
            loss=loss,
            loss_history=history,
            std=std,
            covariance=covariance,
            singular_values=singular_values,
            residual_variance=residual_variance,
            seconds=seconds,
            relative_residual=relative_residual,
            whiteness=whiteness,
            model_std=model_std,
        )

    def _robust_covariance(self, problem, params, index, free, fisher, meat, groups, model_cov) -> Tensor:
        """Covariance [b, n_free, n_free] of the free θ by the ``covariance`` setting (SolverConfig).

        Sandwich: for the estimate θ̂ = argmin ½‖e(θ)‖², θ̂ − θ* ≈ −F⁻¹ Σ_g s_g with F = JᵀJ and s_g the
        score of group g, so Cov θ̂ ≈ F⁻¹ (Σ_g E s_g s_gᵀ) F⁻¹ whatever the residual's distribution, as
        long as the groups are uncorrelated. At θ̂ the scores sum to zero (n_free linear constraints),
        hence the small-sample factor G/(G − n_free) (G groups). Jackknife: ``meat`` is already the
        delete-a-group covariance (:func:`_score_groups`). With a prior (MAP) this data covariance C
        combines with the prior precision Λ as (C⁻¹ + Λ)⁻¹, as the model-based one does.
        "robust_*": per parameter the larger variance of ``model_cov`` and the robust one, applied as a
        diagonal rescaling of ``model_cov`` (stays positive semi-definite, keeps its correlations).
        With no more groups than unknowns there is no robust estimate: ``model_cov`` is returned.
        """
        cfg = self.config
        n_free = fisher.shape[-1]
        n_groups, dof = groups
        if n_groups <= n_free:  # fewer groups than unknowns (a short window, a wide band): nothing to estimate from
            return model_cov
        if cfg.covariance.endswith("jackknife"):
            data_cov = meat
            if cfg.covariance_dof:
                # The variance is estimated from few effective groups: widen to the Student-t quantile.
                nu = dof.clamp_min(1.0).numpy()
                ratio = torch.from_numpy(student_t.ppf(0.975, nu) / student_t.ppf(0.975, math.inf)).to(data_cov.dtype)
                data_cov = data_cov * ratio.unsqueeze(2) * ratio.unsqueeze(1)
        else:
            factor = n_groups / (n_groups - n_free)
            inverse, _, _, _ = _pseudo_inverse(fisher, cfg.rcond)
            data_cov = factor * inverse @ meat @ inverse
        if problem.prior_mean is not None:
            precision, _ = self._prior_terms(problem, params[index][:, free], index)
            information, _, _, _ = _pseudo_inverse(data_cov, cfg.rcond)
            data_cov, _, _, _ = _pseudo_inverse(information + torch.diag_embed(precision), cfg.rcond)
        if not cfg.covariance.startswith("robust"):
            return data_cov
        model_var = model_cov.diagonal(dim1=1, dim2=2).clamp_min(0)
        ratio = data_cov.diagonal(dim1=1, dim2=2) / model_var.clamp_min(1e-300)
        scale = torch.where(model_var > 0, ratio.clamp_min(1.0), torch.ones_like(ratio)).sqrt()
        return model_cov * scale.unsqueeze(2) * scale.unsqueeze(1)

    def _residual_tests(self, problem, params, targets, inputs, index) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Misfit test and covariance inflation from the final residuals of the samples ``index``.

        Per observed channel c: relative RMS r_c = ‖R_c‖/‖a_c‖ and the Ljung-Box statistic
        Q_c = N(N+2) Σ_{k≤K} ρ_k²/(N−k) of the residual's autocorrelations ρ_k (about the origin,
        so an unexplained offset counts as structure). Returns (misfit [b] bool, max_c r_c [b],
        max_c Q_c / χ²_K(1−α) [b] (> 1: not white), covariance inflation [b]).
        """
        cfg = self.config
        misfits, rel, white, inflation = [], [], [], []
        n_steps = targets.shape[1]
        lags = min(int(cfg.misfit_lags), n_steps - 2)
        threshold = float(chi2.ppf(1.0 - cfg.misfit_alpha, lags)) if lags > 0 else math.inf
        for start in range(0, index.numel(), self.config.chunk_size * 2):
            chunk = index[start : start + self.config.chunk_size * 2]
            residual = (
                problem.model.outputs(params[chunk], inputs[chunk], *problem.window)[:, :, problem.observed_index]
                - targets[chunk]
            )
            if problem.noise is not None:
                # Sensor offsets are outside the model (DC dropped): judge the size without them,
                # and test whiteness on the residual whitened by the noise model.
                residual = residual - residual.mean(1, keepdim=True)
                relative = (residual.square().sum(1) / targets[chunk].square().sum(1).clamp_min(1e-300)).sqrt()
                residual = problem.noise.white_time_residual(residual, params[chunk], chunk)
            energy = residual.square().sum(1)  # [b, n_obs]
            if problem.noise is None:
                relative = (energy / targets[chunk].square().sum(1).clamp_min(1e-300)).sqrt()
            q = torch.zeros_like(energy)
            rho1 = torch.zeros_like(energy)
            for k in range(1, lags + 1):
                rho = (residual[:, k:] * residual[:, :-k]).sum(1) / energy.clamp_min(1e-300)
                q += rho.square() / (n_steps - k)
                if k == 1:
                    rho1 = rho
            q *= n_steps * (n_steps + 2)
            structured = (q > threshold) & (relative > cfg.misfit_floor)
            misfits.append((structured | (relative > 1.0)).any(1))
            rel.append(relative.amax(1))
            white.append((q / threshold).amax(1) if lags > 0 else torch.zeros(chunk.numel(), dtype=q.dtype))
            # AR(1) effective-sample-size factor where the lag-1 correlation is significant.
            rho = rho1.mean(1)
            significant = rho > 2.0 / math.sqrt(n_steps)
            rho = rho.clamp(0.0, 0.98)
            inflation.append(torch.where(significant, (1 + rho) / (1 - rho), torch.ones_like(rho)))
        return torch.cat(misfits), torch.cat(rel), torch.cat(white), torch.cat(inflation)


def _score_groups(
    augmented: Tensor, band: int, spectral: bool, jackknife: bool = False
) -> tuple[Tensor, int, Tensor | None]:
    """Σ_g s_g s_gᵀ [b, n, n] of the per-group scores s_g = Σ_{rows in g} J_rᵀ e_r of the (whitened)
    stack ``augmented`` = (e | J) [b, rows, o, 1 + n], and the number of groups G. Spectral stack
    (rows = Re of K frequencies, then Im): a group is ``band`` adjacent frequencies from k = 1 (DC
    carries no rows), real and imaginary parts and all outputs together — at one frequency they are
    correlated, across frequencies asymptotically not (the DFT of a stationary process). Time-domain
    stack: ``band`` consecutive time steps.

    ``jackknife``: instead the delete-a-group jackknife covariance (G − 1)/G Σ_g (d_g − d̄)(d_g − d̄)ᵀ of
    the one-step shifts d_g = (F − F_g)⁻¹ s_g that leaving group g out makes (F = JᵀJ, F_g = J_gᵀJ_g):
    the sandwich with each score taken at its own leave-out fit, so a group that carries much of the
    information (a sharp resonance) is not under-weighted (the cluster "CR3" estimator)."""
    J = augmented[..., 1:]
    contributions = (J * augmented[..., :1]).sum(2)  # [b, rows, n]
    outer = torch.einsum("broi,broj->brij", J, J) if jackknife else None  # [b, rows, n, n]
    if spectral:
        K = contributions.shape[1] // 2
        contributions = (contributions[:, :K] + contributions[:, K:])[:, 1:]
        if outer is not None:
            outer = (outer[:, :K] + outer[:, K:])[:, 1:]
    b, rows, n = contributions.shape
    groups = -(-rows // band)
    pad = groups * band - rows
    scores = torch.nn.functional.pad(contributions, (0, 0, 0, pad)).view(b, groups, band, n).sum(2)
    if not jackknife:
        return torch.bmm(scores.transpose(1, 2), scores), groups, None
    group_fisher = torch.nn.functional.pad(outer, (0, 0, 0, 0, 0, pad)).view(b, groups, band, n, n).sum(2)
    fisher = group_fisher.sum(1, keepdim=True)  # [b, 1, n, n]
    left = fisher - group_fisher  # [b, G, n, n]
    # column scaling by F's diagonal, as in the steps (θ mixes parameters and initial states)
    scale = fisher.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()  # [b, 1, n]
    scaled = left / (scale.unsqueeze(-1) * scale.unsqueeze(-2))
    shifts, _ = _pseudo_inverse_solve(scaled.reshape(b * groups, n, n), (scores / scale).reshape(b * groups, n), 1e-7)
    shifts = shifts.view(b, groups, n) / scale  # d_g [b, G, n]
    centred = shifts - shifts.mean(1, keepdim=True)
    # Satterthwaite: a sum of G independent squares a_g² has (Σ a_g²)² / Σ a_g⁴ degrees of freedom.
    squares = centred.square()
    dof = squares.sum(1).square() / squares.square().sum(1).clamp_min(1e-300)  # [b, n]
    return (groups - 1) / groups * torch.bmm(centred.transpose(1, 2), centred), groups, dof


def _pseudo_inverse(matrix: Tensor, rcond: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pseudo-inverse of symmetric PSD matrices [b, n, n] with column scaling and an eigenvalue cutoff
    rcond² (relative to the largest). Returns (M⁺ [b, n, n], unidentified [b, n] — an entry with
    weight on a dropped direction, or a zero column —, singular values of the column-scaled factor
    [b, n] descending, rank_deficient [b])."""
    scale = matrix.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt()
    safe = torch.where(scale > 0, scale, torch.ones_like(scale))
    scaled = matrix / (safe.unsqueeze(2) * safe.unsqueeze(1))
    eigval, eigvec = torch.linalg.eigh(scaled)  # ascending
    eigval = eigval.clamp_min(0.0)
    keep = (eigval > (rcond**2) * eigval[:, -1:].clamp_min(1e-300)) & (eigval > 0)
    inv = torch.where(keep, 1.0 / eigval.clamp_min(1e-300), torch.zeros_like(eigval))
    pinv = (eigvec * inv.unsqueeze(1)) @ eigvec.transpose(1, 2) / (safe.unsqueeze(2) * safe.unsqueeze(1))
    unidentified = ((eigvec.square() * (~keep).unsqueeze(1).to(eigvec.dtype)).sum(2) > 1e-6) | (scale == 0)
    rank_deficient = (~keep).any(1) | (scale == 0).any(1)
    return pinv, unidentified, eigval.sqrt().flip(1), rank_deficient


def _pseudo_inverse_solve(matrix: Tensor, rhs: Tensor, rcond: float) -> tuple[Tensor, Tensor]:
    """Solve matrix [b, n, n] x = rhs [b, n] (symmetric PSD); Cholesky where well conditioned,
    eigen-decomposition with cutoff rcond² on the eigenvalues elsewhere. Returns (x, rank_deficient)."""
    x = torch.zeros_like(rhs)
    rank_deficient = torch.zeros(rhs.shape[0], dtype=torch.bool)
    if rhs.shape[0] == 0:
        return x, rank_deficient
    factor, info = torch.linalg.cholesky_ex(matrix)
    pivots = factor.diagonal(dim1=1, dim2=2)
    # The smallest Cholesky pivot² bounds the smallest eigenvalue from above: a cheap test for
    # which samples need the (slower) eigen-decomposition.
    max_diag = matrix.diagonal(dim1=1, dim2=2).amax(1).clamp_min(1e-300)
    well = (info == 0) & torch.isfinite(pivots).all(1) & (pivots.square().amin(1) > 1e3 * rcond**2 * max_diag)
    if bool(well.any()):
        x[well] = torch.cholesky_solve(rhs[well].unsqueeze(2), factor[well]).squeeze(2)
    if bool((~well).any()):
        ill = (~well).nonzero().squeeze(1)
        eigval, eigvec = torch.linalg.eigh(matrix[ill])
        keep = eigval > (rcond**2) * eigval[:, -1:].clamp_min(1e-300)
        inv = torch.where(keep, 1.0 / eigval.clamp_min(1e-300), torch.zeros_like(eigval))
        proj = (eigvec.transpose(1, 2) @ rhs[ill].unsqueeze(2)).squeeze(2)
        x[ill] = (eigvec @ (inv * proj).unsqueeze(2)).squeeze(2)
        rank_deficient[ill] = (~keep).any(1)
    return x, rank_deficient


class GaussNewton(NonlinearLeastSquares):
    """Gauss-Newton step δ = F⁺ JᵀR on the column-scaled normal equations."""

    def direction(self, fisher_scaled, gradient_scaled, index):
        step, _ = _pseudo_inverse_solve(fisher_scaled, gradient_scaled, self.config.rcond)
        return step


class LevenbergMarquardt(NonlinearLeastSquares):
    """Damped step (F + λ diag F) δ = JᵀR; λ per sample, shrunk after a full step, grown after backtracking."""

    def init_state(self, batch, dtype):
        self.damping = torch.full((batch,), self.config.lm_initial_damping, dtype=dtype)

    def direction(self, fisher_scaled, gradient_scaled, index):
        # Scaled F has unit diagonal (non-zero columns), so λ I is Marquardt's λ diag(F).
        lam = self.damping[index]
        eye = torch.eye(fisher_scaled.shape[-1], dtype=fisher_scaled.dtype)
        step, _ = _pseudo_inverse_solve(fisher_scaled + lam[:, None, None] * eye, gradient_scaled, self.config.rcond)
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
