"""Which occupant sits on the seat: every candidate model fitted, one chosen per recording, honest intervals.

A seated person is a rigid mass only at low frequency (physics/occupant.py). Each recording is
fitted with every candidate occupant model — rigid, one body mode, two body modes, each with the
channel delay τ when it is estimated — by its own :class:`GaussNewtonRefinement` (stages, noise
model, restarts), and per recording the model with the lowest Bayesian information criterion wins:

    BIC_c = N log(RSS_c / N) + k_c log N

with RSS_c the time-domain residual sum of squares of the observed channels over the fitted window
(without each channel's mean: a sensor offset is no model's business), N the number of residuals and
k_c the free unknowns (parameters, τ and the initial state). A candidate whose fit ended `diverged`
or `misfit` is out of the race unless every candidate did. The reported static mass M = K3 / p2 is
the chosen model's; its 95 % interval is the union of the intervals of every candidate that fits
and whose BIC weight exp(-ΔBIC/2) is at least ``interval_weight`` of the winner's, so that two
models the data cannot tell apart give an interval that holds both answers.

Results are in one layout whatever the winner (``SelectionLayout``): the largest model's
parameters, τ and initial state, with NaN for what the chosen model has not (a rigid occupant has
no body mode).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.occupant import derived

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
    (its body parameters and τ). ``K3``: the seat stiffness (M = K3 / p2)."""

    def __init__(
        self,
        candidates: Mapping[str, GaussNewtonRefinement],
        starts: Mapping[str, Tensor],
        K3: float,
        interval_weight: float = 0.05,
    ) -> None:
        if not candidates:
            raise ValueError("occupant models: the list of candidate models is empty")
        if not 0 < float(interval_weight) <= 1:
            raise ValueError(f"interval_weight must be in (0, 1], got {interval_weight!r}")
        self.candidates = dict(candidates)
        self.names = list(self.candidates)
        self.starts = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in starts.items()}
        self.K3 = float(K3)
        self.interval_weight = float(interval_weight)
        self.response = _union_layout(self.candidates)
        self.max_modes = max((self._modes(r) for r in self.candidates.values()), default=0)
        self.extra_columns = (
            ["occupant_model"]
            + [f"bic_{n}" for n in self.names]
            + [f"m3_{n}" for n in self.names]
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
        init = outputs["init"].double()[:, :2]
        b = init.shape[0]
        records, bic, fits = {}, [], []
        for name, refinement in self.candidates.items():
            extra = self.starts.get(name, torch.zeros(0, dtype=torch.float64))
            start = torch.cat([init, extra.expand(b, -1)], 1)
            if hasattr(refinement, "refine_block"):  # keeps nothing between calls
                record = refinement.refine_block({**outputs, "init": start}, module, 0)
            else:
                record = refinement.refine({**outputs, "init": start}, module)
            records[name] = record
            bic.append(self._bic(refinement, outputs, record))
            status = record["final"].status
            fits.append(status.ne(SolverStatus.MISFIT) & status.ne(SolverStatus.DIVERGED))
        bic_t, fits_t = torch.stack(bic, 1), torch.stack(fits, 1)  # [b, C]
        # the race: among fits if any candidate fits, else among all
        eligible = torch.where(fits_t.any(1, keepdim=True), fits_t, torch.ones_like(fits_t))
        score = torch.where(eligible & torch.isfinite(bic_t), bic_t, torch.full_like(bic_t, math.inf))
        choice = score.argmin(1)
        record = self._merge(records, choice)
        best = score.gather(1, choice[:, None])
        weight = torch.exp(-0.5 * (score - best))  # 0 where inf
        record["m3_low"], record["m3_high"] = self._interval(records, weight, fits_t, choice)
        extra = {"occupant_model": [self.names[int(c)] for c in choice]}
        for j, name in enumerate(self.names):
            extra[f"bic_{name}"] = bic_t[:, j]
            extra[f"m3_{name}"] = self.K3 / records[name]["params"][:, 1].double()
        params = record["params"][:, : self.response.n_params]
        names = self.response.theta_names[: self.response.n_params]
        body = torch.nan_to_num(params[:, [i for i, n in enumerate(names) if n != "tau"]], nan=0.0)
        for key, value in derived(body[:, : 2 + 3 * self.max_modes], self.K3).items():
            extra[key] = value
        modes = torch.tensor([self._modes(self.candidates[self.names[int(c)]]) for c in choice])
        for i in range(1, self.max_modes + 1):  # no such mode in the chosen model: not a number
            for key in (f"f{i}_hz", f"zeta{i}", f"mass{i}_kg"):
                extra[key] = torch.where(modes >= i, extra[key], torch.full_like(extra[key], math.nan))
        record["extra"] = extra
        return record

    def _bic(self, refinement: GaussNewtonRefinement, outputs: Mapping, record: dict) -> Tensor:
        """[b] BIC of one candidate's final fit (module docstring); inf where not finite."""
        targets = outputs["targets"].double()
        offset = int(outputs.get("input_offset", 0))
        with torch.no_grad():
            predicted = refinement.response.outputs(
                record["params"].double(), outputs["road"].double(), offset, targets.shape[1]
            )
        residual = predicted - targets
        residual = residual - residual.mean(1, keepdim=True)
        n = residual.shape[1] * residual.shape[2]
        rss = residual.square().sum((1, 2)).clamp_min(1e-300)
        k = int((~refinement.known).sum())
        bic = n * torch.log(rss / n) + k * math.log(n)
        return torch.where(torch.isfinite(bic), bic, torch.full_like(bic, math.inf))

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
            cols = torch.tensor([layout.index(n) for n in self.candidates[name].response.theta_names])
            if "tau" in layout and "tau" not in self.candidates[name].response.theta_names:
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
            "init": records[self.names[0]]["init"][:, :2],
            "stages": stages,
            "final": merged,
            "params": params,
            "restarts": restarts,
            "relative_loss": relative,
        }

    def _interval(self, records, weight: Tensor, fits: Tensor, choice: Tensor) -> tuple[Tensor, Tensor]:
        """(m3_low, m3_high) [b]: the union of the 95 % intervals of the candidates that fit and weigh at
        least interval_weight (and always the chosen one's)."""
        lows, highs = [], []
        for name in self.names:
            res = records[name]["final"]
            p2, s2 = records[name]["params"][:, 1].double(), res.std[:, 1].double()
            high_p2, low_p2 = p2 + 1.96 * s2, p2 - 1.96 * s2
            lows.append(self.K3 / high_p2)
            highs.append(torch.where(low_p2 > 0, self.K3 / low_p2.clamp_min(1e-300), torch.full_like(p2, math.inf)))
        low, high = torch.stack(lows, 1), torch.stack(highs, 1)
        chosen = torch.zeros_like(fits)
        chosen[torch.arange(choice.numel()), choice] = True
        member = chosen | (fits & (weight >= self.interval_weight))
        low = torch.where(member, low, torch.full_like(low, math.inf)).amin(1)
        high = torch.where(member, high, torch.full_like(high, -math.inf)).amax(1)
        return low, high
