"""What the solver fits: a response model θ -> y with its Jacobian, for a batch of samples.

The solver (:mod:`hybridqcm.estimation.solver`) only ever asks a model for

    outputs(theta [b, n_theta], inputs) -> y [b, time, n_out]
    sensitivities(theta, inputs)        -> [b, time, n_out, 1 + n_theta]   (prediction | ∂y/∂θ)

so the Euler recursion of the source study and the exact discretisation of a continuous-time
linear model are interchangeable behind it. θ holds the physical parameters first (they must
stay > 0: ``positive``) and, for the exact model with an unknown initial state, the state x0 at
the first sample after them (any sign). ``inputs`` is whatever the model is driven by, indexed
by sample along its first axis and by time along its second: the road [b, time] for the Euler
model, the input signals [b, time, n_in] for a linear model.

A solver that evaluates one window many times first calls ``prepare(inputs, start, n_steps)`` and
passes what it returns (indexable by sample like the inputs) in their place: the exact model holds
the input between samples there once (the spline hold's up-sampling is a third of an output
evaluation); the Euler model returns the inputs unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.linear_models import LinearModel, QuarterCarRoad, SeatBaseExcitation, SprungBaseExcitation
from hybridqcm.physics.parameters import CHANNELS, PARAM_NAMES

from .exact import exact_outputs, exact_sensitivities, fallback_sensitivities
from .hold import HOLDS, held_input
from .sensitivity import euler_accelerations, euler_sensitivities

INITIAL_STATES = ("unknown", "rest")


class ResponseModel:
    """Base: names of θ and of the outputs, which θ entries must stay positive, and the two calls."""

    theta_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    n_params: int = 0  # leading entries of θ that are physical parameters (> 0)

    @property
    def n_theta(self) -> int:
        return len(self.theta_names)

    # Whether each sample's outputs (a line search's trial losses) / sensitivities (a Jacobian pass) are the same
    # bits in any batch it is evaluated in, where the compiled loops run, so that a solve may cut those passes
    # anywhere (ProblemEvaluation._pieces). Not by default: a model may choose its method or its layout by the
    # batch (the exact model's fallback stacked up to 32 samples a call; its modal basis as wide as the batch's
    # largest number of propagated modes).
    outputs_apart: bool = False
    sensitivities_apart: bool = False

    @property
    def positive(self) -> Tensor:
        """[n_theta] bool: entries that must stay > 0 (a final estimate outside is `diverged`)."""
        mask = torch.zeros(self.n_theta, dtype=torch.bool)
        mask[: self.n_params] = True
        return mask

    @property
    def boundary(self) -> Tensor:
        """[n_theta] bool: parameters whose zero is a nested model (the linear model's ``nested_at_zero``: a
        body mode's mass ratio r_i, at 0 the model without that mode); the solver may hold them there
        (SolverConfig.boundary_test)."""
        mask = torch.zeros(self.n_theta, dtype=torch.bool)
        for name in getattr(getattr(self, "model", None), "nested_at_zero", {}):
            mask[self.theta_names.index(name)] = True
        return mask

    def boundary_removes(self, column: int) -> list[int]:
        """θ columns that the boundary parameter at θ column ``column`` removes at 0: the output depends on none of
        them there (a body mode's k_i, c_i and, where θ holds the initial state, its dy_i, y_i)."""
        names = getattr(getattr(self, "model", None), "nested_at_zero", {}).get(self.theta_names[column], ())
        theta = [n if n in self.theta_names else f"x0_{n}" for n in names]
        return [self.theta_names.index(n) for n in theta if n in self.theta_names]

    def prepare(self, inputs: Tensor, start: int = 0, n_steps: int | None = None) -> Tensor | PreparedInputs:
        """What to pass as ``inputs`` for repeated evaluations of one window (default: the inputs)."""
        return inputs

    def outputs(self, theta: Tensor, inputs: Tensor, start: int = 0, n_steps: int | None = None) -> Tensor:
        """y [b, n_steps, n_out] for the input samples start .. start + n_steps - 1 (default: to the end)."""
        raise NotImplementedError

    def sensitivities(self, theta: Tensor, inputs: Tensor, start: int = 0, n_steps: int | None = None) -> Tensor:
        """[b, n_steps, n_out, 1 + n_theta] for the same samples."""
        raise NotImplementedError

    def sensitivities_deferred(
        self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None
    ) -> tuple[Tensor, Tensor]:
        """(sensitivities, rows [r]): the rows of the samples left to :meth:`fallback_sensitivities` (their
        result rows not valid), so that a pass over many chunks evaluates them in one call. Default: none."""
        out = self.sensitivities(theta, inputs, start, n_steps)
        return out, torch.zeros(0, dtype=torch.long, device=out.device)

    def fallback_sensitivities(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None) -> Tensor:
        """The sensitivities of the samples that :meth:`sensitivities_deferred` left."""
        return self.sensitivities(theta, inputs, start, n_steps)

    def residual_sensitivities(
        self, theta: Tensor, inputs, start: int, n_steps: int, targets: Tensor
    ) -> tuple[Tensor, Tensor]:
        """:meth:`sensitivities_deferred` with column 0 the residual y - ``targets`` [b, n_steps, n_out]
        (what the solver's normal equations need; a model may subtract where it is cheapest)."""
        out, redo = self.sensitivities_deferred(theta, inputs, start, n_steps)
        out[..., 0] -= targets
        return out, redo


@dataclass(frozen=True)
class PreparedInputs:
    """Inputs [b, T_in, m] with the held input of one window (exact.held_input), stored batch first as
    [b, m, M (T - 1) + M + 1] so that selecting a chunk of samples copies contiguous rows (8x faster
    than gathering along the innermost batch axis); ``held`` is the layer's [W, m, b] view of it.
    Indexing selects samples, like indexing the inputs; a contiguous range is a view."""

    samples: Tensor
    held_by_sample: Tensor
    start: int
    n_steps: int

    @property
    def held(self) -> Tensor:
        return self.held_by_sample.permute(2, 1, 0)

    def __getitem__(self, index) -> PreparedInputs:
        if isinstance(index, Tensor) and index.dtype != torch.bool and index.numel() > 0:
            first = int(index[0])
            if bool((index == torch.arange(first, first + index.numel(), device=index.device)).all()):
                index = slice(first, first + index.numel())
        return PreparedInputs(self.samples[index], self.held_by_sample[index], self.start, self.n_steps)

    @property
    def shape(self) -> torch.Size:
        return self.samples.shape


STATE_NAMES = ("v3", "v2", "v1", "q3", "q2", "q1")


class EulerResponse(ResponseModel):
    """The source's semi-explicit Euler recursion (SPEC §4): θ = p1..p10 (from rest) or (p, x0) with
    ``initial_state="unknown"``; inputs = road [b, time] (u in metres, or p_u u when ``scaled_road``),
    outputs (a3, a2, a1)."""

    output_names = CHANNELS
    n_params = 10

    outputs_apart = sensitivities_apart = True  # the recursion runs each sample on its own

    def __init__(self, h: float = 0.01, scaled_road: bool = False, initial_state: str = "rest") -> None:
        if initial_state not in INITIAL_STATES:
            raise ValueError(f"initial_state={initial_state!r}: choose one of {list(INITIAL_STATES)}")
        self.h, self.scaled_road = float(h), bool(scaled_road)
        self.with_x0 = initial_state == "unknown"
        self.theta_names = PARAM_NAMES + (tuple(f"x0_{s}" for s in STATE_NAMES) if self.with_x0 else ())

    # The recursion holds the input over each step: samples outside the window play no part.
    def outputs(self, theta: Tensor, inputs: Tensor, start: int = 0, n_steps: int | None = None) -> Tensor:
        x0 = theta[:, 10:] if self.with_x0 else None
        road = inputs[:, start : start + n_steps] if n_steps is not None else inputs[:, start:]
        return euler_accelerations(theta[:, :10].contiguous(), road.contiguous(), self.h, self.scaled_road, x0=x0)

    def sensitivities(self, theta: Tensor, inputs: Tensor, start: int = 0, n_steps: int | None = None) -> Tensor:
        x0 = theta[:, 10:] if self.with_x0 else None
        road = inputs[:, start : start + n_steps] if n_steps is not None else inputs[:, start:]
        return euler_sensitivities(
            theta[:, :10].contiguous(), road.contiguous(), self.h, self.scaled_road, x0=x0, with_x0=self.with_x0
        )

    def residual_sensitivities(self, theta: Tensor, inputs: Tensor, start: int, n_steps: int, targets: Tensor):
        if type(self).sensitivities is not EulerResponse.sensitivities:  # a subclass's own sensitivities
            return super().residual_sensitivities(theta, inputs, start, n_steps, targets)
        x0 = theta[:, 10:] if self.with_x0 else None
        road = inputs[:, start : start + n_steps]
        out = euler_sensitivities(
            theta[:, :10].contiguous(),
            road.contiguous(),
            self.h,
            self.scaled_road,
            x0=x0,
            with_x0=self.with_x0,
            targets=targets,
        )
        return out, torch.zeros(0, dtype=torch.long, device=out.device)


class ExactResponse(ResponseModel):
    """Exact discretisation of a continuous-time linear model (SPEC §9), x0 unknown or at rest.

    θ = (p_1..p_P, x0_1..x0_n) with ``initial_state="unknown"``, θ = p with ``"rest"``;
    inputs [b, time, n_in] sampled every h; the input between samples follows ``hold``.
    """

    def __init__(
        self,
        model: LinearModel,
        h: float = 0.01,
        hold: str = "spline",
        substeps: int = 4,
        initial_state: str = "unknown",
        spline_degree: int = 5,
    ) -> None:
        if initial_state not in INITIAL_STATES:
            raise ValueError(f"initial_state={initial_state!r}: choose one of {list(INITIAL_STATES)}")
        if hold not in HOLDS:
            raise ValueError(f"hold={hold!r}: choose one of {list(HOLDS)}")
        if not h > 0:
            raise ValueError(f"h must be > 0, got {h}")
        self.model, self.h, self.hold, self.substeps = model, float(h), hold, int(substeps)
        self.spline_degree = int(spline_degree)  # of the spline hold (estimation/exact.py)
        self.with_x0 = initial_state == "unknown"
        self.n_params = len(model.param_names)
        self.theta_names = tuple(model.param_names) + (
            tuple(f"x0_{s}" for s in model.state_names) if self.with_x0 else ()
        )
        self.output_names = tuple(model.output_names)

    @property
    def positive(self) -> Tensor:
        """As ResponseModel's, less the parameters the model says may take either sign (its
        ``signed_params``, e.g. a seat's coordinates on a vehicle)."""
        mask = super().positive
        for name in getattr(self.model, "signed_params", ()):
            mask[self.theta_names.index(name)] = False
        return mask

    def _split(self, theta: Tensor) -> tuple[Tensor, Tensor | None]:
        return theta[:, : self.n_params], (theta[:, self.n_params :] if self.with_x0 else None)

    def prepare(self, inputs: Tensor | PreparedInputs, start: int = 0, n_steps: int | None = None) -> PreparedInputs:
        if isinstance(inputs, PreparedInputs):  # prepared once by the caller for several solves
            self._unpack(inputs, start, n_steps)  # the window must be the one it was prepared for
            return inputs
        samples = _as_3d(inputs).to(torch.float64)
        n_steps = samples.shape[1] - start if n_steps is None else int(n_steps)
        held = held_input(samples, self.hold, self.substeps, start, n_steps, self.spline_degree)  # [W, m, b]
        return PreparedInputs(samples, held.permute(2, 1, 0).contiguous(), int(start), n_steps)

    def outputs(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None) -> Tensor:
        params, x0 = self._split(theta)
        samples, window = self._unpack(inputs, start, n_steps)
        return exact_outputs(
            self.model,
            params,
            x0,
            samples,
            self.h,
            self.hold,
            self.substeps,
            spline_degree=self.spline_degree,
            **window,
        )

    def sensitivities(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None) -> Tensor:
        return self._sensitivities(exact_sensitivities, theta, inputs, start, n_steps)

    # the outputs by the step recursion with per-sample Van Loan maps, elementwise states and per-sample products;
    # not the sensitivities: a sample's modal basis is as wide as its batch's largest number of propagated modes,
    # and the product's other width rounds otherwise (an under-damped seat beside an over-damped one: 1e-18 of the
    # largest entry)
    outputs_apart = True

    def _own_sensitivities(self) -> bool:
        """A subclass with sensitivities of its own (e.g. a delay): the deferred and residual forms below
        would bypass them, so the base class's generic forms over its sensitivities are used instead."""
        return type(self).sensitivities is not ExactResponse.sensitivities

    def sensitivities_deferred(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None):
        if self._own_sensitivities():
            return super().sensitivities_deferred(theta, inputs, start, n_steps)
        return self._sensitivities(exact_sensitivities, theta, inputs, start, n_steps, defer_fallback=True)

    def fallback_sensitivities(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None) -> Tensor:
        if self._own_sensitivities():
            return self.sensitivities(theta, inputs, start, n_steps)
        return self._sensitivities(fallback_sensitivities, theta, inputs, start, n_steps)

    def residual_sensitivities(self, theta: Tensor, inputs, start: int, n_steps: int, targets: Tensor):
        if self._own_sensitivities():
            return super().residual_sensitivities(theta, inputs, start, n_steps, targets)
        return self._sensitivities(
            exact_sensitivities, theta, inputs, start, n_steps, defer_fallback=True, targets=targets
        )

    def _sensitivities(self, layer, theta: Tensor, inputs, start: int, n_steps: int | None, **options):
        params, x0 = self._split(theta)
        samples, window = self._unpack(inputs, start, n_steps)
        return layer(
            self.model,
            params,
            x0,
            samples,
            self.h,
            self.hold,
            self.substeps,
            with_x0=self.with_x0,
            spline_degree=self.spline_degree,
            **window,
            **options,
        )

    @staticmethod
    def _unpack(inputs, start: int, n_steps: int | None) -> tuple[Tensor, dict]:
        """(inputs [b, T_in, m], keyword arguments of the exact layer for the window)."""
        if not isinstance(inputs, PreparedInputs):
            return _as_3d(inputs), _window(inputs, start, n_steps)
        n_steps = inputs.samples.shape[1] - start if n_steps is None else int(n_steps)
        if (int(start), n_steps) != (inputs.start, inputs.n_steps):
            raise ValueError(
                f"inputs prepared for the window start={inputs.start}, n_steps={inputs.n_steps} "
                f"evaluated at start={start}, n_steps={n_steps}"
            )
        return inputs.samples, {"start": inputs.start, "n_steps": inputs.n_steps, "held": inputs.held}


def _window(inputs: Tensor, start: int, n_steps: int | None) -> dict:
    """Keyword arguments of the exact layer for a window (none for the whole input: older layer API)."""
    if start == 0 and (n_steps is None or n_steps == inputs.shape[1]):
        return {}
    return {"start": int(start), "n_steps": int(inputs.shape[1] - start if n_steps is None else n_steps)}


def _as_3d(inputs: Tensor) -> Tensor:
    """[b, time] -> [b, time, 1] (a single input such as the road)."""
    return inputs.unsqueeze(-1) if inputs.ndim == 2 else inputs


def quarter_car_response(
    model: str,
    h: float,
    scaled_road: bool,
    initial_state: str = "unknown",
    hold: str = "spline",
    substeps: int = 4,
    spline_degree: int = 5,
) -> ResponseModel:
    """The road-driven quarter car as the solver's model: ``model="euler"`` (source protocol, from rest)
    or ``"exact"`` (continuous-time physics)."""
    if model == "euler":
        return EulerResponse(h, scaled_road, initial_state)
    if model == "exact":
        return ExactResponse(QuarterCarRoad(scaled_road=scaled_road), h, hold, substeps, initial_state, spline_degree)
    raise ValueError(f"model={model!r}: choose exact or euler")


BASE_MODELS = {"seat": SeatBaseExcitation, "sprung": SprungBaseExcitation}


def base_excitation_response(
    name: str, h: float, initial_state: str = "unknown", hold: str = "spline", substeps: int = 4, spline_degree: int = 5
) -> ResponseModel:
    """A road-free model driven by a measured acceleration (SPEC §9): ``seat`` (a2 -> a3; p1, p2) or
    ``sprung`` (a1 -> a3, a2; p1..p6), always continuous-time (exact discretisation)."""
    if name not in BASE_MODELS:
        raise ValueError(f"base excitation model {name!r}: choose one of {sorted(BASE_MODELS)}")
    return ExactResponse(BASE_MODELS[name](), h, hold, substeps, initial_state, spline_degree)
