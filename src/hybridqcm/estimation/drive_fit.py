"""aggregate=drive's joint fit: a drive segment's windows fitted together from the file (issue 32).

The information combination (estimation/drive.py) multiplies each window's Gaussian summary; for a seated
person a 5 s window's posterior is far from Gaussian (light persons scatter −90 … +120 % between windows,
with covariances that understate it), and the product is not the drive's likelihood. Here the segment's
windows are read again and fitted jointly (estimation/drive_joint.py): the drive's occupant model's
parameters shared, each window's initial state (and τ where drive.per_window keeps it) its own, the prior
counted once per segment, the noise model each window's own. Per window the problem is the one its own fit
ended with (the refinement's ``final_problem``: the last stage's window and channels, the errors-in-variables
noise model fitted at θ); two passes: the noise fitted at each window's own estimate, the joint fit from the
combination's estimate; the noise fitted again at the joint estimate and the joint fit again from there.
The segment's Gaussian is then the joint Laplace posterior of the shared parameters.

Growing prefixes of a segment (the time to decision) are segments of their own: the windows are rows of one
batch, a window in several prefixes appears once in each.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .blocks import build_inputs
from .drive import Gaussian, InformationCombiner, scaled
from .drive_joint import joint_gauss_newton
from .initial_state import project_initial_state
from .problems import ProblemEvaluation
from .solver import SolverStatus


@dataclass
class SegmentRequest:
    """One segment to fit: rows [n] of the file (its windows, time order), own [n, P] each window's estimate
    under the drive's model in the common layout (``layout``), start [P] where the shared parameters start
    (NaN: from the windows' own median), the drive's model ``family`` and whether its delay variant is used."""

    rows: np.ndarray
    own: Tensor
    start: Tensor
    family: str
    delayed: bool


@dataclass
class SegmentAnswer:
    """The joint posterior of the shared parameters: names [s], mean [s], covariance [s, s], status (label)."""

    names: tuple[str, ...]
    mean: Tensor
    covariance: Tensor
    status: str
    iterations: int


class JointDrives:
    """Joint fits of drive segments (module docstring) with the run's config, plan and refinement (a single
    model's or an occupant-model selection's). per_window: the parameters each window keeps (drive.per_window)."""

    def __init__(self, cfg, plan: Mapping, refinement, layout: Sequence[str], per_window=("tau",), passes: int = 2):
        from .runner import build_module  # the run's network front: the windows as the fits saw them

        self.cfg, self.plan = cfg, plan
        self.module = build_module(cfg, plan)
        self.refinement = refinement
        self.layout = tuple(layout)
        self.per_window = tuple(per_window)
        self.passes = int(passes)
        self.max_iterations = 30
        self.names = list(getattr(refinement, "names", None) or ["rigid"])

    def _model(self, family: str, delayed: bool):
        candidates = getattr(self.refinement, "candidates", None)
        if candidates is None:  # a single model
            return self.refinement
        if delayed and family in getattr(self.refinement, "delayed", {}):
            return self.refinement.delayed[family]
        return candidates[family]

    def _outputs(self, rows: np.ndarray) -> dict:
        """The prepared windows (module.prepare: targets, road, input_offset) of ``rows`` (repeats allowed)."""
        unique, inverse = np.unique(rows, return_inverse=True)
        spans = np.split(unique, np.flatnonzero(np.diff(unique) != 1) + 1)
        parts = [build_inputs(self.cfg, self.plan, slice(int(s[0]), int(s[-1]) + 1)) for s in spans]
        batch = {
            k: torch.cat([p[k] for p in parts]) if isinstance(parts[0][k], Tensor) else parts[0][k]
            for k in parts[0]
            if parts[0][k] is not None
        }
        with torch.no_grad():
            prepared = self.module.prepare(batch)
        pick = torch.as_tensor(inverse, dtype=torch.long)
        b = int(unique.size)
        return {
            k: (v[pick] if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == b else v) for k, v in prepared.items()
        }

    def fit(self, requests: Sequence[SegmentRequest]) -> list[SegmentAnswer]:
        """Every request's joint posterior, batched per model (all segments of one model in one evaluation)."""
        answers: list[SegmentAnswer | None] = [None] * len(requests)
        keys = sorted({(r.family, r.delayed) for r in requests})
        for family, delayed in keys:
            which = [i for i, r in enumerate(requests) if (r.family, r.delayed) == (family, delayed)]
            for i, answer in zip(which, self._fit_model(self._model(family, delayed), [requests[i] for i in which])):
                answers[i] = answer
        return answers

    def _fit_model(self, refinement, requests: Sequence[SegmentRequest]) -> list[SegmentAnswer]:
        response = refinement.response
        names = list(response.theta_names)
        n_p = response.n_params
        cols = [self.layout.index(n) for n in names[:n_p]]
        rows = np.concatenate([r.rows for r in requests])
        group = torch.cat([torch.full((r.rows.size,), g, dtype=torch.long) for g, r in enumerate(requests)])
        own = torch.cat([r.own[:, cols] for r in requests]).double()
        own = torch.where(torch.isfinite(own), own, torch.zeros_like(own))  # a delay the window did not fit: 0
        start = torch.stack([r.start[cols] for r in requests]).double()
        median = torch.stack([own[group == g].median(0).values for g in range(len(requests))])
        start = torch.where(torch.isfinite(start), start, median)
        shared = torch.tensor([j < n_p and n not in self.per_window for j, n in enumerate(names)])
        outputs = self._outputs(rows)
        offset = int(outputs.get("input_offset", 0))
        observed = refinement._channels(refinement.stages[-1], None)
        n_steps = outputs["targets"].shape[1]
        stage_steps = refinement.stages[-1].n_steps
        window = n_steps if stage_steps is None else min(int(stage_steps), n_steps)
        targets, road = outputs["targets"][:, :window].double(), outputs["road"].double()

        def with_states(p: Tensor) -> Tensor:  # x0*(p): the window's initial state by linear least squares
            theta = torch.cat([p, p.new_zeros(p.shape[0], len(names) - n_p)], 1)
            return project_initial_state(response, theta, road, targets, observed, None, offset)

        params = with_states(own)  # the noise model's first fit: at each window's own estimate
        begin = own.clone()
        begin[:, shared[:n_p]] = start[group][:, shared[:n_p]]
        begin = with_states(begin)
        chunk = refinement.stages[-1].solver.config.chunk_size
        fit = None
        for _ in range(self.passes):
            problem = refinement.final_problem(outputs, params)
            prior = _segment_prior(problem, group, len(requests))
            problem.prior_mean, problem.prior_precision = None, None
            fit = joint_gauss_newton(
                ProblemEvaluation(problem, chunk),
                begin,
                group,
                shared,
                prior,
                response.positive,
                max_iterations=self.max_iterations,
            )
            moved = fit.status != int(SolverStatus.DIVERGED)
            params = torch.where(moved[group][:, None], fit.params, begin)
            begin = params
        shared_names = tuple(n for n, s in zip(names, shared.tolist()) if s)
        return [
            SegmentAnswer(
                shared_names,
                fit.shared[g],
                fit.covariance[g],
                SolverStatus(int(fit.status[g])).label,
                int(fit.iterations[g]),
            )
            for g in range(len(requests))
        ]


