"""The noise model fitted to a residual (estimation/weighting.py): the input noise's band bound."""

from __future__ import annotations

import math

import torch

from hybridqcm.estimation.response import base_excitation_response
from hybridqcm.estimation.weighting import NoiseFit, NoiseWeighting, input_band_power
from hybridqcm.testing import seat_recordings

H_STEP = 0.01


def test_band_power_is_the_white_noise_variance_beside_a_strong_low_band_signal():
    g = torch.Generator().manual_seed(3)
    b, T, sigma = 64, 512, 0.05
    t = torch.arange(T, dtype=torch.float64)[None, :, None] * H_STEP
    freq = torch.rand(b, 1, 5, generator=g, dtype=torch.float64) * 14 + 0.5  # all below a quarter of 100 Hz
    signal = torch.sin(2 * math.pi * freq * t).sum(-1, keepdim=True) * 20  # 400x the noise's RMS
    noise = sigma * torch.randn(b, T, 1, generator=g, dtype=torch.float64)
    power = input_band_power(signal + noise)
    # the mean over 64 recordings of ~130 tapered bins each: within a few per cent of σ² (no leakage of the signal)
    assert abs(float(power.mean()) / sigma**2 - 1) < 0.05
    assert float(input_band_power(signal).max()) < 1e-3 * sigma**2


def test_the_input_noise_of_a_misfit_is_bounded_by_the_inputs_band_power():
    """At a wrong seat (p2 30 % off) the Whittle fit reads the misfit at the resonance as input noise, several
    times the truth; the band bound (the input's own upper band: white noise only here) keeps it near the truth."""
    b, T, margin, sigma = 16, 512, 8, 0.05
    p, a2, a3 = seat_recordings(b, T, margin, sigma, seed=5, h=H_STEP)
    truth = (sigma**2) * a2[:, margin : margin + T].square().mean(1)[:, 0] / (1 + sigma**2)  # [b]
    response = base_excitation_response("seat", H_STEP, substeps=16)
    wrong = torch.cat([p * torch.tensor([1.0, 1.3], dtype=torch.float64), torch.zeros(b, 2)], 1)
    known = torch.zeros(4, dtype=torch.bool)
    ratios = {}
    for cap in (False, True):
        fit = NoiseFit(response, H_STEP, known, NoiseWeighting(mode="spectral", band_cap=cap), quarter_car=False)
        noise = fit.noise_model(a3, a2, wrong, (True,), offset=margin)
        ratios[cap] = noise.v_in[:, 0] / truth
    assert float(ratios[False].median()) > 2.0  # the misfit, called input noise
    assert float(ratios[True].max()) < 1.3
    assert float(ratios[True].median()) > 0.8
