"""Which occupant sits on the seat: every candidate model fitted, one chosen per recording, honest intervals.

A seated person is a rigid mass only at low frequency (physics/occupant.py). Each recording is fitted
with every candidate occupant model — a rigid mass, one body mode, two body modes — by its own
:class:`GaussNewtonRefinement` (stages, noise model, restarts), and per recording the candidate with the
highest (Laplace) evidence wins:

    log Z_c = −L_c(θ̂) + ½ log det Σ_c + ½ Σ_{j: prior} log λ_j − Σ_{j: no prior} (½ log N + log σ_j)
              + log N(x̂0; 0, P + Σ_x)

L_c is the last stage's loss at its estimate (the noise-whitened residual's ½ Σ e² plus the prior's
½ Σ λ (θ − μ)², :meth:`GaussNewtonRefinement.final_problem`) under one noise model for all candidates
(:meth:`OccupantSelection._weigh`), Σ_c the Laplace posterior covariance of the free unknowns, λ the
prior precisions (the literature's body ranges on recordings with a sensor noise floor) and σ_j the
posterior standard deviations of the parameters without a prior (p1, p2, a delay), each charged the
unit-information Occam factor 1/√N of N residual components (so that, without any prior, the comparison
is the Bayesian information criterion's). The likelihood is the errors-in-variables one with the true
input profiled out (estimation/noise.py): its normalisation, log det of the input and output noise,
is the same for every model, while ½ Σ_k log S_k(θ) — the Gaussian normalisation of the residual's
spectrum, which grows with |H(θ)| — is not a part of it (with it, every body model's resonance paid
~90 nats against a rigid seat's flatter transmissibility). The initial state (a transient that the window's first instants inform, not every
sample) is charged instead its own Gaussian prior: the state's steady-state covariance under the measured
input, integrated against its posterior (:func:`~hybridqcm.estimation.occupant_evidence.initial_state_prior`). Each candidate's prior probability
``model_prior`` adds its logarithm: a seat's occupant is a person, and a person is rigid only as the
limit of no resonating body mass (ballast is the exception), so the rigid model gets a small share — under
sensor noise some persons' data are as well explained by a rigid mass 30 % heavier, and without it the
rigid model's few parameters won those recordings by its Occam factor. A candidate whose fit ended
`diverged` or `misfit` is out of the race unless every candidate's did.

Two clocks (``delayed``): the winner is then fitted once more with the channel delay τ as an unknown
(estimation/delay.py), started from its own estimate; the delayed fit replaces it where its evidence is
higher. One extra fit per recording instead of one per candidate, and a delay that the data do not
show costs its Occam factor instead of shifting a noisy person's body mode.

The static mass M = K3 / p2 is the winner's. Its 95 % interval is the profile-likelihood interval
of p2 under the winner (estimation/profile.py: under sensor noise the posterior of a person's static
mass and the share of the body that resonates is a banana, and the Laplace interval misses on one
side), joined with the Laplace intervals of the other candidates that fit and whose evidence weight
exp(log Z_c − log Z_max) is at least ``interval_weight`` (default e^-5: only evidence that Kass and Raftery
call very strong rules a candidate out), and with those the residual tests reject that have more evidence
than the winner: two models the data cannot tell apart give an interval that holds both answers.

Results are in one layout whatever the winner (``SelectionLayout``): the largest model's
parameters, τ and initial state, with NaN for what the chosen model has not (a rigid occupant has
no body mode).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch
from torch import Tensor

from hybridqcm.physics.occupant import MODE_PARAMS, derived

from ._blas import available_cores, op_threads, parallel_map
from .occupant_evidence import nest, polish_and_weigh
from .occupant_interval import VERY_STRONG, static_mass_interval
from .occupant_records import empty_like, fit_candidate, merge, record_fits, scatter, select_rows, subset
from .refinement import GaussNewtonRefinement
from .solver import SolverStatus


@dataclass
class SelectionLayout:
    """The common θ layout of the candidates: names, how many are parameters (with τ), outputs."""

    theta_names: tuple[str, ...]
    n_params: int
    output_names: tuple[str, ...]

    @property
    def n_theta(self) -> int:
        return len(self.theta_names)


@dataclass
class PhaseClock:
    """Seconds of one block's selection by phase (``PHASES``; "total": the whole of ``refine``, so what it holds
    beyond the phases is the records' assembly): ``wall`` and this process's ``cpu`` seconds — the phases run
    one after another, so each is exact, while the threads of a phase (``workers``) overlap inside it — and
    ``fit_wall`` and ``fit_cpu``: each candidate's own fit, wall seconds and CPU seconds of its thread (on the
    workers each fit's ops run on one intra-op thread, ``_blas.parallel_map``; with one worker they sum to the
    process's CPU over "fits"), so the candidates' costs stay apart when they overlap. summary.json sums them
    over the blocks (``seconds_phases``): where a selection's time goes, without a profiler."""

    wall: dict[str, float] = field(default_factory=dict)
    cpu: dict[str, float] = field(default_factory=dict)
    fit_wall: dict[str, float] = field(default_factory=dict)
    fit_cpu: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - t0
            self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - c0

    def as_dict(self) -> dict:
        return {
            "wall": dict(self.wall),
            "cpu": dict(self.cpu),
            "fit_wall": dict(self.fit_wall),
            "fit_cpu": dict(self.fit_cpu),
        }


