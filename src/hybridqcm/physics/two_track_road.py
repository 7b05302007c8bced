"""Two wheel tracks of one ISO 8608 road: left and right correlated, the rear wheels on the front's track.

Each track is SPEC § 3's sum of sines, u(s) = Σ_i A_i sin(Ω_i s − φ_i), with the ISO 8608 amplitudes
of its road class. The left and right tracks (a track width B = w_l + w_r apart) are neither equal
nor independent: for a homogeneous, isotropic road surface the cross-spectral density of two parallel
tracks is real and their coherence depends only on Ω B (Dodds & Robson 1973, "The description of
road surface roughness", J. Sound Vib. 31(2) 175-183; Kamash & Robson 1978, "The application of
isotropy in road surface modelling", J. Sound Vib. 57(1) 89-100). For ISO 8608's waviness w = 2
(Φ ∝ Ω⁻², i.e. a 2-D spectrum ∝ |κ|⁻³) the integral has a closed form:

    γ(Ω) = S_lr(Ω) / S(Ω) = Ω B K₁(Ω B)        (K₁ the modified Bessel function of the second kind)

from ∫₀^∞ cos(κB) (Ω² + κ²)^(-3/2) dκ = (B/Ω) K₁(ΩB) over ∫₀^∞ (Ω² + κ²)^(-3/2) dκ = 1/Ω². γ → 1 for
long waves (Ω B → 0: both wheels ride the same swell) and decays like e^(-Ω B) for short ones
(Bogsjö, Podgórski & Rychlik 2012, "Models for road surface roughness", Veh. Syst. Dyn. 50(5)
725-747, review it beside Ammon's empirical fit). The right track is drawn wave by wave as

    u_r(s) = Σ_i A_i [γ_i sin(Ω_i s − φ_i) + sqrt(1 − γ_i²) sin(Ω_i s − ψ_i)],   ψ_i ~ U[0, 2π) independent,

so it has the left track's ISO spectrum and the coherence γ with it. The rear wheels follow the
front ones on the same track, delayed by the wheelbase: u_b(t) = u_f(t − (l_f + l_b)/v). The half
car rides one track (the left one's).

In time, s = v t and wave i has the temporal frequency ω_i = Ω_i v. A wheel's input is then
u(t) = Im[Σ_i z_i e^(i ω_i t)] with the complex amplitude z_i = A_i e^(-i φ_i) (left front),
A_i (γ_i e^(-i φ_i) + sqrt(1 − γ_i²) e^(-i ψ_i)) (right front), times e^(-i ω_i τ) at the rear;
its velocity has i ω_i z_i. physics/vehicle_response.py integrates the vehicle exactly for such inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hybridqcm.physics.road import RoadProfile

COHERENCE_MODELS = ("isotropic", "identical", "independent")


@dataclass
class TwoTrackDraw:
    """amplitude A_i [b, W] (ISO 8608, the road class), phase φ_i of the left track [b, W] and ψ_i, the
    independent phase of the right track's incoherent part [b, W]."""

    amplitude: Tensor
    phase_left: Tensor
    phase_right: Tensor

    def __getitem__(self, index) -> TwoTrackDraw:
        return TwoTrackDraw(self.amplitude[index], self.phase_left[index], self.phase_right[index])


class TwoTrackRoad:
    """Two correlated tracks of an ISO 8608 road (module docstring).

    coherence: "isotropic" (γ = Ω B K₁(Ω B), the default), "identical" (γ = 1: both wheels of an axle
    on the same profile, e.g. to reduce the full car to the half car) or "independent" (γ = 0)."""

    def __init__(self, profile: RoadProfile | None = None, coherence: str = "isotropic") -> None:
        if coherence not in COHERENCE_MODELS:
            raise ValueError(f"road coherence={coherence!r}: choose one of {list(COHERENCE_MODELS)}")
        self.profile = profile if profile is not None else RoadProfile()
        self.coherence_model = coherence

    @property
    def omega(self) -> Tensor:
        """Spatial angular frequencies Ω_i [W] rad/m."""
        return self.profile.omega

    def coherence(self, track_width: Tensor) -> Tensor:
        """γ(Ω_i) [b, W] for track widths B [b] in metres."""
        x = self.omega[None, :] * track_width.to(torch.float64)[:, None]
        if self.coherence_model == "identical":
            return torch.ones_like(x)
        if self.coherence_model == "independent":
            return torch.zeros_like(x)
        return (x * torch.special.modified_bessel_k1(x)).clamp(0.0, 1.0)

    def draw(self, road_class: Tensor, generator: torch.Generator | None = None) -> TwoTrackDraw:
        """One two-track road per class index [b]: the left track exactly as RoadProfile.draw (same
        generator draws), then the right track's independent phases."""
        amplitude, phase_left = self.profile.draw(road_class, generator)
        phase_right = 2 * math.pi * torch.rand(phase_left.shape, generator=generator, dtype=torch.float64)
        return TwoTrackDraw(amplitude, phase_left, phase_right)

    def wheel_amplitudes(
        self, draw: TwoTrackDraw, wheels: tuple[str, ...], speed_mps: float, wheelbase: Tensor, track_width: Tensor
    ) -> Tensor:
        """Complex amplitudes z [b, n_wheels, W] of every wheel's road input, u_w(t) = Im Σ_i z_wi e^(i ω_i t),
        ω_i = Ω_i speed; wheelbase l_f + l_b and track width w_l + w_r per sample [b] (metres).
        Wheels f, b (one track: the left) or fl, fr, bl, br."""
        if not speed_mps > 0:
            raise ValueError(f"speed must be > 0 m/s, got {speed_mps}")
        left = torch.polar(draw.amplitude, -draw.phase_left)  # A e^{-iφ}
        if any(w.endswith("r") for w in wheels):
            gamma = self.coherence(track_width)
            right = torch.polar(draw.amplitude * gamma, -draw.phase_left) + torch.polar(
                draw.amplitude * torch.sqrt((1 - gamma.square()).clamp_min(0.0)), -draw.phase_right
            )
        omega_t = self.omega * float(speed_mps)
        delay = torch.polar(
            torch.ones_like(draw.amplitude), -omega_t[None, :] * (wheelbase.to(torch.float64)[:, None] / speed_mps)
        )
        out = []
        for wheel in wheels:
            z = right if wheel.endswith("r") else left
            out.append(z * delay if wheel.startswith("b") else z)
        return torch.stack(out, 1)


__all__ = ["TwoTrackRoad", "TwoTrackDraw", "COHERENCE_MODELS"]