def _segment_prior(problem, group: Tensor, n_groups: int) -> tuple[Tensor, Tensor] | None:
    """Each segment's prior (mean, precision) [G, n_theta], once: the windows' own (the body ranges, applied
    where a window shows a sensor noise floor); a segment takes the largest precision any of its windows has."""
    if problem.prior_mean is None:
        return None
    precision = torch.zeros(n_groups, problem.prior_precision.shape[1], dtype=torch.float64)
    index = group[:, None].expand(-1, precision.shape[1])
    precision = precision.scatter_reduce(0, index, problem.prior_precision.double(), "amax", include_self=True)
    first = torch.tensor([int((group == g).nonzero()[0]) for g in range(n_groups)])
    return problem.prior_mean.double()[first], precision


def robust_ratio(view, rows, columns: Tensor, layout: Sequence[str], names: Sequence[str]) -> Tensor:
    """[s] per shared parameter (``names``) the ratio of the windows' combined reported standard deviation to
    their combined model-based one, at least 1 (1 where the combination has no such parameter): what the
    windows' robust (jackknife) intervals say beyond the noise model, carried over to the joint fit's
    model-based covariance."""
    theta = torch.stack([view.theta[int(r)] for r in rows])[:, columns].double()
    reported = torch.stack([view.cov[int(r)] for r in rows])[:, columns][:, :, columns].double()
    model = torch.stack([view.weight_cov[int(r)] for r in rows])[:, columns][:, :, columns].double()
    window = list(range(len(rows)))
    try:
        var_r = InformationCombiner(theta, reported).combine(window).covariance.diagonal()
        var_m = InformationCombiner(theta, model).combine(window).covariance.diagonal()
    except RuntimeError:  # a singular model-based covariance: no ratio to carry
        return torch.ones(len(names), dtype=torch.float64)
    ratio = (var_r / var_m).sqrt().nan_to_num(1.0, 1.0, 1.0).clamp_min(1.0)
    combined = [layout[int(i)] for i in columns]
    return torch.tensor([float(ratio[combined.index(n)]) if n in combined else 1.0 for n in names])


