"""One drive's windows under one occupant model (issue 32): the model chosen by the windows' summed evidence
and each window's estimate under it, for reports/drive.py's combination.

An occupant-model selection (estimation/occupant.py) fits every candidate to every window; the block's columns
carry each candidate's estimate, covariance, status, fit flag and evidence (estimation/drive_plan.py,
drive_cand_*). :func:`drive_model` picks the drive's model (the rule: reports/drive.py's docstring),
:class:`DriveView` holds each window's estimate under it and says which windows can be combined.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from hybridqcm.estimation.drive import InformationCombiner, usable_windows
from hybridqcm.estimation.drive_plan import DrivePlan
from hybridqcm.estimation.drive_prior import PriorOnceCombiner
from hybridqcm.estimation.solver import STATUS_LABELS
from hybridqcm.physics.occupant import MODE_PARAMS, body_prior


def present(theta: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """[W, P] bool: the parameters a window estimated (finite, variance > 0): not the ones its occupant model
    lacks (NaN in a model selection's common layout) nor the known ones (variance 0)."""
    var = cov.diagonal(dim1=1, dim2=2)
    return torch.isfinite(theta) & torch.isfinite(var) & (var > 0)


def usable_estimates(theta: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """[W] bool: p2 estimated and the estimated parameters' covariance positive definite."""
    have = present(theta, cov)
    mask = have.unsqueeze(2) & have.unsqueeze(1)
    eye = torch.eye(theta.shape[1], dtype=cov.dtype).expand_as(cov)
    patched = torch.where(mask, cov, torch.where(eye.bool(), eye, torch.zeros_like(cov)))
    return have[:, 1] & usable_windows(torch.where(have, theta, torch.zeros_like(theta)), patched)


def _families(names: Sequence[str]) -> list[str]:
    """The occupant models a drive can be pooled under: the candidates without their delay variants (a delay
    is each window's own, drive.per_window), in the candidates' order."""
    return list(dict.fromkeys(n.split("+")[0] for n in names))


def _log_prior(log_prior: Mapping[str, float] | None, family: str) -> float:
    return float((log_prior or {}).get(family, 0.0))


def drive_model(
    logz: torch.Tensor,
    fits: torch.Tensor,
    chosen: torch.Tensor,
    names: Sequence[str],
    log_prior=None,
    settled: torch.Tensor | None = None,
):
    """The occupant model of one drive, by its windows' summed evidence (module docstring).

    logz [W, C] (−inf: not fitted), fits [W, C] (neither misfit nor diverged), chosen [W] (each window's own
    choice, index into names) of the drive's windows, settled [W, C] (the fit ended with a status the drive
    combines; default: all): only fits that fit and settled weigh (a Laplace evidence away from an optimum is
    no evidence: one max_iterations fit 110 nats above the rest decided a drive). Returns (family, variant [W]
    — per window the index into names of that family's variant with the highest evidence among those that
    fit, −1 if none does —, the evidence margin over the runner-up [nats], the windows' own choices as a
    label)."""
    families = _families(names)
    member = torch.tensor([[n.split("+")[0] == f for n in names] for f in families])  # [F, C]
    weighs = fits & (torch.ones_like(fits) if settled is None else settled)
    evidence = torch.where(weighs, logz, torch.full_like(logz, -math.inf))
    masked = torch.where(member[None], evidence[:, None, :], torch.full_like(logz[:, None, :], -math.inf))
    best = masked.max(2).values  # [W, F]: each family's evidence in each window (its better variant)
    # a model that fits and settles in fewer than half the windows cannot carry the drive (a person's
    # two-mode fit that ran out of iterations in 10 of 12 windows won one drive by 0.2 nats on the other 2)
    carries = torch.isfinite(best).sum(0) * 2 >= best.shape[0]
    carries = carries if bool(carries.any()) else torch.ones_like(carries)
    common = torch.isfinite(best[:, carries]).all(1)
    if bool(common.any()) and int(carries.sum()) > 1:
        # one model prior per drive, not one per window: the occupant is the same in every window
        prior = torch.tensor([_log_prior(log_prior, f) for f in families], dtype=torch.float64)
        score = torch.where(carries, (best[common] - prior).nan_to_num(0.0, 0.0, 0.0).sum(0) + prior, -math.inf)
        order = torch.argsort(score, descending=True)
        family, margin = families[int(order[0])], float(score[order[0]] - score[order[1]])
    elif int(carries.sum()) == 1:  # the only model that carries (inf), or the only model there is (no race)
        family, margin = families[int(carries.nonzero()[0])], math.inf if len(families) > 1 else math.nan
    else:  # nothing to compare on: the family most windows chose
        votes = torch.bincount(
            torch.tensor([families.index(names[int(c)].split("+")[0]) for c in chosen]), minlength=len(families)
        )
        family, margin = families[int(votes.argmax())], math.nan
    f = families.index(family)
    eligible = member[f][None] & fits & torch.isfinite(logz)
    preferred = eligible & weighs  # a settled variant before one that ran out of iterations
    eligible = torch.where(preferred.any(1, keepdim=True), preferred, eligible)
    scored = torch.where(eligible, logz, torch.full_like(logz, -math.inf))
    variant = torch.where(eligible.any(1), scored.argmax(1), torch.full((logz.shape[0],), -1, dtype=torch.long))
    return family, variant, margin, _label(chosen, names)


def _label(models: torch.Tensor, names: Sequence[str]) -> str:
    counts = {names[int(k)]: int(c) for k, c in zip(*torch.unique(models, return_counts=True))}
    return ";".join(f"{k}:{v}" for k, v in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


class DriveView:
    """One drive's windows under its occupant model: per row (of the whole file) the chosen variant's θ [P],
    covariances [P, P], status and whether it can be combined."""

    def __init__(self, columns: Mapping, rows: np.ndarray, drive: DrivePlan, names, log_prior, kept_out):
        """kept_out [M] bool: windows kept from the fit (no_signal, clipped): not weighed."""
        fitted = rows[~kept_out[rows].numpy()]
        self.family, variant, self.margin, self.own = "", torch.zeros(0, dtype=torch.long), math.nan, ""
        self.variant = {}
        if fitted.size:
            allowed = torch.tensor(sorted(k for k, v in STATUS_LABELS.items() if v in drive.statuses))
            self.family, variant, self.margin, self.own = drive_model(
                columns["drive_cand_logz"][fitted],
                columns["drive_cand_fits"][fitted],
                columns["drive_model"][fitted],
                names,
                log_prior,
                torch.isin(columns["drive_cand_status"][fitted], allowed),
            )
            self.variant = {int(r): int(v) for r, v in zip(fitted, variant)}
        n_p = columns["drive_cand_theta"].shape[2]
        self.theta = {}
        self.cov = {}
        self.weight_cov = {}
        self.status_ok = {}
        self.status = {}
        self.prior = {}  # per row: the window's prior (mean [P], precision [P]) where the shards carry it
        allowed = {k for k, v in STATUS_LABELS.items() if v in drive.statuses}
        members = [j for j, n in enumerate(names) if n.split("+")[0] == self.family]
        for r in rows:
            v = self.variant.get(int(r), -1)
            if v < 0:  # no variant of the drive's model fitted: the status of its best one says why
                if int(r) in self.variant:
                    best = max(members, key=lambda j: float(columns["drive_cand_logz"][r, j]))
                    self.status[int(r)] = int(columns["drive_cand_status"][r, best])
                continue
            self.theta[int(r)] = columns["drive_cand_theta"][r, v]
            self.cov[int(r)] = columns["drive_cand_cov"][r, v]
            self.weight_cov[int(r)] = columns["drive_cand_model_cov"][r, v]
            if "drive_cand_prior_precision" in columns:
                self.prior[int(r)] = (
                    columns["drive_cand_prior_mean"][r, v],
                    columns["drive_cand_prior_precision"][r, v],
                )
            self.status_ok[int(r)] = int(columns["drive_cand_status"][r, v]) in allowed
            self.status[int(r)] = int(columns["drive_cand_status"][r, v])
        self.n_params = n_p
        self.fit = "combined"  # how the drive's segments were estimated (reports/drive.py sets it)

    def usable(self, rows: np.ndarray, weights: str) -> np.ndarray:
        """[len(rows)] bool: the drive's model fitted the window (not misfit, not diverged), its status is one
        drive.statuses combines, p2 estimated and the estimated parameters' covariance positive definite."""
        ok = np.zeros(rows.size, dtype=bool)
        have = [i for i, r in enumerate(rows) if int(r) in self.theta and self.status_ok[int(r)]]
        if not have:
            return ok
        theta = torch.stack([self.theta[int(rows[i])] for i in have])
        good = usable_estimates(theta, torch.stack([self.cov[int(rows[i])] for i in have]))
        if weights == "model":
            good &= usable_estimates(theta, torch.stack([self.weight_cov[int(rows[i])] for i in have]))
        ok[np.asarray(have)[good.numpy()]] = True
        return ok

    def gaussians(self, rows: np.ndarray, drive: DrivePlan, param_names: Sequence[str]):
        """(combiner, index of p2 within the combined parameters) for the usable windows ``rows``: the parameters
        every window estimated under the drive's model, less those each window keeps (drive.per_window)."""
        theta = torch.stack([self.theta[int(r)] for r in rows])
        cov = torch.stack([self.cov[int(r)] for r in rows])
        shared = torch.tensor([n not in drive.per_window for n in param_names[: theta.shape[1]]], dtype=torch.bool)
        keep = (present(theta, cov).all(0) & shared).nonzero().squeeze(1)
        index = int((keep == 1).nonzero()[0])  # p2 within the shared parameters
        weight = None
        if drive.weights == "model":
            weight = torch.stack([self.weight_cov[int(r)] for r in rows])[:, keep][:, :, keep]
        log = (theta[:, keep] > 0).all(0) if drive.space == "log" else None  # positive parameters: in logarithms
        if drive.prior == "once":
            mean, precision = self._priors(rows, param_names, theta.shape[1], keep)
            model = torch.stack([self.weight_cov[int(r)] for r in rows])[:, keep][:, :, keep]
            combiner = PriorOnceCombiner(
                theta[:, keep],
                cov[:, keep][:, :, keep],
                mean[:, keep],
                precision[:, keep],
                model if drive.prior_from == "model" else None,
                drive.scale,
                index,
                log,
            )
        else:
            combiner = InformationCombiner(theta[:, keep], cov[:, keep][:, :, keep], weight, drive.scale, index, log)
        combiner.columns = keep  # the combined parameters' places in the common layout (a joint fit's start)
        return combiner, index

    def _priors(self, rows: np.ndarray, param_names: Sequence[str], n_p: int, keep: torch.Tensor):
        """(mean [W, P], precision [W, P]) of the windows' priors: the shards' drive_cand_prior_* where they carry
        them for every window on the combined parameters ``keep``; else (shards written before, a single model's
        fit) assumed: the body prior (physics/occupant.BODY_PRIOR) on every body parameter of every window, as the
        refinement applies it on a recording with a sensor noise floor."""
        known = all(int(r) in self.prior and bool(torch.isfinite(self.prior[int(r)][1][keep]).all()) for r in rows)
        if known:  # NaN elsewhere: parameters the model lacks
            return tuple(torch.stack([self.prior[int(r)][k] for r in rows]).double().nan_to_num(0.0) for k in (0, 1))
        mean, std = body_prior(2)
        body = [f"{x}{i}" for i in (1, 2) for x in MODE_PARAMS]
        m = torch.zeros(n_p, dtype=torch.float64)
        lam = torch.zeros(n_p, dtype=torch.float64)
        for j, name in enumerate(param_names[:n_p]):
            if name in body:
                m[j], lam[j] = mean[body.index(name)], std[body.index(name)] ** -2
        return m.expand(len(rows), n_p), lam.expand(len(rows), n_p)


__all__ = ["DriveView", "drive_model", "present", "usable_estimates"]
