"""qcm-estimate's occupant settings: which occupant models to fit and the channel delay (SPEC § 10).

    occupant.models: [rigid, body1, body2]   candidates; several: per recording the highest evidence
    occupant.interval_weight: 0.0067         candidates this close (evidence weight; e^-5, Kass and Raftery's
                                             'very strong') widen m3's interval
    occupant.body_prior: true                the literature's ranges as a weak prior on body modes
    occupant.profile: true                   the winner's m3 interval by profile likelihood (else Laplace)
    occupant.boundary_hold: false            hold a body mode the data do not resolve at r = 0 (its nested model)
    occupant.rigid_prior: 0.05               prior probability of a rigid occupant (ballast); the body
                                             models share the rest
    occupant.workers: auto                   threads for a batch's independent solves (auto: the cores this
                                             process may use; the same numbers on any count)
    delay: auto | estimate | <ms> | null     a3 behind its driving channel: the winner refitted with the
                                             delay estimated (evidence decides), estimated in every
                                             candidate, known, or none
    delay_max_ms: 20                         the largest delay searched (either sign)

Occupant models exist for the road-free seat (``base_excitation: seat``) and sprung models and for the
road-driven quarter car with the exact model (exp 8, 10: ``occupant_linear_model``); the channel delay
for the seat model only. Asking for more is refused.
"""

from __future__ import annotations

import math

import torch

from hybridqcm.errors import ConfigError
from hybridqcm.physics.occupant import N_MODES, OCCUPANT_MODELS, body_prior, body_start

from .occupant_interval import VERY_STRONG


def occupant_plan(cfg, base: str | None, model: str = "exact") -> dict | None:
    """The validated occupant and delay settings, or None when the plain rigid model is asked for.
    ``base``: the road-free model (seat, sprung) or None (road-driven, fitted with ``model``)."""
    occupant = cfg.get("occupant") or {}
    models = occupant.get("models", ["rigid"])
    if isinstance(models, str) or models is None:
        models = [models]
    models = [str(m) for m in models]
    if not models:
        raise ConfigError(f"occupant.models is empty: list one or more of {list(OCCUPANT_MODELS)}")
    bad = [m for m in models if m not in OCCUPANT_MODELS]
    if bad:
        raise ConfigError(f"occupant.models={models}: {bad} unknown; choose from {list(OCCUPANT_MODELS)}")
    if len(set(models)) != len(models):
        raise ConfigError(f"occupant.models={models}: a model is listed twice")
    delay = cfg.get("delay", None)
    max_ms = cfg.get("delay_max_ms", 20)
    if isinstance(max_ms, bool) or not isinstance(max_ms, (int, float)) or not math.isfinite(max_ms) or max_ms < 0:
        raise ConfigError(f"delay_max_ms={max_ms!r}: give the largest channel delay searched, a number >= 0 [ms]")
    if delay is not None and str(delay) not in ("estimate", "auto"):
        if isinstance(delay, bool) or not isinstance(delay, (int, float)) or not math.isfinite(delay):
            raise ConfigError(f"delay={delay!r}: give auto, estimate, null (none) or the known delay in ms (a number)")
        if abs(delay) > max_ms:
            raise ConfigError(f"delay={delay} ms lies beyond delay_max_ms={max_ms}")
    weight = occupant.get("interval_weight", VERY_STRONG)
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not 0 < weight <= 1:
        raise ConfigError(f"occupant.interval_weight={weight!r}: give a number in (0, 1]")
    plain = models == ["rigid"] and (delay is None or (str(delay) not in ("estimate", "auto") and float(delay) == 0.0))
    if plain:
        return None
    if base != "seat" and not (delay is None or (str(delay) not in ("estimate", "auto") and float(delay) == 0.0)):
        raise ConfigError(
            f"delay={delay!r}: the channel delay is available for the road-free seat model (base_excitation: seat, "
            f"e.g. experiment=occupant_roadfree); this run fits {base or 'the road-driven quarter car'} on one clock "
            f"(delay=null)"
        )
    if base is None and model != "exact":
        raise ConfigError(
            f"occupant.models={models}: body models need the exact continuous-time model (dynamics=exact); "
            f"this run fits the source's Euler recursion (dynamics={cfg.get('dynamics', 'auto')}, a file from "
            f"our Euler generator) with a rigid occupant"
        )
    return {
        "models": models,
        "delay": None
        if delay is None
        else (str(delay) if str(delay) in ("estimate", "auto") else float(delay) / 1000.0),
        "max_delay": float(max_ms) / 1000.0,
        "interval_weight": float(weight),
        "body_prior": bool(occupant.get("body_prior", True)),
        "profile": _flag(occupant, "profile", True),
        "boundary_hold": _flag(occupant, "boundary_hold", False),
        "rigid_prior": _probability(occupant, "rigid_prior", 0.05),
        "workers": _workers(occupant),
        "delay_prior": _delay_prior(cfg),
    }


