"""Forward-mode sensitivities of the Euler recursion: values and Jacobian (FD and autograd), each by the
compiled loop (estimation/_kernels.py, the default on the CPU in float64) and by the torch recursion."""

import sys

import pytest
import torch

from hybridqcm.estimation import _kernels
from hybridqcm.estimation.sensitivity import (
    EulerSensitivity,
    accelerations_and_jacobian,
    euler_accelerations,
    euler_sensitivities,
)
from hybridqcm.physics import reference_params, simulate
from hybridqcm.physics.integrators import SemiExplicitEuler
from hybridqcm.testing import synthetic_samples

H = 0.01


@pytest.fixture(params=["kernel", "torch"])
def path(request, monkeypatch):
    if request.param == "torch":
        monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    else:
        assert _kernels.applies(torch.zeros(1, 10, dtype=torch.float64))
    return request.param


@pytest.fixture(scope="module")
def samples():
    return synthetic_samples(6, n_steps=60, seed=3)


@pytest.mark.parametrize("scaled_road", [False, True])
@pytest.mark.parametrize("tangents, with_x0", [(True, False), (True, True), (False, False)])
def test_the_compiled_loop_equals_the_torch_recursion(scaled_road, tangents, with_x0, monkeypatch):
    """Every column, with an initial state, its tangents and the residual, far from the data's parameters."""
    assert _kernels.applies(torch.zeros(1, 10, dtype=torch.float64))
    g = torch.Generator().manual_seed(5)
    b, T = 40, 120
    params = reference_params().expand(b, 10) * (1 + 0.3 * torch.randn(b, 10, generator=g, dtype=torch.float64))
    road = 0.01 * torch.randn(b, T, generator=g, dtype=torch.float64).cumsum(1)
    x0 = 1e-2 * torch.randn(b, 6, generator=g, dtype=torch.float64)
    targets = torch.randn(b, T, 3, generator=g, dtype=torch.float64)
    run = (
        (lambda: euler_sensitivities(params, road, H, scaled_road, x0=x0, with_x0=with_x0, targets=targets))
        if tangents
        else (lambda: euler_accelerations(params, road, H, scaled_road, x0=x0)[..., None])
    )
    compiled = run()
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    reference = run()
    assert compiled.shape == reference.shape == (b, T, 3, (17 if with_x0 else 11) if tangents else 1)
    scale = reference.abs().amax(dim=(1, 2), keepdim=True)  # each sample's column scale
    assert ((compiled - reference).abs() <= 1e-11 * scale).all()


@pytest.mark.parametrize("scaled_road", [False, True])
def test_layer_matches_data_generator(path, samples, scaled_road):
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
def test_jacobian_matches_autograd(path, samples, scaled_road):
    p, road = samples["params"][:3], samples["road"][:3]
    _, jac = EulerSensitivity(H, scaled_road)(p, road)  # [batch, time, 3, 10]
    layer = SemiExplicitEuler(H, scaled_road=scaled_road)
    full = torch.autograd.functional.jacobian(lambda q: layer(q, road), p, vectorize=True)  # [b, T, 3, b, 10]
    reverse = torch.stack([full[i, :, :, i] for i in range(3)])
    scale = reverse.abs().amax()
    torch.testing.assert_close(jac, reverse, rtol=1e-9, atol=1e-12 * scale)


def test_jacobian_matches_finite_differences(path, samples):
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


def test_sensitivity_layout_and_validation(path, samples):
    p, road = samples["params"], samples["road"]
    out = euler_sensitivities(p, road, H)
    assert out.shape == (6, 60, 3, 11)
    with pytest.raises(ValueError, match=r"\[batch, 10\]"):
        euler_accelerations(p[:, :9], road, H)
    with pytest.raises(ValueError, match="road"):
        euler_accelerations(p, road[:3], H)


def test_where_numba_does_not_import_the_torch_recursion_runs(samples, monkeypatch):
    p, road = samples["params"], samples["road"]
    compiled = euler_sensitivities(p, road, H)
    monkeypatch.setattr(_kernels, "_numba_module", [])
    monkeypatch.setitem(sys.modules, "numba", None)  # `import numba` raises ImportError
    with pytest.warns(UserWarning, match="numba does not import"):
        assert not _kernels.applies(p)
    assert not _kernels.applies(p) and not _kernels.compiled_loops()  # decided once, warned once
    torch.testing.assert_close(euler_sensitivities(p, road, H), compiled, rtol=1e-11, atol=1e-14)


def test_without_a_writable_cache_the_loops_compile_in_the_process(samples, monkeypatch):
    """numba raises RuntimeError at decoration where no cache folder is writable (a read-only install, no home):
    the loop is compiled without the cache instead."""
    import numba

    def njit(**options):
        if options.get("cache"):
            raise RuntimeError("cannot cache function: no locator available")
        return numba.njit(**options)

    p, road = samples["params"], samples["road"]
    expected = euler_sensitivities(p, road, H)
    monkeypatch.setattr(_kernels, "_compiled", {})
    monkeypatch.setattr(_kernels, "_numba", lambda: type("fake", (), {"njit": staticmethod(njit)}))
    assert torch.equal(euler_sensitivities(p, road, H), expected)
    assert "_euler_loop" in _kernels._compiled


def test_the_loops_refuse_shapes_they_would_index_past():
    """numba does not check bounds: a mismatched shape is refused before the loop, in one line naming it."""
    b, T = 3, 8
    params, road = torch.ones(b, 10, dtype=torch.float64), torch.zeros(b, T, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^_kernels: targets must be \[3, 8, 3\], got \[3, 7, 3\]$"):
        _kernels.euler_recursion(params, road, H, False, 11, targets=torch.zeros(b, T - 1, 3, dtype=torch.float64))
    Z = torch.zeros(T, b, 2, 2, 1, dtype=torch.complex128)
    with pytest.raises(ValueError, match=r"^_kernels: rate must be \[3, 2, 2, 1\], got \[3, 2, 1\]$"):
        _kernels.modal_scan(Z, torch.zeros(b, 2, 1, dtype=torch.complex128), H)
    states = torch.zeros(T, 6, b, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^_kernels: forcing must be \[7, 6, 3\], got \[8, 6, 3\]$"):
        _kernels.linear_states(
            torch.zeros(6, 6, b, dtype=torch.float64), torch.zeros(T, 6, b, dtype=torch.float64), states
        )
