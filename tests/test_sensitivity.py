"""Forward-mode sensitivities of the Euler recursion: values and Jacobian (FD and autograd)."""

import pytest
import torch

from hybridqcm.estimation.sensitivity import (
    EulerSensitivity,
    accelerations_and_jacobian,
    euler_accelerations,
    euler_sensitivities,
)
from hybridqcm.physics import simulate
from hybridqcm.physics.integrators import SemiExplicitEuler
from hybridqcm.testing import synthetic_samples

H = 0.01


@pytest.fixture(scope="module")
def samples():
    return synthetic_samples(6, n_steps=60, seed=3)


@pytest.mark.parametrize("scaled_road", [False, True])
def test_layer_matches_data_generator(samples, scaled_road):
    p, road = samples["params"], samples["road"]
    forcing = (p[:, 9] - p[:, 8])[:, None] * road if scaled_road else road
    ours = euler_accelerations(p, forcing, H, scaled_road=scaled_road)
    reference = simulate(p, forcing, H, scaled_road=scaled_road).accel
    assert ours.shape == (6, 60, 3) and ours.dtype == torch.float64
    torch.testing.assert_close(ours, reference, rtol=1e-12, atol=1e-14)
    # the true parameters reproduce the generator's stored accelerations
    torch.testing.assert_close(ours, samples["accel"], rtol=1e-12, atol=1e-14)
    # the tangent recursion carries the same primal
    accel, _ = accelerations_and_jacobian(p, forcing, H, scaled_road)
    torch.testing.assert_close(accel, reference, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("scaled_road", [False, True])
def test_jacobian_matches_autograd(samples, scaled_road):
    p, road = samples["params"][:3], samples["road"][:3]
    _, jac = EulerSensitivity(H, scaled_road)(p, road)  # [batch, time, 3, 10]
    layer = SemiExplicitEuler(H, scaled_road=scaled_road)
    full = torch.autograd.functional.jacobian(lambda q: layer(q, road), p, vectorize=True)  # [b, T, 3, b, 10]
    reverse = torch.stack([full[i, :, :, i] for i in range(3)])
    scale = reverse.abs().amax()
    torch.testing.assert_close(jac, reverse, rtol=1e-9, atol=1e-12 * scale)


def test_jacobian_matches_finite_differences(samples):
    p, road = samples["params"][:2], samples["road"][:2]
    _, jac = accelerations_and_jacobian(p, road, H)
    for j in range(10):
        step = 1e-5 * p[:, j]
        plus, minus = p.clone(), p.clone()
        plus[:, j] += step
        minus[:, j] -= step
        fd = (euler_accelerations(plus, road, H) - euler_accelerations(minus, road, H)) / (2 * step)[:, None, None]
        scale = fd.abs().amax().clamp_min(1e-300)
        assert (jac[..., j] - fd).abs().amax() <= 1e-5 * scale, f"p{j + 1}"


def test_sensitivity_layout_and_validation(samples):
    p, road = samples["params"], samples["road"]
    out = euler_sensitivities(p, road, H)
    assert out.shape == (6, 60, 3, 11)
    with pytest.raises(ValueError, match=r"\[batch, 10\]"):
        euler_accelerations(p[:, :9], road, H)
    with pytest.raises(ValueError, match="road"):
        euler_accelerations(p, road[:3], H)
