"""A delay between the input and output channels as an unknown of the fit (two loggers, two clocks).

When the output channel's logger runs τ behind the input's (SPEC § 10), the recorded output is
y(t - τ) = (model driven by w(· - τ))(t): the same model, driven by the input delayed by τ. A delay
of 1 ms costs about 0.8 % of the occupant's mass on the reference seat, so τ is estimated with p.

θ = (p_1..p_P, τ, x0_1..x0_n): τ [s] sits with the parameters (known masks, priors and restarts
address it by name) but may take either sign (``positive`` leaves it out); x0 is the state at the
window's first sample under the delayed input.

The held input. The exact layer holds the input on a fine grid of step Δ = h/M (M = substeps, the
spline's sub-samples; estimation/exact.py). ``prepare`` holds it once over the window widened by
D samples on each side (D·h ≥ ``max_delay``, as far as the recording holds samples), and each
evaluation reads the window's sub-samples at t - τ by four-point Lagrange interpolation on that fine
grid (error ~ (ωΔ)⁴/24: below 1e-6 of a 15 Hz component at 100 Hz, M = 16), per sample:

    s_τ[j] = Σ_{i=-1..2} L_i(u) s[base + i],   base + u = D M + j - τ/Δ,   u ∈ [0, 1)

The outputs are linear in the held input, so dy/dτ is the model's response, from rest, to
ds_τ/dτ = -(1/Δ) Σ_i L_i'(u) s[base + i]: one more output evaluation per Jacobian. Delays beyond the
held range are clamped to it (their column is then zero: such a fit ends singular, not silently).
Models with a direct feed-through (E ≠ 0) read the raw samples at the window's instants and are refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ._kernels import applies as _compiled_applies
from ._kernels import delay_taps as _compiled_taps
from .exact import exact_outputs, exact_sensitivities
from .hold import held_input
from .response import ExactResponse, PreparedInputs, ResponseModel, _as_3d


@dataclass(frozen=True)
class DelayedInputs(PreparedInputs):
    """Inputs [b, T_in, m] with the held input of the *widened* window, batch first [b, m, W_wide]
    (``held_by_sample``, without the exact layer's leading zero rows); ``pad`` fine samples of it lie
    before the window's first sub-sample. Indexing selects samples."""

    pad: int = 0

    def __getitem__(self, index) -> DelayedInputs:
        return DelayedInputs(self.samples[index], self.held_by_sample[index], self.start, self.n_steps, self.pad)


def _lagrange(u: Tensor) -> tuple[Tensor, Tensor]:
    """Four-point Lagrange weights on nodes -1, 0, 1, 2 at u [b] and their derivatives: [b, 4] each."""
    u = u[:, None]
    w = torch.cat(
        [
            -u * (u - 1) * (u - 2) / 6,
            (u + 1) * (u - 1) * (u - 2) / 2,
            -(u + 1) * u * (u - 2) / 2,
            (u + 1) * u * (u - 1) / 6,
        ],
        1,
    )
    dw = torch.cat(
        [
            -(3 * u * u - 6 * u + 2) / 6,
            (3 * u * u - 4 * u - 1) / 2,
            -(3 * u * u - 2 * u - 2) / 2,
            (3 * u * u - 1) / 6,
        ],
        1,
    )
    return w, dw


class DelayedResponse(ResponseModel):
    """An :class:`ExactResponse` whose input is delayed by an estimated τ (module docstring)."""

    def __init__(self, inner: ExactResponse, max_delay: float = 0.02) -> None:
        if not isinstance(inner, ExactResponse):
            raise ValueError(f"a channel delay needs the exact model, got {type(inner).__name__}")
        if not (isinstance(max_delay, (int, float)) and math.isfinite(max_delay) and max_delay >= 0):
            raise ValueError(f"max_delay must be a number >= 0 [s], got {max_delay!r}")
        self.inner, self.model, self.h = inner, inner.model, inner.h
        self.max_delay = float(max_delay)
        self.n_params = inner.n_params + 1
        names = inner.theta_names
        self.theta_names = names[: inner.n_params] + ("tau",) + names[inner.n_params :]
        self.output_names = inner.output_names
        self.with_x0 = inner.with_x0
        self.m_sub = inner.substeps if inner.hold == "spline" else 1
        self.fine_step = self.h / self.m_sub

    @property
    def positive(self) -> Tensor:
        mask = super().positive
        mask[self.n_params - 1] = False
        return mask

    def margin_samples(self) -> int:
        """Input samples needed beyond each end of the window: the delay, and two for the interpolation."""
        return math.ceil(self.max_delay / self.h - 1e-9) + 2

    def prepare(self, inputs, start: int = 0, n_steps: int | None = None) -> DelayedInputs:
        if isinstance(inputs, DelayedInputs):
            n = inputs.samples.shape[1] - start if n_steps is None else int(n_steps)
            if (int(start), n) != (inputs.start, inputs.n_steps):
                raise ValueError(
                    f"inputs prepared for the window start={inputs.start}, n_steps={inputs.n_steps} "
                    f"evaluated at start={start}, n_steps={n}"
                )
            return inputs
        samples = _as_3d(inputs).to(torch.float64)
        n_steps = samples.shape[1] - start if n_steps is None else int(n_steps)
        D = self.margin_samples()
        before = min(D, int(start))
        after = min(D, samples.shape[1] - int(start) - n_steps)
        if before < 1 or after < 1:
            raise ValueError(
                f"a channel delay needs input samples on both sides of the window (start={start}, n_steps={n_steps} "
                f"of {samples.shape[1]}): give the fit an input margin"
            )
        held = held_input(samples, self.inner.hold, self.inner.substeps, int(start) - before, n_steps + before + after)
        wide = held[self.m_sub :].permute(2, 1, 0).contiguous()  # drop the leading zero rows: [b, m, W_wide]
        return DelayedInputs(samples, wide, int(start), n_steps, before * self.m_sub)

    def _held(self, inputs: DelayedInputs, tau: Tensor, derivative: bool = True) -> tuple[Tensor, Tensor | None]:
        """(held, d held/dτ), each [W, m, b] in the exact layer's layout (M leading zero rows); the derivative
        None unless ``derivative`` (a loss evaluation needs the held input alone)."""
        wide = inputs.held_by_sample  # [b, m, W_wide]
        b, m, n_wide = wide.shape
        n_fine = (inputs.n_steps - 1) * self.m_sub + 1
        # keep base - 1 .. base + n_fine + 1 inside the held range
        shift = (tau.double() / self.fine_step).clamp(-(n_wide - n_fine - inputs.pad - 2), inputs.pad - 2)
        position = inputs.pad - shift  # fractional index of the window's first sub-sample at t - τ
        base = position.floor()
        u = position - base
        w, dw = _lagrange(u)
        if _compiled_applies(wide):  # the same sums per fine sample, compiled, straight into the exact layer's layout
            held, dheld = _compiled_taps(wide, base.long() - 1, w, dw if derivative else None, self.m_sub, n_fine)
            held = held.permute(2, 1, 0)
            if not derivative:
                return held, None
            dheld[..., self.m_sub :] *= -1.0 / self.fine_step  # du/dτ = -1/Δ (the leading zeros stay +0)
            return held, dheld.permute(2, 1, 0)
        # the four taps (offsets -1 .. 2) of every fine sample: one gather of the span, its sliding windows
        # [b, m, n_fine, 4] (a view), times the weights as one product (5x faster than a gather per tap)
        index = (base.long() - 1)[:, None] + torch.arange(n_fine + 3, device=wide.device)[None, :]
        taps = wide.gather(2, index[:, None, :].expand(b, m, n_fine + 3)).unfold(2, 4, 1)
        if derivative:
            both = taps @ torch.stack([w, dw], 2)[:, None]  # [b, m, n_fine, 2]
            held, dheld = both[..., 0], both[..., 1]
        else:
            held = (taps @ w[:, None, :, None])[..., 0]
        lead = wide.new_zeros(b, m, self.m_sub)
        held = torch.cat([lead, held], 2).permute(2, 1, 0)
        if not derivative:
            return held, None
        dheld = dheld * (-1.0 / self.fine_step)  # du/dτ = -1/Δ
        return held, torch.cat([lead, dheld], 2).permute(2, 1, 0)

    def _split(self, theta: Tensor):
        P = self.n_params - 1
        return theta[:, :P], theta[:, P], (theta[:, P + 1 :] if self.with_x0 else None)

    def _window(self, inputs, start: int, n_steps: int | None) -> DelayedInputs:
        return self.prepare(inputs, start, n_steps)

    def outputs(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None) -> Tensor:
        params, tau, x0 = self._split(theta)
        prepared = self._window(inputs, start, n_steps)
        held, _ = self._held(prepared, tau, derivative=False)
        inner = self.inner
        return exact_outputs(
            self.model, params, x0, prepared.samples, self.h, inner.hold, inner.substeps,
            start=prepared.start, n_steps=prepared.n_steps, held=held,
        )  # fmt: skip

    def sensitivities(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None) -> Tensor:
        params, tau, x0 = self._split(theta)
        prepared = self._window(inputs, start, n_steps)
        held, dheld = self._held(prepared, tau)
        inner = self.inner
        common = dict(start=prepared.start, n_steps=prepared.n_steps)
        out = exact_sensitivities(
            self.model, params, x0, prepared.samples, self.h, inner.hold, inner.substeps,
            with_x0=self.with_x0, held=held, **common,
        )  # fmt: skip
        dtau = exact_outputs(
            self.model, params, None, prepared.samples, self.h, inner.hold, inner.substeps, held=dheld, **common
        )
        P = self.n_params - 1
        return torch.cat([out[..., : 1 + P], dtau[..., None], out[..., 1 + P :]], -1)


def check_no_feedthrough(response: ExactResponse) -> None:
    """Refuse a model whose outputs read the input directly (E ≠ 0): the delay would miss that term."""
    model = response.model
    p = torch.ones(1, model.n_params, dtype=torch.float64)
    if bool(model.matrices(p)[3].abs().gt(0).any()):
        raise ValueError(f"a channel delay is not available for {model.name}: its outputs read the input directly")
