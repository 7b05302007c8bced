"""The seated occupant: a rigid mass, or a rigid part with one or two body modes (SPEC § 10).

A seated person is not rigid: the apparent mass of the body in vertical vibration equals the static
mass only near 0 Hz and has its principal resonance at 4–6 Hz (Fairley & Griffin 1989, J. Biomech.
22: 81–94; a one-mode model with a rigid part fits their mean at 5 Hz with a damping ratio near 0.5,
Brammer & Peterson, Biomedical Engineering and Design Handbook, ch. 11), often a second mode at
8–12 Hz (Wei & Griffin 1998, J. Sound Vib. 212: 855–874; ISO 5982).

Model. On the seat spring K3 and damper C3 rides a rigid part m_s (the seat pan, whose mass nobody
knows, and the part of the body that moves with it) and, hung on it, up to two body masses m_i
through k_i, c_i. The pan then sees the apparent mass

    AM(s) = m_s + Σ_i m_i T_i(s),     T_i(s) = (c_i s + k_i) / (m_i s² + c_i s + k_i),

and the static mass on the seat spring is M = AM(0) = m_s + Σ m_i: what the estimator reports.

Parameters, per unit static mass so that the rigid model's (p1, p2) keep their meaning and any
positive values are physical:

    p1 = C3 / M,  p2 = K3 / M          (the rigid occupant's parameters; M = K3 / p2)
    r_i = m_i / m_s                    body mass over the rigid part (> 0)
    k_i = k_i / m_i = ω_i²  [rad²/s²]  the body mode's squared natural frequency on a fixed pan
    c_i = c_i / m_i = 2 ζ_i ω_i  [1/s]

With R = 1 + Σ r_i (so m_s = M / R, m_i = r_i M / R), base excitation by the seat base's
acceleration a2, pan deflection z = q_pan − q2 and body deflections y_i = q_i − q_pan:

    a_pan = R (−p1 ż − p2 z) + Σ r_i (c_i ẏ_i + k_i y_i)
    z̈ = a_pan − a2,    ÿ_i = −(c_i ẏ_i + k_i y_i) − a_pan

and the seat transmissibility is A_pan/A2 = (p1 s + p2) / (s² AM(s)/M + p1 s + p2).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

OCCUPANT_MODELS = ("rigid", "body1", "body2")
N_MODES = {"rigid": 0, "body1": 1, "body2": 2}
MODE_PARAMS = ("r", "k", "c")


def occupant_param_names(n_modes: int) -> tuple[str, ...]:
    """("p1", "p2", "r1", "k1", "c1", ...) for a seat with ``n_modes`` body modes."""
    return ("p1", "p2") + tuple(f"{name}{i}" for i in range(1, n_modes + 1) for name in MODE_PARAMS)


# The literature's ranges as a weak Gaussian prior on each mode's (r, k, c): the centre and a
# standard deviation about half the range's width (a prior, not a constraint). Mode 1: 4–6 Hz,
# ζ 0.3–0.5, a rigid part (pan + the body's rigid part) of 20–45 % of the static mass (r 1.2–4).
# Mode 2: 8–12 Hz, ζ 0.2–0.5, a smaller mass (r 0.1–1). Used only where the data are noisy
# (the refinement's prior acts on recordings with a sensor noise floor).
def _mode_prior(f_lo: float, f_hi: float, z_lo: float, z_hi: float, r_mean: float, r_std: float):
    w_lo, w_hi = 2 * math.pi * f_lo, 2 * math.pi * f_hi
    k_mean, k_std = 0.5 * (w_lo**2 + w_hi**2), 0.5 * (w_hi**2 - w_lo**2)
    c_lo, c_hi = 2 * z_lo * w_lo, 2 * z_hi * w_hi
    return (r_mean, k_mean, 0.5 * (c_lo + c_hi)), (r_std, k_std, 0.5 * (c_hi - c_lo))


BODY_PRIOR = (_mode_prior(4.0, 6.0, 0.3, 0.5, 2.0, 1.5), _mode_prior(8.0, 12.0, 0.2, 0.5, 0.5, 0.5))


def body_prior(n_modes: int) -> tuple[Tensor, Tensor]:
    """(mean, std) [3 n_modes] of the body parameters (r_i, k_i, c_i) (BODY_PRIOR)."""
    mean = [v for i in range(n_modes) for v in BODY_PRIOR[i][0]]
    std = [v for i in range(n_modes) for v in BODY_PRIOR[i][1]]
    return torch.tensor(mean, dtype=torch.float64), torch.tensor(std, dtype=torch.float64)


def body_start(n_modes: int) -> Tensor:
    """Where a fit starts the body parameters [3 n_modes]: the prior's centre."""
    return body_prior(n_modes)[0]


def _split(params: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """params [b, 2 + 3 n] -> p1 [b], p2 [b], r [b, n], k [b, n], c [b, n]."""
    n_modes = (params.shape[-1] - 2) // 3
    if params.shape[-1] != 2 + 3 * n_modes:
        raise ValueError(f"occupant params must be [batch, 2 + 3 n_modes], got {tuple(params.shape)}")
    modes = params[:, 2:].reshape(params.shape[0], n_modes, 3)
    return params[:, 0], params[:, 1], modes[..., 0], modes[..., 1], modes[..., 2]


def normalised_apparent_mass(params: Tensor, omega: Tensor) -> Tensor:
    """AM(iω)/M, complex [b, F], for params [b, 2 + 3 n] and angular frequencies omega [F] (rad/s)."""
    _, _, r, k, c = _split(params.to(torch.float64))
    s = 1j * omega.to(torch.float64)[None, :, None]  # [1, F, 1]
    T = (c[:, None] * s + k[:, None]) / (s * s + c[:, None] * s + k[:, None])  # per unit m_i: [b, F, n]
    R = 1.0 + r.sum(-1)
    return (1.0 + (r[:, None] * T).sum(-1)) / R[:, None]


def transmissibility(params: Tensor, omega: Tensor) -> Tensor:
    """A_pan/A2 (iω), complex [b, F] (seat base to seat pan)."""
    p1, p2 = params[:, 0].double()[:, None], params[:, 1].double()[:, None]
    s = 1j * omega.to(torch.float64)[None]
    return (p1 * s + p2) / (s * s * normalised_apparent_mass(params, omega) + p1 * s + p2)


def derived(params: Tensor, K3: float) -> dict[str, Tensor]:
    """Readable diagnostics [b] per mode i: f{i}_hz (natural frequency on a fixed pan), zeta{i},
    mass{i}_kg (body mass) and rigid_kg (pan + rigid part); static mass m3 = K3 / p2."""
    p1, p2, r, k, c = _split(params.double())
    M = K3 / p2
    R = 1.0 + r.sum(-1)
    out = {"rigid_kg": M / R}
    for i in range(r.shape[1]):
        w = k[:, i].clamp_min(0).sqrt()
        out[f"f{i + 1}_hz"] = w / (2 * math.pi)
        out[f"zeta{i + 1}"] = c[:, i] / (2 * w).clamp_min(1e-300)
        out[f"mass{i + 1}_kg"] = r[:, i] * M / R
    return out
