"""The least-squares problem a solve fits (:class:`LeastSquaresProblem`) and its evaluation during one
solve (:class:`ProblemEvaluation`): the weighted or noise-whitened residual, its loss and the normal
equations F = JᵀJ, JᵀR with the Gaussian prior's terms (SPEC §8)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch
from torch import Tensor

from ._blas import even_slices, gram_matrix
from ._kernels import compiled_loops
from .noise import SpectralNoise
from .response import EulerResponse, PreparedInputs, ResponseModel
from .uncertainty import score_groups

# the fewest rows of a piece cut for another worker (ProblemEvaluation._pieces), in a Jacobian pass and in a
# line search's trial losses (rows about a fifth as costly): below, a call's own cost and the threads' wait for
# each other's Python outweigh the rows'
_MIN_PIECE = 64
_MIN_TRIAL_PIECE = 256


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

    def subset(self, rows: Tensor) -> LeastSquaresProblem:
        """The problem of the samples ``rows`` (every per-sample field indexed)."""
        b = self.targets.shape[0]

        def pick(value):
            if value is None:
                return None
            return value[rows] if isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == b else value

        return dataclasses.replace(
            self,
            targets=self.targets[rows],
            inputs=self.inputs[rows],
            weights=pick(self.weights),
            prior_mean=pick(self.prior_mean),
            prior_precision=pick(self.prior_precision),
            noise=None if self.noise is None else self.noise.subset(rows),
        )


class ProblemEvaluation:
    """A problem as one solve evaluates it, repeatedly: the observed targets [batch, time, n_obs] in float64
    (the layout the recursion writes, so residuals need no permute), the window's inputs prepared once
    (``road``; the exact model holds them), the observed channels' weights [batch, n_obs] or None,
    ``chunk_size`` samples per Jacobian pass, whether the score groups are the jackknife's and, with ``moments``,
    whether they carry the jackknife's working-model moments (uncertainty.score_groups).

    ``workers`` > 1: the chunks of a pass run on that many threads at once (CPU tensors only; the
    caller sets torch's intra-op threads to 1), cut so that the threads finish together where the model
    evaluates each sample on its own, else as one thread cuts them (_pieces); the results are joined in
    order, so the numbers are those of one thread, bit for bit. torch's ops and numpy's products release
    the GIL, which is what makes this the way to use a second core for the many small per-chunk operations
    (each op on two intra-op threads waits for the second one more than it gains; docs/measurements/roofline.md)."""

    def __init__(
        self,
        problem: LeastSquaresProblem,
        chunk_size: int,
        jackknife: bool = False,
        workers: int = 1,
        moments: bool = False,
    ):
        dtype = torch.float64
        obs = problem.observed_index
        self.problem = problem
        self.targets = problem.targets.to(dtype)[:, :, obs].contiguous()
        inputs = problem.inputs if isinstance(problem.inputs, PreparedInputs) else problem.inputs.to(dtype)
        self.road = problem.model.prepare(inputs, *problem.window)
        self.weights = None if problem.weights is None else problem.weights[:, obs].to(dtype).contiguous()
        self.chunk_size = chunk_size
        self.jackknife = jackknife
        self.moments = moments
        self.workers = max(1, int(workers)) if self.targets.device.type == "cpu" else 1

    @property
    def full_targets(self) -> Tensor:
        """The targets on every output channel [batch, time, n_out] (0 on the unobserved ones, which are
        dropped after the model's residual)."""
        n_out = len(self.problem.model.output_names)
        if self.targets.shape[2] == n_out:
            return self.targets
        if getattr(self, "_full_targets", None) is None:
            full = self.targets.new_zeros(*self.targets.shape[:2], n_out)
            full[:, :, self.problem.observed_index] = self.targets
            self._full_targets = full
        return self._full_targets

    def _pieces(self, n: int, size: int, least: int, apart: bool) -> list[slice]:
        """The rows 0..n-1 of a pass cut into pieces of at most ``size`` rows. One worker: ``size`` rows each and
        the rest. Several: the fewest pieces, of equal length to one row, and their count a multiple of the
        workers' where every piece keeps ``least`` rows (a pass of three pieces on two threads, or of 33 full
        ones and a rest, waits for its last one alone), where the model evaluates each sample of this pass on its
        own (``apart``: the model's outputs_apart or sensitivities_apart) with the compiled loops: then its numbers
        are the same in any piece. Elsewhere the pieces stay those of one worker (torch's Van Loan maps scale a
        whole batch by one power of two; ResponseModel.outputs_apart)."""
        if self.workers == 1 or n == 0 or not apart or not compiled_loops():
            return [slice(start, min(n, start + size)) for start in range(0, n, size)]
        count = -(-n // size)
        rounded = -(-count // self.workers) * self.workers
        if n // rounded >= least:
            count = rounded
        return even_slices(n, count)

    def _map(self, fn: Callable, chunks: list) -> list:
        """[fn(chunk) for chunk in chunks], on ``workers`` threads when there are several chunks."""
        if self.workers == 1 or len(chunks) < 2:
            return [fn(chunk) for chunk in chunks]
        with ThreadPoolExecutor(min(self.workers, len(chunks))) as pool:
            return list(pool.map(fn, chunks))

    def prior_terms(self, free_params: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
        """Precision λ [b, n_free] and deviation θ − μ [b, n_free] of the prior at ``free_params``."""
        problem = self.problem
        free = torch.tensor(problem.free_index)
        precision = problem.prior_precision[index][:, free]
        return precision, free_params - problem.prior_mean[index][:, free]

    def normal_equations(self, params, index, with_prior: bool = True):
        """With the prior (MAP): F + diag λ, JᵀR + λ (θ − μ), L + ½ Σ λ (θ − μ)²."""
        problem = self.problem
        fisher, gradient, loss = self.data_normal_equations(params, index)
        if with_prior and problem.prior_mean is not None:
            precision, deviation = self.prior_terms(params[index][:, torch.tensor(problem.free_index)], index)
            fisher = fisher + torch.diag_embed(precision)
            gradient = gradient + precision * deviation
            loss = loss + 0.5 * (precision * deviation.square()).sum(1)
        return fisher, gradient, loss

    def data_normal_equations(self, params, index, band: int | None = None):
        """F = JᵀJ [b, n_free, n_free], JᵀR [b, n_free], L [b] for the samples ``index``; with ``band``
        also the score matrix of :func:`~hybridqcm.estimation.uncertainty.score_groups` [b, n_free, n_free]
        and (G, the jackknife's moments [b, n_free, 3] or None: uncertainty.score_groups).

        The sensitivities come batch-major as [b, T, 3, 11] = (prediction | J); subtracting the
        targets from column 0 turns it into A = (R | J) and one bmm gives AᵀA = [[RᵀR, RᵀJ], [JᵀR, JᵀJ]].
        """
        problem, road = self.problem, self.road
        free_cols = torch.tensor(problem.free_index) + 1  # column 0 of the tangents is the primal
        cols = torch.cat([torch.zeros(1, dtype=torch.long), free_cols])
        obs = problem.observed_index
        width = problem.n_theta + 1
        full_targets = self.full_targets

        n_free, batch = len(cols) - 1, index.numel()
        # each chunk writes its own rows of F, JᵀR and L (the copies out of its Gram on its own thread, not one
        # serial join of the whole batch after them: ~40 ms of a 17 000-sample iteration)
        fisher = full_targets.new_empty(batch, n_free, n_free)
        gradient = full_targets.new_empty(batch, n_free)
        loss = full_targets.new_empty(batch)

        def rows(where, gram: Tensor) -> None:
            fisher[where] = gram[:, 1:, 1:]
            gradient[where] = gram[:, 1:, 0]
            loss[where] = 0.5 * gram[:, 0, 0]

        def one(chunk, where, fallback=False):
            model, args = problem.model, (params[chunk], road[chunk], *problem.window)
            if fallback:
                out, redo = model.fallback_sensitivities(*args), None
                out[..., 0] -= full_targets[chunk]
            else:  # [b, T, n_out, 1 + n_theta] with the residual R in column 0, and the rows to redo
                out, redo = model.residual_sensitivities(*args, full_targets[chunk])
            if len(obs) < out.shape[2]:
                out = out[:, :, obs[0] : obs[0] + 1] if len(obs) == 1 else out[:, :, obs]
            if problem.noise is not None:  # the score groups are frequency bands: only they need the DFT's rows
                out = problem.noise.whiten(out, params[chunk], chunk, frequency_rows=band is not None)
            elif self.weights is not None:
                out *= self.weights[chunk][:, None, :, None]
            b = chunk.numel()
            augmented = out.view(b, -1, width) if out.is_contiguous() else out.reshape(b, -1, width)
            gram = gram_matrix(augmented)  # [b, width, width]
            if len(cols) < width:
                gram = gram[:, cols][:, :, cols]
            scores = None
            if band is not None:
                scores = score_groups(out[..., cols], band, problem.noise is not None, self.jackknife, self.moments)
            rows(where, gram)  # the chunk's rows of the pass: a slice, or the fallback's positions
            return scores, redo

        pieces = self._pieces(index.numel(), self.chunk_size, _MIN_PIECE, problem.model.sensitivities_apart)
        parts = self._map(lambda piece: one(index[piece], piece), pieces)
        # the samples each chunk left to the model's fallback, by position in ``index``: one pass for all
        redo = torch.cat(
            [piece.start + part[1].to(index.device) for piece, part in zip(pieces, parts)]
            + [torch.zeros(0, dtype=torch.long, device=index.device)]
        )
        scores = _cat_scores([part[0] for part in parts])
        if redo.numel():
            positions = redo.split(self.chunk_size)
            fixes = self._map(lambda at: one(index[at], at.to(fisher.device), fallback=True), list(positions))
            redo = redo.to(fisher.device)
            if scores is not None:
                fixed = _cat_scores([fix[0] for fix in fixes])
                scores[0][redo] = fixed[0]
                if scores[2] is not None:
                    scores[2][redo] = fixed[2]
        if band is not None:
            meat, n_groups, moments = scores
            return fisher, gradient, loss, meat, (n_groups, moments)
        return fisher, gradient, loss

    def loss_at(self, trial_params, index) -> Tensor:
        """The loss [b] at θ ``trial_params`` [b, n_theta] of the samples ``index`` (inf where not finite)."""
        problem, targets, road = self.problem, self.targets, self.road
        obs = problem.observed_index

        def one(sl):
            chunk = index[sl]
            accel = problem.model.outputs(trial_params[sl], road[chunk], *problem.window)
            residual = accel[:, :, obs] - targets[chunk]
            if problem.noise is not None:
                residual = problem.noise.whiten_residual(residual, trial_params[sl], chunk, frequency_rows=False)
            elif self.weights is not None:
                residual = residual * self.weights[chunk][:, None, :]
            loss = 0.5 * residual.square().sum((1, 2))
            return torch.where(torch.isfinite(loss), loss, torch.full_like(loss, math.inf))

        pieces = self._pieces(index.numel(), self.chunk_size * 2, _MIN_TRIAL_PIECE, problem.model.outputs_apart)
        losses = self._map(one, pieces)
        loss = torch.cat(losses)
        if problem.prior_mean is not None:
            precision, deviation = self.prior_terms(trial_params[:, torch.tensor(problem.free_index)], index)
            loss = loss + 0.5 * (precision * deviation.square()).sum(1)
        return loss


def _cat_scores(scores: list) -> tuple | None:
    """score_groups' (meat, n_groups, moments or None) of several chunks joined; None without scores."""
    if not scores or scores[0] is None:
        return None
    moments = None if scores[0][2] is None else torch.cat([part[2] for part in scores])
    return torch.cat([part[0] for part in scores]), scores[-1][1], moments