def as_gaussian(answer: SegmentAnswer, base: Gaussian, scale: str, robust: Tensor | None = None) -> Gaussian:
    """The segment's Gaussian from the joint fit, with the windows' consistency (χ², dof, the focus's χ²) of the
    combination ``base``; robust [s]: per-parameter factors on the standard deviations (:func:`robust_ratio`);
    scale "birge" | "marginal": the covariance widened as the combination's is (estimation/drive.scaled; the
    focus is p2)."""
    covariance = answer.covariance
    if robust is not None:
        covariance = covariance * robust[:, None] * robust[None, :]
    g = Gaussian(answer.mean, covariance, base.chi2, base.dof, base.n, covariance, base.focus_chi2, base.focus_scatter)
    focus = answer.names.index("p2") if "p2" in answer.names else None
    return scaled(g, scale, focus)


def joint_running(joint: JointDrives, view, good, segments, running, combiner, drive, param_names):
    """The running estimates of a drive's segments from joint fits: (running [[(Gaussian, index of p2)]] per
    segment, the fit's label for drives.csv). drive.joint "final": each segment's last estimate; "progress":
    every prefix too. A joint fit that did not converge leaves the combination's estimate (label says so)."""
    requests, where = [], []
    for k, seg in enumerate(segments):
        rows = np.asarray(good)[seg]
        own = torch.stack([view.theta[int(r)] for r in rows]).double()
        variants = [joint.names[view.variant[int(r)]] for r in rows if view.variant.get(int(r), -1) >= 0]
        delayed = any(v.endswith("+delay") for v in variants)  # a window that needed its own delay: all get one
        prefixes = range(1, len(seg) + 1) if drive.joint == "progress" else [len(seg)]
        for j in prefixes:
            start = torch.full((own.shape[1],), math.nan, dtype=torch.float64)
            start[combiner.columns] = running[k][j - 1][0].mean.double()
            requests.append(SegmentRequest(rows[:j], own[:j], start, view.family, delayed))
            where.append((k, j - 1))
    answers = joint.fit(requests)
    running = [list(r) for r in running]
    statuses = []
    for (k, j), answer in zip(where, answers):
        statuses.append(answer.status)
        if answer.status == "converged" and "p2" in answer.names:
            rows = np.asarray(good)[segments[k][: j + 1]]
            robust = (
                robust_ratio(view, rows, combiner.columns, joint.layout, answer.names)
                if drive.scale != "none"
                else None
            )
            gaussian = as_gaussian(answer, running[k][j][0], drive.scale, robust)
            running[k][j] = (gaussian, answer.names.index("p2"))
    last = [answers[i].status for i, (k, j) in enumerate(where) if j == len(segments[k]) - 1]
    label = "joint" if all(s == "converged" for s in last) else "joint:" + ";".join(sorted(set(last)))
    return running, label


__all__ = ["JointDrives", "SegmentRequest", "SegmentAnswer", "as_gaussian", "joint_running"]