def _flag(group, key: str, default: bool) -> bool:
    value = group.get(key, default)
    if not isinstance(value, bool):
        raise ConfigError(f"occupant.{key}={value!r}: give true or false")
    return value


def _workers(group) -> int | None:
    """occupant.workers: None for auto (the available cores, judged where the fits run), else a count >= 1."""
    value = group.get("workers", "auto")
    if value == "auto":
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"occupant.workers={value!r}: give auto or a number of threads >= 1")
    return value


def _probability(group, key: str, default: float) -> float:
    value = group.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
        raise ConfigError(f"occupant.{key}={value!r}: give a probability in (0, 1)")
    return float(value)


def _delay_prior(cfg) -> float:
    """The delay prior's standard deviation [s] (inf: none) from delay_prior_ms."""
    value = cfg.get("delay_prior_ms", None)
    if value is None:
        return math.inf
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise ConfigError(f"delay_prior_ms={value!r}: give a standard deviation > 0 [ms] or null (none)")
    return float(value) / 1000.0


def delay_margin(cfg, h: float) -> int:
    """Input samples the delay needs beyond each end of the window (0 without a delay)."""
    delay = cfg.get("delay", None)
    if delay is None or (str(delay) not in ("estimate", "auto") and float(delay) == 0.0):
        return 0
    return math.ceil(float(cfg.get("delay_max_ms", 20)) / 1000.0 / h - 1e-9) + 2


def occupant_linear_model(base: str | None, n_modes: int, scaled_road: bool = False):
    """The LinearModel of an occupant with ``n_modes`` body modes (0: rigid) for the road-free ``base``
    (seat, sprung) or, with None, the road-driven quarter car (``scaled_road``: its input is p_u u).
    Its parameters are the rigid model's, then the body's (r_i, k_i, c_i) per mode."""
    from hybridqcm.physics import linear_models as lm

    if base == "seat":
        return lm.SeatBaseExcitation() if n_modes == 0 else lm.SeatOccupantBaseExcitation(n_modes)
    if base == "sprung":
        return lm.SprungBaseExcitation() if n_modes == 0 else lm.SprungOccupantBaseExcitation(n_modes)
    if base is None:
        return lm.QuarterCarRoad(scaled_road) if n_modes == 0 else lm.QuarterCarOccupantRoad(n_modes, scaled_road)
    raise ValueError(f"occupant models: no model for base_excitation={base!r}; choose seat, sprung or null")


def _vehicle_settings(cfg, plan, names) -> tuple:
    """(mean [n], std [n]) of the run's vehicle prior over the parameter ``names`` (std inf where it has none)
    and the restarts' centre [n] (None unless restarts go around the reference vehicle), as the rigid run
    has them (estimation/runner.build_refinement)."""
    from hybridqcm.physics.parameters import PARAM_NAMES, PhysicalConstants

    p_ref = PhysicalConstants(**{k: float(v) for k, v in cfg.vehicle.items()}).to_params()
    reference = torch.stack([p_ref[PARAM_NAMES.index(n)] for n in names])
    std = torch.full_like(reference, math.inf)
    if plan["vehicle_prior"] is not None:
        listed = torch.tensor([n in plan["vehicle_prior"]["params"] for n in names])
        std = torch.where(listed, plan["vehicle_prior"]["rel_std"] * reference, std)
    return reference, std, (reference if plan["restarts_around"] == "reference" else None)


# The 5 % level of the likelihood-ratio test of a body mode's mass ratio on its boundary r = 0 (½χ²₀ + ½χ²₁:
# 2ΔL = 2.71), in nats of the noise-whitened loss (solver.SolverConfig.boundary_test).
BOUNDARY_NATS = 1.35
# A candidate's path is stopped as `diverged` where it is outside the domain and its full Gauss-Newton step, no longer
# than one standard deviation (decrement δᵀJᵀR ≤ 1 nat), lands outside too (solver.SolverConfig.outside_tol).
OUTSIDE_NATS = 1.0


def _interpolating(refinement, boundary_hold: bool = False):
    """The refinement with its stages' line search set to "interpolate" (solver.SolverConfig.backtrack): a body
    candidate's GN steps overshoot by 10-1000×, and halving them took 9-12 loss evaluations an iteration; the
    same α in fewer (docs/measurements/persons.md). The rigid one-clock fit outside a selection keeps halving.
    A path that converges outside the domain (most often a mass ratio r_i < 0 on a rigid occupant, where the fit ends
    `diverged`) is stopped there (SolverConfig.outside_tol = OUTSIDE_NATS).
    With ``boundary_hold`` the boundary test (SolverConfig.boundary_test, BOUNDARY_NATS): a body mode whose full
    step heads to r = 0 and whose removal costs less than the test's level is held at r = 0, its nested model
    (on a rigid occupant the mode is not identifiable and its fit crawled to r -> 0 for 30 iterations a pass,
    or across it: `diverged`); the selection takes it out of the comparison (estimation/occupant.py). Off by
    default: at 10 % noise it held real persons' modes mid-fit (the test runs at the iterate, not at the
    optimum), and rigid then won +30-70 % off (docs/measurements/persons.md)."""
    for stage in refinement.stages:
        stage.solver.config.backtrack = "interpolate"
        stage.solver.config.outside_tol = OUTSIDE_NATS
        if boundary_hold:
            stage.solver.config.boundary_test = BOUNDARY_NATS
    return refinement


