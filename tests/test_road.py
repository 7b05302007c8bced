"""ISO 8608 road profiles (SPEC §3): variance, class scaling, the fast method equals the direct sum."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hybridqcm.physics.road import ROAD_CLASSES, RoadProfile, road_class_index, road_class_phi0

SPEED = 30 / 3.6


def spec_variance(phi0: float, n_waves: int = 1000) -> float:
    """1/2 sum A_i^2 from SPEC §3 written out by hand."""
    omega = np.linspace(0.02 * np.pi, 6 * np.pi, n_waves)
    d_omega = (6 * np.pi - 0.02 * np.pi) / (n_waves - 1)
    amplitude_sq = phi0 * omega**-2.0 * d_omega / np.pi
    return 0.5 * amplitude_sq.sum()


def test_class_phi0_and_expected_variance_match_spec():
    for index, phi0 in enumerate([1e-6, 4e-6, 16e-6, 64e-6, 256e-6]):
        assert road_class_phi0(index).item() == pytest.approx(phi0, rel=1e-15)
        assert RoadProfile().variance(index) == pytest.approx(spec_variance(phi0), rel=1e-12)
    # class A: std about 4.6 mm over this band
    assert math.sqrt(RoadProfile().variance(0)) == pytest.approx(math.sqrt(spec_variance(1e-6)), rel=1e-12)


def test_variance_of_one_long_profile():
    """Time average of u^2 over 2 km of one profile approaches 1/2 sum A_i^2 (phases random,
    frequencies distinct, so cross terms average out)."""
    road = RoadProfile()
    for cls in (0, 2):
        amplitude, phase = road._draw(torch.tensor([cls]), torch.Generator().manual_seed(cls + 1))
        s = torch.arange(0, 2000, 0.1, dtype=torch.float64)  # 0.1 m < half the shortest wavelength (1/3 m)
        u = road.evaluate(amplitude, phase, s)
        assert (u**2).mean().item() == pytest.approx(spec_variance(1e-6 * 4**cls), rel=0.03)
        assert abs(u.mean().item()) < 0.1 * math.sqrt(spec_variance(1e-6 * 4**cls))


def test_variance_over_many_profiles():
    """Ensemble mean of u^2 over 3000 independent class-B profiles, within 4 standard errors."""
    road = RoadProfile()
    u = road.sample(torch.full((3000,), 1), 20, 0.01, SPEED, torch.Generator().manual_seed(0))
    per_profile = (u**2).mean(1)
    expected = spec_variance(4e-6)
    standard_error = per_profile.std().item() / math.sqrt(per_profile.numel())
    assert abs(per_profile.mean().item() - expected) < 4 * standard_error
    assert standard_error < 0.05 * expected


def test_class_scaling_is_factor_four_in_variance():
    """Same generator state, class k+1 vs class k: the same phases, amplitudes x2, variance x4."""
    road = RoadProfile()
    base = road.sample(torch.zeros(5, dtype=torch.long), 300, 0.01, SPEED, torch.Generator().manual_seed(3))
    for k in range(1, len(ROAD_CLASSES)):
        scaled = road.sample(torch.full((5,), k), 300, 0.01, SPEED, torch.Generator().manual_seed(3))
        torch.testing.assert_close(scaled, base * 2**k, rtol=1e-12, atol=0)
        assert road.variance(k) / road.variance(k - 1) == pytest.approx(4.0, rel=1e-13)


def test_sample_equals_sample_direct():
    road = RoadProfile()
    classes = torch.tensor([0, 1, 2, 0, 5])
    fast = road.sample(classes, 700, 0.01, SPEED, torch.Generator().manual_seed(42))
    direct = road.sample_direct(classes, 700, 0.01, SPEED, torch.Generator().manual_seed(42))
    assert fast.shape == direct.shape == (5, 700) and fast.dtype == torch.float64
    scale = direct.abs().max(1, keepdim=True).values
    assert ((fast - direct).abs() / scale).max() < 1e-10
    # a different generator state gives a different profile
    other = road.sample(classes, 700, 0.01, SPEED, torch.Generator().manual_seed(43))
    assert not torch.allclose(fast, other)


def test_profile_starts_at_sum_of_phases_and_uses_speed():
    """u(0) = -sum A_i sin(phi_i); at twice the speed the profile is the same one sampled twice as far."""
    road = RoadProfile(n_waves=50)
    amplitude, phase = road._draw(torch.tensor([2]), torch.Generator().manual_seed(7))
    u = road.sample(torch.tensor([2]), 40, 0.01, SPEED, torch.Generator().manual_seed(7))
    assert u[0, 0].item() == pytest.approx(-(amplitude * torch.sin(phase)).sum().item(), rel=1e-12)
    u2 = road.sample(torch.tensor([2]), 20, 0.01, 2 * SPEED, torch.Generator().manual_seed(7))
    torch.testing.assert_close(u2[0], u[0, ::2], rtol=1e-10, atol=1e-15)


def test_road_class_names_and_errors():
    assert [road_class_index(c) for c in "ABCH"] == [0, 1, 2, 7]
    assert road_class_index("b") == 1 and road_class_index(" c ") == 2
    for bad in ("Z", "AB", "", "I", 1):
        with pytest.raises(ValueError, match="unknown road class"):
            road_class_index(bad)
    with pytest.raises(ValueError, match="out of range"):
        road_class_phi0(8)
    with pytest.raises(ValueError, match="out of range"):
        RoadProfile().sample(torch.tensor([0, -1]), 10, 0.01, SPEED)


def test_road_grid_validation():
    road = RoadProfile()
    for n_steps, h, speed in [(0, 0.01, SPEED), (10, 0.0, SPEED), (10, 0.01, -1.0)]:
        with pytest.raises(ValueError, match="road grid"):
            road.sample(torch.tensor([0]), n_steps, h, speed)
    with pytest.raises(ValueError, match="n_waves"):
        RoadProfile(n_waves=1)
    with pytest.raises(ValueError, match="omega"):
        RoadProfile(omega_min=1.0, omega_max=0.5)
