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
input, integrated against its posterior (:func:`_initial_state_prior`). Each candidate's prior probability
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
exp(log Z_c − log Z_max) is at least ``interval_weight``, and with those the residual tests reject that
have more evidence than the winner: two models the data cannot tell apart give an interval that holds
both answers.

Results are in one layout whatever the winner (``SelectionLayout``): the largest model's
parameters, τ and initial state, with NaN for what the chosen model has not (a rigid occupant has
no body mode).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.occupant import MODE_PARAMS, derived

from .profile import profile_interval
from .refinement import GaussNewtonRefinement
from .solver import SolverResult, SolverStatus


@dataclass
class SelectionLayout:
    """The common θ layout of the candidates: names, how many are parameters (with τ), outputs."""

    theta_names: tuple[str, ...]
    n_params: int
    output_names: tuple[str, ...]

    @property
    def n_theta(self) -> int:
        return len(self.theta_names)


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
    (M = K3 / p2). ``profile``: the winner's interval by profile likelihood (else its Laplace one)."""

    def __init__(
        self,
        candidates: Mapping[str, GaussNewtonRefinement],
        starts: Mapping[str, Tensor],
        K3: float,
        interval_weight: float = 0.05,
        delayed: Mapping[str, GaussNewtonRefinement] | None = None,
        profile: bool = True,
        profile_iterations: int = 8,
        polish_iterations: int = 5,
        model_prior: Mapping[str, float] | None = None,
        rescue: Mapping[str, GaussNewtonRefinement] | None = None,
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
        self._all = {**self.candidates, **{f"{n}+delay": r for n, r in self.delayed.items()}}
        self.response = _union_layout(self._all)
        self.max_modes = max((self._modes(r) for r in self._all.values()), default=0)
        # the rigid model's parameters, before the body's: (p1, p2) of the seat, p1..pN of a vehicle
        leads = {
            r.response.n_params - 3 * self._modes(r) - ("tau" in r.response.theta_names) for r in self._all.values()
        }
        if len(leads) != 1:
            raise ValueError(f"occupant models: the candidates disagree on the rigid model's parameters ({leads})")
        self.n_lead = leads.pop()
        self.extra_columns = (
            ["occupant_model"]
            + [f"logz_{n}" for n in self.names]
            + [f"m3_{n}" for n in self.names]
            + ["m3_interval"]
            + ["rigid_kg"]
            + [c for i in range(1, self.max_modes + 1) for c in (f"f{i}_hz", f"zeta{i}", f"mass{i}_kg")]
        )

    @staticmethod
    def _modes(refinement) -> int:
        return sum(1 for n in refinement.response.theta_names if n.startswith("r") and n[1:].isdigit())

    def refine_block(self, outputs: Mapping, module, block: int) -> dict:
        """The block's record (apps.estimate_shards.BlockRefinement's contract: nothing is kept)."""
        return self.refine(outputs, module)

    def refine(self, outputs: Mapping, module=None) -> dict:
        init = outputs["init"].double()[:, : self.n_lead]  # the batch's own vehicle per recording
        b = init.shape[0]
        records = {}
        for name, refinement in self.candidates.items():
            extra = self.starts.get(name, torch.zeros(0, dtype=torch.float64))
            records[name] = _fit(refinement, {**outputs, "init": torch.cat([init, extra.expand(b, -1)], 1)}, module)
        logz, fits = self._weigh(outputs, records, list(self.candidates))
        choice = self._choose(logz, fits, list(self.candidates))
        # The winner once more, with the channel delay. Where a candidate the data reject (misfit) has more
        # evidence than the winner, or none fits — noise-free data from two clocks leave the one-clock
        # models misfit, and a flexible one may absorb the delay's phase into a wrong fit — every candidate
        # with the delay, all weighed together.
        phase1 = choice.clone()
        logz1 = torch.stack([logz[n] for n in self.candidates], 1)
        fits1 = torch.stack([fits[n] for n in self.candidates], 1)
        winner_logz = logz1.gather(1, phase1[:, None])
        every = (~fits1 & (logz1 > winner_logz)).any(1) | ~fits1.any(1)
        for name, refinement in self.delayed.items():
            variant = f"{name}+delay"
            records[variant] = _empty_like(records[name], refinement.response.n_theta, refinement.response.n_params)
            logz[variant] = torch.full((b,), -math.inf, dtype=torch.float64)
            fits[variant] = torch.zeros(b, dtype=torch.bool)
            won = (phase1 == self.names.index(name)) & ~every
            rows = (won | every).nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            own = records[name]["params"][rows, : self.candidates[name].response.n_params].double()
            start = torch.cat([own, torch.zeros(rows.numel(), 1, dtype=torch.float64)], 1)
            _scatter(records[variant], _fit(refinement, {**_select(outputs, rows, b), "init": start}, module), rows)
            rows = won.nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            self._compare(outputs, records, logz, fits, choice, rows, [name, variant])
        rows = every.nonzero().squeeze(1)
        if self.delayed and rows.numel() > 0:
            self._compare(
                outputs, records, logz, fits, choice, rows, list(self.candidates) + [f"{n}+delay" for n in self.delayed]
            )
        self._rescue(outputs, records, logz, fits, choice, module)
        record = self._merge(records, choice)
        logz_t = torch.stack([logz[n] for n in self.names], 1)  # [b, C]
        fits_t = torch.stack([fits[n] for n in self.names], 1)
        record["m3_low"], record["m3_high"], profiled = self._interval(outputs, records, logz_t, fits_t, choice)
        extra = {"occupant_model": [self.names[int(c)] for c in choice]}
        for j, name in enumerate(self.names):
            extra[f"logz_{name}"] = logz_t[:, j]
            extra[f"m3_{name}"] = self.K3 / records[name]["params"][:, 1].double()
        extra["m3_interval"] = ["profile" if bool(p) else "laplace" for p in profiled]
        names = self.response.theta_names
        wanted = ["p1", "p2"] + [f"{k}{i}" for i in range(1, self.max_modes + 1) for k in MODE_PARAMS]
        body = torch.nan_to_num(record["params"][:, [names.index(n) for n in wanted]].double(), nan=0.0)
        for key, value in derived(body, self.K3).items():
            extra[key] = value
        modes = torch.tensor([self._modes(self._all[self.names[int(c)]]) for c in choice])
        for i in range(1, self.max_modes + 1):  # no such mode in the chosen model: not a number
            for key in (f"f{i}_hz", f"zeta{i}", f"mass{i}_kg"):
                extra[key] = torch.where(modes >= i, extra[key], torch.full_like(extra[key], math.nan))
        record["extra"] = extra
        return record

    def _compare(self, outputs, records: dict, logz: dict, fits: dict, choice: Tensor, rows: Tensor, names) -> None:
        """In place: the candidates ``names`` of the recordings ``rows`` weighed together (_weigh), the winner
        among them chosen there."""
        b = choice.numel()
        group = {n: _subset(records[n], rows) for n in names}
        group_logz, group_fits = self._weigh(_select(outputs, rows, b), group, list(names))
        for key in names:
            _scatter(records[key], group[key], rows)
            logz[key][rows], fits[key][rows] = group_logz[key], group_fits[key]
        choice[rows] = self._choose(group_logz, group_fits, list(names))

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
            sub = _select(outputs, rows, b)
            attempt = _fit(self.rescue[name], {**sub, "init": records[name]["init"][rows].double()}, module)
            good = _fits(attempt).nonzero().squeeze(1)
            if good.numel() == 0:
                continue
            rows, attempt = rows[good], _subset(attempt, good)
            sub_logz, sub_fits = self._weigh(_select(outputs, rows, b), {name: attempt}, [name])
            _scatter(records[name], attempt, rows)
            logz[name][rows], fits[name][rows] = sub_logz[name], sub_fits[name]

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
        for name in reversed(names):
            rows = ((records[name]["final"].status != SolverStatus.DIVERGED) & ~assigned).nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            noise = self._all[name].final_problem(_select(outputs, rows, b), records[name]["params"][rows]).noise
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
            self._nest(outputs, records, smaller, larger, v_out, v_in, assigned)
        logz, fits = {}, {}
        for name in names:
            record = records[name]
            logz[name] = torch.full((b,), -math.inf, dtype=torch.float64)
            rows = (assigned & (record["final"].status != SolverStatus.DIVERGED)).nonzero().squeeze(1)
            if rows.numel():
                variances = (v_out[rows], None if v_in is None else v_in[rows])
                weighed = self._polish_and_weigh(name, _select(outputs, rows, b), record, rows, variances)
                logz[name][rows] = weighed + self.log_prior[name.split("+")[0]]
            record["variances"] = (v_out, v_in, log_std)
            fits[name] = _fits(record)
        return logz, fits

    def _nest(self, outputs, records, smaller: str, larger: str, v_out, v_in, assigned: Tensor) -> None:
        """In place: where the ``larger`` candidate (which nests ``smaller``: an added body mode, or the delay)
        fits worse under the common noise model than ``smaller``'s estimate embedded in it (a new mode with a
        tenth of the rigid part's mass at the prior's frequency and damping, τ = 0, new states at rest) and
        polished, take that. A nesting model can always fit as well as the one it nests; a fit that does not
        is in another basin, and would lose the comparison for it."""
        b = assigned.shape[0]
        big, small = self._all[larger].response, self._all[smaller].response
        rows = (
            (
                assigned
                & (records[smaller]["final"].status != SolverStatus.DIVERGED)
                & (records[larger]["final"].status != SolverStatus.DIVERGED)
            )
            .nonzero()
            .squeeze(1)
        )
        if rows.numel() == 0 or not set(small.theta_names) <= set(big.theta_names):
            return
        fill = self.starts.get(larger.split("+")[0], torch.zeros(0, dtype=torch.float64))
        embedded = torch.zeros(rows.numel(), big.n_theta, dtype=torch.float64)
        theirs = records[smaller]["params"][rows].double()
        for j, name in enumerate(big.theta_names):
            if name in small.theta_names:
                embedded[:, j] = theirs[:, small.theta_names.index(name)]
            elif self.n_lead <= j < big.n_params and name != "tau":  # a new body mode's (r, k, c)
                embedded[:, j] = 0.1 if name.startswith("r") else fill[j - self.n_lead]
        refinement = self._all[larger]
        sub = _select(outputs, rows, b)
        variances = (v_out[rows], None if v_in is None else v_in[rows])
        mine = records[larger]["params"][rows].double()
        problem = refinement.final_problem(sub, mine, variances=variances)
        solver = _evaluation_solver(refinement, 3 * self.polish_iterations)
        result = solver.solve(problem, embedded)
        better = (result.status != SolverStatus.DIVERGED) & (
            solver.objective(problem, result.params) < solver.objective(problem, mine)
        )
        if bool(better.any()):
            _put(records[larger], result, rows[better], result.params[better], subset=better)

    def _polish_and_weigh(self, name: str, outputs: Mapping, record: dict, rows: Tensor, variances) -> Tensor:
        """[rows] log Z of candidate ``name``'s fits of the recordings ``rows`` (module docstring) under the
        noise ``variances``, after a few iterations from its estimate under them (``record`` updated where
        they lower the loss); -inf where not finite."""
        refinement = self._all[name]
        params = record["params"][rows].double()
        problem = refinement.final_problem(outputs, params, variances=variances)
        polish = _evaluation_solver(refinement, self.polish_iterations)
        before = polish.objective(problem, params)
        result = polish.solve(problem, params)
        after = polish.objective(problem, result.params)
        take = (result.status != SolverStatus.DIVERGED) & (after <= before)
        params = torch.where(take[:, None], result.params, params)
        loss = torch.where(take, after, before)
        if not bool(take.all()):  # the covariance at the kept estimate
            result = _evaluation_solver(refinement, 0).solve(problem, params)
        _put(record, result, rows, params)
        n_steps = problem.targets.shape[1]
        free = ~problem.known
        cov = result.covariance[:, free][:, :, free]
        sign, log_det_post = torch.linalg.slogdet(cov)
        log_det_post = torch.where(sign > 0, log_det_post, torch.full_like(log_det_post, -math.inf))
        precision = (torch.zeros_like(params) if problem.prior_precision is None else problem.prior_precision.double())[
            :, free
        ]
        proper = precision > 0
        names = [n for n, f in zip(refinement.response.theta_names, free.tolist()) if f]
        state = torch.tensor([n.startswith("x0_") for n in names])
        n_components = (n_steps - 1) * len(problem.observed_index)
        sigma = cov.diagonal(dim1=1, dim2=2).clamp_min(1e-300).sqrt()
        occam_flat = torch.where(proper | state, 0.0, 0.5 * math.log(n_components) + sigma.log()).sum(1)
        occam_prior = 0.5 * torch.where(proper, precision.clamp_min(1e-300).log(), 0.0).sum(1)
        x0 = params[:, [j for j, n in enumerate(refinement.response.theta_names) if n.startswith("x0_")]]
        value = -loss + 0.5 * log_det_post + occam_prior - occam_flat
        value = value + _initial_state_prior(refinement.response, problem, params, x0, cov[:, state][:, :, state])
        diverged = record["final"].status[rows] == SolverStatus.DIVERGED
        return torch.where(torch.isfinite(value) & ~diverged, value, torch.full_like(value, -math.inf))

    def _choose(self, logz: Mapping[str, Tensor], fits: Mapping[str, Tensor], names) -> Tensor:
        """[b] index into self.names of the highest evidence among the candidates that fit (all if none does)."""
        score = torch.stack([logz[n] for n in names], 1)
        ok = torch.stack([fits[n] for n in names], 1)
        eligible = torch.where(ok.any(1, keepdim=True), ok, torch.ones_like(ok))
        score = torch.where(eligible & torch.isfinite(score), score, torch.full_like(score, -math.inf))
        best = score.argmax(1)
        return torch.tensor([self.names.index(names[int(j)]) for j in best], dtype=torch.long)

    def _merge(self, records: Mapping[str, dict], choice: Tensor) -> dict:
        """The chosen candidate's results per recording, in the common layout (NaN where it has no entry)."""
        layout = self.response.theta_names
        b = choice.numel()
        params = torch.full((b, len(layout)), math.nan, dtype=torch.float64)
        std = torch.full_like(params, math.nan)
        model_std = torch.full_like(params, math.nan)
        covariance = torch.full((b, len(layout), len(layout)), math.nan, dtype=torch.float64)
        first = records[self.names[0]]["final"]
        n_sv = max(r["final"].singular_values.shape[1] for r in records.values())
        n_hist = max(r["final"].loss_history.shape[0] for r in records.values())
        merged = SolverResult(
            params=params,
            status=first.status.clone(),
            iterations=first.iterations.clone(),
            loss=first.loss.clone(),
            loss_history=torch.zeros(n_hist, b, dtype=torch.float64),
            std=std,
            covariance=covariance,
            singular_values=torch.zeros(b, n_sv, dtype=torch.float64),
            residual_variance=first.residual_variance.clone(),
            relative_residual=first.relative_residual.clone(),
            whiteness=first.whiteness.clone(),
            model_std=model_std,
        )
        restarts = torch.zeros(b, dtype=torch.int64)
        relative = torch.zeros(b, dtype=torch.float64)
        for j, name in enumerate(self.names):
            rows = (choice == j).nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            rec, res = records[name], records[name]["final"]
            theta_names = self._all[name].response.theta_names
            cols = torch.tensor([layout.index(n) for n in theta_names])
            if "tau" in layout and "tau" not in theta_names:
                params[rows, layout.index("tau")] = 0.0  # fitted on one clock
                std[rows, layout.index("tau")] = 0.0
            params[rows[:, None], cols] = rec["params"][rows].double()
            std[rows[:, None], cols] = res.std[rows].double()
            if res.model_std is not None:
                model_std[rows[:, None], cols] = res.model_std[rows].double()
            covariance[rows[:, None, None], cols[None, :, None], cols[None, None, :]] = res.covariance[rows].double()
            for field in ("status", "iterations", "loss", "residual_variance", "relative_residual", "whiteness"):
                getattr(merged, field)[rows] = getattr(res, field)[rows].to(getattr(merged, field).dtype)
            sv = res.singular_values[rows]
            merged.singular_values[rows, : sv.shape[1]] = sv.double()
            hist = res.loss_history[:, rows].double()
            merged.loss_history[:, rows] = torch.cat([hist, hist[-1:].expand(n_hist - hist.shape[0], -1)])
            restarts[rows] = rec["restarts"][rows]
            relative[rows] = rec["relative_loss"][rows].double()
        stages = {
            f"{name}/{stage}": result
            for name, rec in records.items()
            for stage, result in rec["stages"].items()
        }  # fmt: skip
        return {
            "index": records[self.names[0]]["index"],
            "init": records[self.names[0]]["init"][:, : self.n_lead],
            "stages": stages,
            "final": merged,
            "params": params,
            "restarts": restarts,
            "relative_loss": relative,
        }

    def _interval(self, outputs, records, logz: Tensor, fits: Tensor, choice: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(m3_low, m3_high, profiled) [b]: the winner's 95 % interval (profile likelihood where it could be
        computed, else Laplace) joined with the Laplace intervals of the other candidates that fit and weigh at
        least interval_weight of the winner."""
        b = choice.numel()
        lows, highs = [], []
        for name in self.names:
            res = records[name]["final"]
            p2, s2 = records[name]["params"][:, 1].double(), res.std[:, 1].double() * records[name]["robust"][:, 1]
            high_p2, low_p2 = p2 + 1.96 * s2, p2 - 1.96 * s2
            lows.append(self.K3 / high_p2)
            highs.append(torch.where(low_p2 > 0, self.K3 / low_p2.clamp_min(1e-300), torch.full_like(p2, math.inf)))
        low, high = torch.stack(lows, 1), torch.stack(highs, 1)  # [b, C] (NaN where a candidate did not run)
        profiled = torch.zeros(b, dtype=torch.bool)
        if self.profile:
            for j, name in enumerate(self.names):
                rows = ((choice == j) & (records[name]["final"].status != SolverStatus.DIVERGED)).nonzero().squeeze(1)
                if rows.numel() == 0:
                    continue
                p2_low, p2_high, _ = self._profile(name, _select(outputs, rows, b), records[name], rows)
                ok = torch.isfinite(p2_low) & torch.isfinite(p2_high) & (p2_high > 0)
                rows, p2_low, p2_high = rows[ok], p2_low[ok], p2_high[ok]
                # widened as the jackknife widened the candidate's own interval (the residual's spread)
                p2, ratio = records[name]["params"][rows, 1].double(), records[name]["robust"][rows, 1]
                p2_low, p2_high = p2 - ratio * (p2 - p2_low), p2 + ratio * (p2_high - p2)
                # never narrower than the Laplace interval it refines
                low[rows, j] = torch.minimum(low[rows, j], self.K3 / p2_high)
                high[rows, j] = torch.maximum(
                    high[rows, j],
                    torch.where(p2_low > 0, self.K3 / p2_low.clamp_min(1e-300), torch.full_like(p2_low, math.inf)),
                )
                profiled[rows] = True
        member = _interval_members(logz, fits, choice, self.interval_weight)
        member &= torch.isfinite(low) & ~torch.isnan(high)
        low = torch.where(member, low, torch.full_like(low, math.inf)).amin(1)
        high = torch.where(member, high, torch.full_like(high, -math.inf)).amax(1)
        return low, high, profiled

    def _profile(self, name: str, outputs: Mapping, record: dict, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(p2_low, p2_high, reached) [rows] of candidate ``name``'s fits of the recordings ``rows``."""
        refinement = self._all[name]
        params = record["params"][rows].double()
        v_out, v_in, log_std = record.get("variances", (None, None, None))
        variances = None if v_out is None else (v_out[rows], None if v_in is None else v_in[rows])
        problem = refinement.final_problem(outputs, params, variances=variances)
        evaluated = _evaluation_solver(refinement, 0).solve(problem, params)
        solver = _evaluation_solver(refinement, self.profile_iterations, "log")
        # in units of the residual variance where it exceeds the noise model's (as the Laplace covariance)
        scale = evaluated.residual_variance.double().clamp_min(1.0)
        low, high, reached = profile_interval(solver, problem, params, evaluated.covariance, 1, scale=scale)
        if v_in is None or log_std is None:
            return low, high, reached
        # The input noise's variance is fitted from this window and uncertain by tens of per cent
        # (noise.input_noise_log_std); the interval at its estimate treats it as known. Its effect on p2, by
        # a polish at e^δ times it, adds in quadrature to each half-width (delta method in log v_in).
        delta = 0.5
        shifted = problem.noise.subset(torch.arange(rows.numel()))
        shifted.v_in = shifted.v_in * math.exp(delta)
        moved = _evaluation_solver(refinement, self.polish_iterations).solve(
            dataclasses.replace(problem, noise=shifted), params
        )
        slope = (moved.params[:, 1] - params[:, 1]) / delta
        spread = 1.96 * slope.abs() * log_std[rows].amax(1)
        spread = torch.where(torch.isfinite(spread) & (moved.status != SolverStatus.DIVERGED), spread, 0.0)
        p2 = params[:, 1]
        high = p2 + ((high - p2).square() + spread.square()).sqrt()
        low = p2 - ((p2 - low).square() + spread.square()).sqrt()
        return low, high, reached


def _interval_members(logz: Tensor, fits: Tensor, choice: Tensor, interval_weight: float) -> Tensor:
    """[b, C] bool: the candidates whose intervals m3's interval joins — the chosen one, those that fit with an
    evidence weight exp(log Z_c - log Z_chosen) of at least ``interval_weight``, and those with more evidence
    than the chosen one although the residual tests reject them (a model that explains the data better but
    not to the noise floor: under sensor noise its answer, 50 % from the chosen one's, was the truth's)."""
    b = choice.numel()
    weight = torch.exp(logz - logz.gather(1, choice[:, None]))  # 0 where -inf
    chosen = torch.zeros_like(fits)
    chosen[torch.arange(b), choice] = True
    return chosen | ((fits | (weight > 1)) & (weight >= interval_weight))


def _fit(refinement: GaussNewtonRefinement, outputs: Mapping, module) -> dict:
    """One candidate's refinement of the batch, with ``robust`` [b, n_theta]: its reported standard deviations
    (the run's ``intervals.covariance``, a delete-a-band jackknife for a measured input) over the model-based
    ones, at least 1 — what the residual's own spread says beyond the noise model, kept for the intervals
    after the polish has replaced the standard deviations by model-based ones."""
    if hasattr(refinement, "refine_block"):  # keeps nothing between calls
        record = refinement.refine_block(outputs, module, 0)
    else:
        record = refinement.refine(outputs, module)
    final = record["final"]
    ratio = torch.ones_like(final.std, dtype=torch.float64)
    if final.model_std is not None:
        ratio = (final.std.double() / final.model_std.double().clamp_min(1e-300)).nan_to_num(1.0, 1.0, 1.0)
    record["robust"] = ratio.clamp_min(1.0)
    return record


def _fits(record: dict) -> Tensor:
    status = record["final"].status
    return status.ne(SolverStatus.MISFIT) & status.ne(SolverStatus.DIVERGED)


def _evaluation_solver(refinement: GaussNewtonRefinement, max_iterations: int, parametrization: str | None = None):
    """The refinement's last-stage solver with the model-based covariance, ``max_iterations`` and, where given,
    another ``parametrization`` (a profile's points: "log", so that a step cannot take a body mass near zero
    through it and end the constrained solve `diverged`)."""
    solver = refinement.stages[-1].solver
    config = dataclasses.replace(
        solver.config,
        covariance="model",
        max_iterations=int(max_iterations),
        parametrization=parametrization or solver.config.parametrization,
    )
    return type(solver)(config)


def _select(outputs: Mapping, rows: Tensor, b: int) -> dict:
    """The batch's outputs of the recordings ``rows`` (every per-recording tensor indexed)."""
    return {k: (v[rows] if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == b else v) for k, v in outputs.items()}


def _empty_like(record: dict, n_theta: int, n_params: int) -> dict:
    """A record of the same batch where nothing was fitted: NaN estimates, status diverged."""
    final = record["final"]
    b = final.status.shape[0]
    nan = torch.full((b, n_theta), math.nan, dtype=torch.float64)
    result = SolverResult(
        params=nan.clone(),
        status=torch.full_like(final.status, int(SolverStatus.DIVERGED)),
        iterations=torch.zeros_like(final.iterations),
        loss=torch.full_like(final.loss, math.inf),
        loss_history=torch.zeros(1, b, dtype=torch.float64),
        std=torch.full_like(nan, math.inf),
        covariance=torch.full((b, n_theta, n_theta), math.nan, dtype=torch.float64),
        singular_values=torch.zeros(b, n_theta, dtype=torch.float64),
        residual_variance=torch.full((b,), math.nan, dtype=torch.float64),
        relative_residual=torch.full((b,), math.inf, dtype=torch.float64),
        whiteness=torch.full((b,), math.inf, dtype=torch.float64),
        model_std=torch.full_like(nan, math.inf),
    )
    return {
        "index": record["index"],
        "init": torch.full((b, n_params), math.nan, dtype=torch.float64),
        "stages": {},
        "final": result,
        "params": nan,
        "restarts": torch.zeros(b, dtype=torch.int64),
        "relative_loss": torch.full((b,), math.inf, dtype=torch.float64),
        "robust": torch.ones(b, n_theta, dtype=torch.float64),
    }


def _scatter(into: dict, record: dict, rows: Tensor) -> None:
    """In place: the sub-batch ``record`` (of the recordings ``rows``) into the full-batch record ``into``."""
    src, dst = record["final"], into["final"]
    for field in ("params", "status", "iterations", "loss", "std", "covariance", "residual_variance"):
        getattr(dst, field)[rows] = getattr(src, field).to(getattr(dst, field).dtype)
    for field in ("relative_residual", "whiteness", "model_std"):
        if getattr(src, field) is not None:
            getattr(dst, field)[rows] = getattr(src, field).to(getattr(dst, field).dtype)
    n_sv = src.singular_values.shape[1]
    dst.singular_values[rows, :n_sv] = src.singular_values.double()
    history = torch.zeros(src.loss_history.shape[0], dst.status.shape[0], dtype=torch.float64)
    history[:, rows] = src.loss_history.double()
    dst.loss_history = history
    into["params"][rows] = record["params"].double()
    into["init"][rows] = record["init"].double()
    into["robust"][rows] = record["robust"].double()
    if "variances" in record:  # the noise model the sub-batch was weighed under
        b = into["params"].shape[0]
        mine = into.get("variances") or tuple(
            None if v is None else torch.zeros(b, *v.shape[1:], dtype=v.dtype) for v in record["variances"]
        )
        into["variances"] = tuple(
            None if (m is None or v is None) else m.index_copy(0, rows, v) for m, v in zip(mine, record["variances"])
        )
    into["restarts"][rows] = record["restarts"]
    into["relative_loss"][rows] = record["relative_loss"].double()
    into["stages"] = {**into["stages"], **record["stages"]}


def _subset(record: dict, rows: Tensor) -> dict:
    """The record of the recordings ``rows`` (a copy)."""
    final = record["final"]
    fields = {f.name: getattr(final, f.name) for f in dataclasses.fields(final)}
    for key, value in fields.items():
        if isinstance(value, Tensor) and value.ndim > 0:
            fields[key] = value[:, rows].clone() if key == "loss_history" else value[rows].clone()
    return {
        "index": record["index"][rows],
        "init": record["init"][rows],
        "stages": {},
        "final": SolverResult(**fields),
        "params": record["params"][rows].clone(),
        "restarts": record["restarts"][rows].clone(),
        "relative_loss": record["relative_loss"][rows].clone(),
        "robust": record["robust"][rows].clone(),
    }


def _put(record: dict, result: SolverResult, rows: Tensor, params: Tensor, subset: Tensor | None = None) -> None:
    """In place: the polished estimates ``params`` [rows] with ``result``'s uncertainty and residual tests
    (under the common noise model, at ``params``; ``result``'s samples ``subset`` where given) into
    ``record``'s rows."""
    final = record["final"]
    record["params"][rows] = params.to(record["params"].dtype)
    final.params[rows] = params.to(final.params.dtype)
    pick = slice(None) if subset is None else subset
    for field in ("std", "covariance", "model_std", "relative_residual", "whiteness", "residual_variance"):
        value = getattr(result, field)
        if value is not None and getattr(final, field) is not None:
            getattr(final, field)[rows] = value[pick].to(getattr(final, field).dtype)
    # The refinement's status stands (a short polish ends at its iteration limit by design), except that
    # the residual tests under the common noise model can expose a misfit that a model's own noise fit hid.
    status = final.status[rows]
    exposed = (result.status[pick] == SolverStatus.MISFIT) & (status != SolverStatus.DIVERGED)
    final.status[rows] = torch.where(exposed, result.status[pick].to(status.dtype), status)


def _initial_state_prior(response, problem, params: Tensor, x0: Tensor, posterior: Tensor) -> Tensor:
    """[b] log N(x̂0; 0, P + Σ_x) without its 2π: the initial state's prior integrated against its Gaussian
    posterior (covariance ``posterior`` Σ_x [b, n, n], mean x̂0 = ``x0``; the outputs are linear in x0, so
    this is the exact marginal at the Laplace level). P is the state's covariance in steady state under
    the measured input (Parseval over the window's periodogram, P = Σ_k c_k Re(X_k U_k U_kᴴ X_kᴴ) / T²,
    X_k = (jω_k I − A)⁻¹ B). An initial state is informed by the window's first instants only (its
    transient decays): charging it the unit-information Occam factor ½ log N, as a parameter that every
    sample informs, would penalise a body model's two extra states by ~6 nats and hand light persons to
    the rigid model."""
    linear = response.model
    p = params[:, : linear.n_params].double()
    A, B, _, _ = linear.matrices(p)
    inputs = problem.inputs.samples if hasattr(problem.inputs, "samples") else problem.inputs
    start, n_steps = problem.window
    window = inputs[:, start : start + n_steps].double()
    window = window if window.ndim == 3 else window[..., None]
    U = torch.fft.rfft(window, dim=1).to(torch.complex128)  # [b, K, m]
    omega = 2 * math.pi * torch.fft.rfftfreq(n_steps, d=float(response.h), dtype=torch.float64)
    n = A.shape[-1]
    eye = torch.eye(n, dtype=torch.complex128)
    pencil = (1j * omega)[None, :, None, None] * eye - A.to(torch.complex128)[:, None]
    X = torch.linalg.solve(pencil, B.to(torch.complex128)[:, None] @ U[..., None])  # [b, K, n, 1]
    c = torch.full((omega.numel(),), 2.0, dtype=torch.float64)
    c[0] = 0.0
    if n_steps % 2 == 0:
        c[-1] = 1.0
    P = ((X @ X.conj().transpose(-1, -2)).real * c[None, :, None, None]).sum(1) / n_steps**2  # [b, n, n]
    P = (
        P
        + posterior.double()
        + 1e-12 * P.diagonal(dim1=1, dim2=2).mean(1).clamp_min(1e-300)[:, None, None] * torch.eye(n)
    )
    sign, log_det = torch.linalg.slogdet(P)
    quad = (x0.double()[:, None, :] @ torch.linalg.solve(P, x0.double()[:, :, None]))[:, 0, 0]
    value = -0.5 * log_det - 0.5 * quad
    return torch.where((sign > 0) & torch.isfinite(value), value, torch.full_like(value, -math.inf))