def _surplus_kept(refinement, modes: int):
    """``refinement`` with a body model's jackknife intervals left uncorrected (intervals.jackknife_test applies to
    the rigid model only). A person is never exactly a body model of ours, and under sensor noise that model
    error does not show in the jackknife's test against the working model: with the Efron-Stein excess divided
    out, persons of another simulator at 5 % noise were answered `converged`, > 10 % off and outside their
    interval 9 times in 240 instead of 6 (docs/measurements/persons.md). A rigid mass is the exact model of
    ballast and of a rigid occupant, where the uncorrected surplus made a 95 % interval cover 99 %."""
    if modes:
        for stage in refinement.stages:
            stage.solver.config.jackknife_test = None
    return refinement


def build_selection(cfg, plan, occupant: dict, make_refinement):
    """The candidates' refinements and the selection over them (estimation/occupant.py).

    ``make_refinement(response, known [n_params] bool, param_prior | None, restarts: bool[, centre])`` builds
    one candidate's GaussNewtonRefinement with the run's stages and noise model, with or without its
    restarts (around ``centre`` where given). The sprung and road-driven models keep the rigid run's
    vehicle prior and restart centre on their p1..pN; the body's prior and start come after them."""
    from hybridqcm.estimation.delay import DelayedResponse
    from hybridqcm.estimation.occupant import OccupantSelection
    from hybridqcm.estimation.response import ExactResponse

    base = plan["base_excitation"]
    delay = occupant["delay"]

    def candidate(name: str, tau_setting):
        modes = N_MODES[name]
        linear = occupant_linear_model(base, modes, bool(cfg.pu_known))
        n_vehicle = linear.n_params - 3 * modes  # the rigid model's parameters come first
        response = ExactResponse(linear, plan["h"], str(cfg.hold), int(cfg.substeps), plan["initial_state"])
        start = body_start(modes)
        mean, std = body_prior(modes)
        known = torch.zeros(linear.n_params, dtype=torch.bool)
        known[plan["known"]] = True
        if tau_setting is not None:
            response = DelayedResponse(response, occupant["max_delay"])
            tau = 0.0 if tau_setting == "estimate" else tau_setting
            start = torch.cat([start, torch.tensor([tau], dtype=torch.float64)])
            mean = torch.cat([mean, torch.zeros(1, dtype=torch.float64)])
            std = torch.cat([std, torch.full((1,), occupant["delay_prior"], dtype=torch.float64)])
            known = torch.cat([known, torch.tensor([tau_setting != "estimate"])])
        if not occupant["body_prior"]:
            std[: 3 * modes] = math.inf
        centre = None
        if base == "seat":
            vehicle_mean = torch.ones(n_vehicle, dtype=torch.float64)
            vehicle_std = torch.full((n_vehicle,), math.inf, dtype=torch.float64)
        else:  # the vehicle's prior and restart centre as in the rigid run
            vehicle_mean, vehicle_std, centre = _vehicle_settings(cfg, plan, linear.param_names[:n_vehicle])
            centre = None if centre is None else torch.cat([centre, start])
        full_std = torch.cat([vehicle_std, std])
        prior = (torch.cat([vehicle_mean, mean]), full_std) if bool(torch.isfinite(full_std).any()) else None
        pair = tuple(
            _surplus_kept(
                _interpolating(make_refinement(response, known, prior, restarts, centre), occupant["boundary_hold"]),
                modes,
            )
            for restarts in (False, True)
        )
        return pair, start

    # auto: every model on one clock, then the winner once more with the delay estimated (evidence decides);
    # each candidate in one attempt, the chosen one restarted where it does not fit (rescue)
    candidates, starts, delayed, rescue = {}, {}, {}, {}
    for name in occupant["models"]:
        (candidates[name], rescue[name]), starts[name] = candidate(name, None if delay == "auto" else delay)
        if delay == "auto":
            (delayed[name], rescue[f"{name}+delay"]), _ = candidate(name, "estimate")
    rigid = occupant["rigid_prior"]
    n_body = sum(1 for n in candidates if n != "rigid")
    model_prior = {n: (rigid if n == "rigid" else (1.0 - rigid) / n_body) if n_body else 1.0 for n in candidates}
    return OccupantSelection(
        candidates,
        starts,
        float(cfg.K3),
        occupant["interval_weight"],
        delayed=delayed,
        profile=occupant["profile"],
        model_prior=model_prior,
        rescue=rescue,
        workers=occupant["workers"],
    )