# the selection's phases, in order: the candidates' fits, their weighing (the common noise model, the nests, the
# polishes, the evidence), the winners' delay variants and their weighing, the rescue fits, the m3 interval
PHASES = ("fits", "weigh", "delay_fits", "delay_weigh", "rescue", "interval")


def _union_layout(candidates: Mapping[str, GaussNewtonRefinement]) -> SelectionLayout:
    params: list[str] = []
    states: list[str] = []
    for refinement in candidates.values():
        r = refinement.response
        for name in r.theta_names[: r.n_params]:
            if name not in params:
                params.append(name)
        for name in r.theta_names[r.n_params :]:
            if name not in states:
                states.append(name)
    params.sort(key=lambda n: (n == "tau", 0))  # τ after the physical parameters
    # velocities before displacements, as in every model's own state vector
    states.sort(key=lambda n: (not n.startswith("x0_d"), n))
    first = next(iter(candidates.values())).response
    return SelectionLayout(tuple(params) + tuple(states), len(params), tuple(first.output_names))


class OccupantSelection:
    """Fits every candidate (name -> refinement) to each batch and keeps one per recording (module docstring).

    ``starts``: name -> extra start values [k] appended to the batch's (p1, p2) for that candidate
    (its body parameters). ``delayed``: name -> the refinement of that candidate with the channel delay
    (θ = its parameters, then τ), fitted where that candidate wins. ``K3``: the seat stiffness
    (M = K3 / p2). ``profile``: the winner's interval by profile likelihood (else its Laplace one).
    ``workers``: threads that run the independent solves of a batch at once — the candidates' fits, the
    delay variants', each candidate's polish under a noise model, the winners' profiles (_blas.parallel_map:
    the same numbers as one thread); None: the cores this process may use (_blas.available_cores, judged at
    each batch); always one where a candidate's solver runs torch on several threads itself."""

    def __init__(
        self,
        candidates: Mapping[str, GaussNewtonRefinement],
        starts: Mapping[str, Tensor],
        K3: float,
        interval_weight: float = VERY_STRONG,
        delayed: Mapping[str, GaussNewtonRefinement] | None = None,
        profile: bool = True,
        profile_iterations: int = 8,
        polish_iterations: int = 5,
        model_prior: Mapping[str, float] | None = None,
        rescue: Mapping[str, GaussNewtonRefinement] | None = None,
        workers: int | None = 1,
    ) -> None:
        if not candidates:
            raise ValueError("occupant models: the list of candidate models is empty")
        if not 0 < float(interval_weight) <= 1:
            raise ValueError(f"interval_weight must be in (0, 1], got {interval_weight!r}")
        delayed = dict(delayed or {})
        unknown = sorted(set(delayed) - set(candidates))
        if unknown:
            raise ValueError(f"delayed variants of {unknown} have no candidate of that name")
        self.candidates = dict(candidates)
        self.delayed = delayed
        self.names = list(self.candidates) + [f"{n}+delay" for n in self.delayed]
        self.starts = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in starts.items()}
        self.K3 = float(K3)
        self.interval_weight = float(interval_weight)
        self.profile = bool(profile)
        self.profile_iterations = int(profile_iterations)
        self.polish_iterations = int(polish_iterations)
        prior = {n: 1.0 for n in self.candidates} if model_prior is None else dict(model_prior)
        if set(prior) != set(self.candidates) or not all(math.isfinite(v) and v > 0 for v in prior.values()):
            raise ValueError(f"model_prior must give every candidate {list(self.candidates)} a probability > 0")
        self.rescue = dict(rescue or {})
        total = sum(prior.values())
        self.log_prior = {n: math.log(v / total) for n, v in prior.items()}
        self.all_models = {**self.candidates, **{f"{n}+delay": r for n, r in self.delayed.items()}}
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be an integer >= 1 or None (the available cores), got {workers!r}")
        threaded = any(
            (op_threads(stage.solver.config) or 1) > 1
            for r in [*self.all_models.values(), *self.rescue.values()]
            for stage in getattr(r, "stages", ())
        )
        self._workers = 1 if threaded else workers
        self.response = _union_layout(self.all_models)
        self.max_modes = max((self._modes(r) for r in self.all_models.values()), default=0)
        # the rigid model's parameters, before the body's: (p1, p2) of the seat, p1..pN of a vehicle
        leads = {
            r.response.n_params - 3 * self._modes(r) - ("tau" in r.response.theta_names)
            for r in self.all_models.values()
        }
        if len(leads) != 1:
            raise ValueError(f"occupant models: the candidates disagree on the rigid model's parameters ({leads})")
        self.n_lead = leads.pop()
        self.extra_columns = (
            ["occupant_model"]
            + [f"logz_{n}" for n in self.names]
            + [f"m3_{n}" for n in self.names]
            + ["m3_interval", "at_boundary"]
            + ["rigid_kg"]
            + [c for i in range(1, self.max_modes + 1) for c in (f"f{i}_hz", f"zeta{i}", f"mass{i}_kg")]
        )

    @property
    def workers(self) -> int:
        """Threads for the batch's independent solves (the constructor's ``workers``)."""
        return available_cores() if self._workers is None else self._workers

    def collapsed(self, name: str, params: Tensor) -> Tensor:
        """[b] bool: candidate ``name``'s fits ``params`` [b, n_theta] that hold a body mode at r_i = 0 (the
        solver's boundary test: the data do not resolve what the mode adds). Such a fit is a smaller model of the
        set (body1 at r1 = 0 is rigid, body2 at r_i = 0 is body1), already fitted in its own right; its evidence
        is at most that model's likelihood times the prior's mass where the mode is unresolved, so it is out of
        the comparison (log Z -inf, not fitting; estimates.csv's ``at_boundary`` names it), not `diverged`."""
        cols = self.all_models[name].response.boundary.nonzero().flatten()
        if cols.numel() == 0:
            return torch.zeros(params.shape[0], dtype=torch.bool)
        return (params[:, cols].double() == 0).any(1)

    def cost(self, name: str, rows: int) -> int:
        """A solve of candidate ``name`` on ``rows`` recordings, relative to the others' (the body modes' states make
        it dearer): independent solves are handed to the threads largest first, so the small ones fill in."""
        return rows * (1 + self._modes(self.all_models[name]))

    def solve_all(self, function: Callable, jobs: list, costs: list[int]) -> list:
        """[function(job) for job in jobs] on the selection's threads (_blas.parallel_map), the dearest job
        (``costs``, each a ``cost``) handed out first; the results in the jobs' order."""
        order = sorted(range(len(jobs)), key=lambda i: -costs[i])
        results = [None] * len(jobs)
        for i, result in zip(order, parallel_map(lambda i: function(jobs[i]), order, self.workers)):
            results[i] = result
        return results

    @staticmethod
    def _modes(refinement) -> int:
        return sum(1 for n in refinement.response.theta_names if n.startswith("r") and n[1:].isdigit())

    def refine_block(self, outputs: Mapping, module, block: int) -> dict:
        """The block's record (estimation.shards.BlockRefinement's contract: nothing is kept)."""
        return self.refine(outputs, module)

    def refine(self, outputs: Mapping, module=None) -> dict:
        """The block's record (module docstring), with ``phase_seconds``: PhaseClock.as_dict()."""
        clock = PhaseClock()
        with clock.phase("total"):
            record = self._refine(outputs, module, clock)
        record["phase_seconds"] = clock.as_dict()
        return record

    def _refine(self, outputs: Mapping, module, clock: PhaseClock) -> dict:
        init = outputs["init"].double()[:, : self.n_lead]  # the batch's own vehicle per recording
        b = init.shape[0]

        def fit(name: str) -> dict:
            t0, c0 = time.perf_counter(), time.thread_time()
            extra = self.starts.get(name, torch.zeros(0, dtype=torch.float64))
            start = torch.cat([init, extra.expand(b, -1)], 1)
            record = fit_candidate(self.candidates[name], {**outputs, "init": start}, module)
            # one thread per candidate: no two write one key
            clock.fit_wall[name] = time.perf_counter() - t0
            clock.fit_cpu[name] = time.thread_time() - c0
            return record

        names = list(self.candidates)
        with clock.phase("fits"):
            records = dict(zip(names, self.solve_all(fit, names, [self.cost(n, b) for n in names])))
        with clock.phase("weigh"):
            logz, fits = self._weigh(outputs, records, names)
            choice = self._choose(logz, fits, names)
        # The winner once more, with the channel delay. Where a candidate the data reject (misfit) has more
        # evidence than the winner, or none fits — noise-free data from two clocks leave the one-clock
        # models misfit, and a flexible one may absorb the delay's phase into a wrong fit — every candidate
        # with the delay, all weighed together.
        phase1 = choice.clone()
        logz1 = torch.stack([logz[n] for n in self.candidates], 1)
        fits1 = torch.stack([fits[n] for n in self.candidates], 1)
        winner_logz = logz1.gather(1, phase1[:, None])
        every = (~fits1 & (logz1 > winner_logz)).any(1) | ~fits1.any(1)
        # Each variant's fit reads its candidate's estimates on the recordings it won or on `every`; a compare
        # writes only the recordings its candidate won (not `every`): the fits run first, all at once.
        jobs = []
        for name, refinement in self.delayed.items():
            variant = f"{name}+delay"
            records[variant] = empty_like(records[name], refinement.response.n_theta, refinement.response.n_params)
            logz[variant] = torch.full((b,), -math.inf, dtype=torch.float64)
            fits[variant] = torch.zeros(b, dtype=torch.bool)
            won = (phase1 == self.names.index(name)) & ~every
            rows = (won | every).nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            own = records[name]["params"][rows, : self.candidates[name].response.n_params].double()
            start = torch.cat([own, torch.zeros(rows.numel(), 1, dtype=torch.float64)], 1)
            jobs.append((name, rows, won, {**select_rows(outputs, rows, b), "init": start}))
        with clock.phase("delay_fits"):
            done = self.solve_all(
                lambda job: fit_candidate(self.delayed[job[0]], job[3], module),
                jobs,
                [self.cost(f"{name}+delay", rows.numel()) for name, rows, _, _ in jobs],
            )
        with clock.phase("delay_weigh"):
            for (name, rows, won, _), record in sorted(zip(jobs, done), key=lambda pair: self.names.index(pair[0][0])):
                variant = f"{name}+delay"
                scatter(records[variant], record, rows)
                rows = won.nonzero().squeeze(1)
                if rows.numel() == 0:
                    continue
                self._compare(outputs, records, logz, fits, choice, rows, [name, variant])
            rows = every.nonzero().squeeze(1)
            if self.delayed and rows.numel() > 0:
                everyone = list(self.candidates) + [f"{n}+delay" for n in self.delayed]
                self._compare(outputs, records, logz, fits, choice, rows, everyone)
        with clock.phase("rescue"):
            self._rescue(outputs, records, logz, fits, choice, module)
        record = merge(self, records, choice)
        logz_t = torch.stack([logz[n] for n in self.names], 1)  # [b, C]
        fits_t = torch.stack([fits[n] for n in self.names], 1)
        with clock.phase("interval"):
            record["m3_low"], record["m3_high"], profiled = static_mass_interval(
                self, outputs, records, logz_t, fits_t, choice
            )
        extra = {"occupant_model": [self.names[int(c)] for c in choice]}
        for j, name in enumerate(self.names):
            extra[f"logz_{name}"] = logz_t[:, j]
            extra[f"m3_{name}"] = self.K3 / records[name]["params"][:, 1].double()
        extra["m3_interval"] = ["profile" if bool(p) else "laplace" for p in profiled]
        held = {n: self.collapsed(n, records[n]["params"]) for n in self.names}
        extra["at_boundary"] = [" ".join(n for n in self.names if bool(held[n][i])) for i in range(b)]
        names = self.response.theta_names
        wanted = ["p1", "p2"] + [f"{k}{i}" for i in range(1, self.max_modes + 1) for k in MODE_PARAMS]
        body = torch.nan_to_num(record["params"][:, [names.index(n) for n in wanted]].double(), nan=0.0)
        for key, value in derived(body, self.K3).items():
            extra[key] = value
        modes = torch.tensor([self._modes(self.all_models[self.names[int(c)]]) for c in choice])
        for i in range(1, self.max_modes + 1):  # no such mode in the chosen model: not a number
            for key in (f"f{i}_hz", f"zeta{i}", f"mass{i}_kg"):
                extra[key] = torch.where(modes >= i, extra[key], torch.full_like(extra[key], math.nan))
        record["extra"] = extra
        record["candidates"] = self._candidates(records, fits)
        return record

    def _candidates(self, records: Mapping[str, dict], fits: Mapping[str, Tensor]) -> dict:
        """Every candidate's estimate per recording in the common parameter layout (τ last), for a caller that
        pools recordings under one model (aggregate=drive, reports/drive.py): params [b, C, P], the model-based
        covariance [b, C, P, P] after the polish, robust [b, C, P] (the reported standard deviation over it, as
        the intervals scale it), prior_mean and prior_precision [b, C, P] (the prior in that covariance, NaN where
        not polished), status [b, C] and fits [b, C] (neither misfit nor diverged); C = self.names,
        NaN where a candidate has no such parameter or was not fitted."""
        layout = list(self.response.theta_names[: self.response.n_params])
        b, n_c, n_p = next(iter(records.values()))["params"].shape[0], len(self.names), len(layout)
        params = torch.full((b, n_c, n_p), math.nan, dtype=torch.float64)
        covariance = torch.full((b, n_c, n_p, n_p), math.nan, dtype=torch.float64)
        robust = torch.ones(b, n_c, n_p, dtype=torch.float64)
        prior = {k: torch.full((b, n_c, n_p), math.nan, dtype=torch.float64) for k in ("prior_mean", "prior_precision")}
        status = torch.zeros(b, n_c, dtype=torch.long)
        for j, name in enumerate(self.names):
            rec, n = records[name], self.all_models[name].response.n_params
            cols = torch.tensor([layout.index(x) for x in self.all_models[name].response.theta_names[:n]])
            params[:, j, cols] = rec["params"][:, :n].double()
            robust[:, j, cols] = rec["robust"][:, :n].double()
            for key, value in prior.items():
                if key in rec:  # the polish's prior (NaN: a fit not polished)
                    value[:, j, cols] = rec[key][:, :n].double()
            covariance[:, j, cols[:, None], cols[None, :]] = rec["final"].covariance[:, :n, :n].double()
            status[:, j] = rec["final"].status.long()
        fitted = torch.stack([fits[n] for n in self.names], 1)
        return {"params": params, "covariance": covariance, "robust": robust, "status": status, "fits": fitted, **prior}

    def _compare(self, outputs, records: dict, logz: dict, fits: dict, choice: Tensor, rows: Tensor, names) -> None:
        """In place: the candidates ``names`` of the recordings ``rows`` weighed together (_weigh), the winner
        among them chosen there; the recordings' other candidates weighed again under the same noise (_reweigh)."""
        b = choice.numel()
        group = {n: subset(records[n], rows) for n in names}
        group_logz, group_fits = self._weigh(select_rows(outputs, rows, b), group, list(names))
        for key in names:
            scatter(records[key], group[key], rows)
            logz[key][rows], fits[key][rows] = group_logz[key], group_fits[key]
        choice[rows] = self._choose(group_logz, group_fits, list(names))
        self._reweigh(outputs, records, logz, fits, rows, names, group[names[-1]]["variances"])

    def _reweigh(self, outputs, records: dict, logz: dict, fits: dict, rows: Tensor, names, variances) -> None:
        """In place: the candidates of the recordings ``rows`` other than ``names`` that were weighed before
        (finite log Z) polished and weighed under ``variances`` (v_out, v_in, log_std [len(rows), ...]), the
        noise model ``names`` were just weighed under. Evidences weighed under different noise models are not
        comparable: each _weigh fits the variances at its own most flexible candidate (one that ended misfit
        gives others, with band_cap up to hundreds of nats apart), and every reader of a recording's log Z
        (the interval's members, the logz_* columns, a drive's model summed over its windows) compares them."""
        b = next(iter(records.values()))["params"].shape[0]
        v_out, v_in, log_std = variances
        if v_out is None:
            return
        # where every one of ``names`` diverged, no noise was fitted (_weigh's placeholder): nothing to weigh under
        noise = torch.stack([records[n]["final"].status[rows] != SolverStatus.DIVERGED for n in names]).any(0)
        jobs = []
        for key in self.names:
            if key in names or key not in logz:  # a delay variant not set up yet: not fitted
                continue
            local = (torch.isfinite(logz[key][rows]) & noise).nonzero().squeeze(1)
            if local.numel() == 0:
                continue
            record = subset(records[key], rows[local])
            record["variances"] = tuple(None if v is None else v[local] for v in (v_out, v_in, log_std))
            jobs.append((key, rows[local], record))

        def polished(job) -> Tensor:  # a copy of the candidate's record (subset), in place
            key, at, record = job
            here = torch.arange(at.numel())
            return polish_and_weigh(self, key, select_rows(outputs, at, b), record, here, record["variances"][:2])

        costs = [self.cost(key, at.numel()) for key, at, _ in jobs]
        for (key, at, record), weighed in zip(jobs, self.solve_all(polished, jobs, costs)):
            scatter(records[key], record, at)
            logz[key][at] = weighed + self.log_prior[key.split("+")[0]]
            fits[key][at] = record_fits(record)

    def _rescue(self, outputs, records: dict, logz: dict, fits: dict, choice: Tensor, module) -> None:
        """In place: where the chosen candidate's fit is `misfit` or `diverged` (a wrong basin), its refinement
        with restarts (``rescue``) from the same start; a restart that fits replaces it (weighed again under
        its own noise model). Candidates run without restarts: in the comparison a misfit model is a model the
        data reject, and restarting every rejected one (all of them, on a recording with a channel delay) was
        most of the selection's time."""
        b = choice.numel()
        for j, name in enumerate(self.names):
            rows = ((choice == j) & ~fits[name]).nonzero().squeeze(1)
            if rows.numel() == 0 or name not in self.rescue:
                continue
            sub = select_rows(outputs, rows, b)
            attempt = fit_candidate(self.rescue[name], {**sub, "init": records[name]["init"][rows].double()}, module)
            good = record_fits(attempt).nonzero().squeeze(1)
            if good.numel() == 0:
                continue
            rows, attempt = rows[good], subset(attempt, good)
            sub_logz, sub_fits = self._weigh(select_rows(outputs, rows, b), {name: attempt}, [name])
            scatter(records[name], attempt, rows)
            logz[name][rows], fits[name][rows] = sub_logz[name], sub_fits[name]
            self._reweigh(outputs, records, logz, fits, rows, [name], attempt["variances"])

    def _weigh(self, outputs: Mapping, records: dict, names: list[str]) -> tuple[dict, dict]:
        """Evidence and fit flags of the candidates ``names`` (their records, in place) under one noise model.

        The sensors' noise is the recording's, not a model's: each candidate's own variances would let a
        model that explains less call its misfit noise and lose nothing. The variances are those fitted at the
        most flexible candidate's estimate (the last of ``names`` that did not diverge; they nest: rigid is
        a body model without body mass), every candidate is polished under them (a few iterations from its
        estimate; kept where it lowers the loss) and weighed there."""
        b = next(iter(records.values()))["params"].shape[0]
        v_out, v_in, log_std = None, None, None
        assigned = torch.zeros(b, dtype=torch.bool)
        held = {n: self.collapsed(n, records[n]["params"]) for n in names}
        for name in reversed(names):  # a fit held at its boundary is a smaller model's: not the most flexible
            ok = (records[name]["final"].status != SolverStatus.DIVERGED) & ~held[name]
            rows = (ok & ~assigned).nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            noise = (
                self.all_models[name].final_problem(select_rows(outputs, rows, b), records[name]["params"][rows]).noise
            )
            if v_out is None:
                v_out = torch.ones(b, noise.v_out.shape[1], dtype=torch.float64)
                if noise.v_in is not None:
                    v_in = torch.zeros(b, noise.v_in.shape[1], dtype=torch.float64)
                    log_std = torch.zeros_like(v_in)
            v_out[rows] = noise.v_out
            if v_in is not None:
                v_in[rows] = noise.v_in if noise.v_in is not None else 0.0
                if noise.v_in_log_std is not None:
                    log_std[rows] = noise.v_in_log_std
            assigned[rows] = True
        for smaller, larger in zip(names, names[1:]):
            nest(self, outputs, records, smaller, larger, v_out, v_in, assigned)
        held = {n: self.collapsed(n, records[n]["params"]) for n in names}  # a nest may have moved a fit
        weigh = {
            name: (assigned & (records[name]["final"].status != SolverStatus.DIVERGED) & ~held[name])
            .nonzero()
            .squeeze(1)
            for name in names
        }
        jobs = [n for n in names if weigh[n].numel()]

        def polished(name: str) -> Tensor:  # each candidate's own record, in place
            rows = weigh[name]
            variances = (v_out[rows], None if v_in is None else v_in[rows])
            return polish_and_weigh(self, name, select_rows(outputs, rows, b), records[name], rows, variances)

        weighed = dict(zip(jobs, self.solve_all(polished, jobs, [self.cost(n, weigh[n].numel()) for n in jobs])))
        logz, fits = {}, {}
        for name in names:
            record = records[name]
            logz[name] = torch.full((b,), -math.inf, dtype=torch.float64)
            if name in weighed:
                logz[name][weigh[name]] = weighed[name] + self.log_prior[name.split("+")[0]]
            record["variances"] = (v_out, v_in, log_std)
            fits[name] = record_fits(record) & ~held[name]
        return logz, fits

    def _choose(self, logz: Mapping[str, Tensor], fits: Mapping[str, Tensor], names) -> Tensor:
        """[b] index into self.names of the highest evidence among the candidates that fit (all if none does)."""
        score = torch.stack([logz[n] for n in names], 1)
        ok = torch.stack([fits[n] for n in names], 1)
        eligible = torch.where(ok.any(1, keepdim=True), ok, torch.ones_like(ok))
        score = torch.where(eligible & torch.isfinite(score), score, torch.full_like(score, -math.inf))
        best = score.argmax(1)
        return torch.tensor([self.names.index(names[int(j)]) for j in best], dtype=torch.long)
