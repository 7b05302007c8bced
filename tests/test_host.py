"""estimation/_host.on_host: the host's share of a solve on another device. Sliced over threads, every sample's
result is the whole batch's bit for bit (the routines are per sample; at one torch thread), and the function's own new tensors are
made on the CPU even inside another device's default (the GPU solve runs under torch.device(gpu))."""

from __future__ import annotations

import pytest
import torch

from hybridqcm.estimation import _host
from hybridqcm.estimation._blas import torch_threads
from hybridqcm.estimation._modal import _eig
from hybridqcm.estimation.initial_state import _min_norm_lstsq


@pytest.fixture
def small_slices(monkeypatch):
    monkeypatch.setattr(_host, "_MIN_SLICE", 64)
    monkeypatch.setattr(_host, "available_cores", lambda: 3)


def test_eigen_decomposition_in_slices_is_the_whole_batchs(small_slices):
    g = torch.Generator().manual_seed(0)
    M = torch.randn(1000, 6, 6, generator=g, dtype=torch.float64)
    M[17] = float("nan") * M[17]  # a matrix LAPACK refuses: one not-converged sample in its slice only
    whole = _eig(M)
    sliced = _host.on_host(_eig, M, rows=True)
    assert not bool(whole[2][17]) and int((~whole[2]).sum()) == 1
    for a, b in zip(whole, sliced, strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)


def test_minimum_norm_least_squares_in_slices_is_the_whole_batchs(small_slices):
    g = torch.Generator().manual_seed(1)
    design = torch.randn(500, 120, 6, generator=g, dtype=torch.float64)
    design[:, :, 5] = design[:, :, 4]  # rank deficient: the cutoff's minimum-norm answer
    rhs = torch.randn(500, 120, generator=g, dtype=torch.float64)
    x = _host.on_host(lambda d, r: _min_norm_lstsq(d, r, 1e-10), design, rhs, rows=True)
    with torch_threads(1):  # the slices' threads run one torch thread each: the same reductions' order
        assert torch.equal(x, _min_norm_lstsq(design, rhs, 1e-10))
    assert torch.allclose(x[:, 4], x[:, 5])  # the dropped direction: equal shares, not an arbitrary split


def test_the_functions_new_tensors_are_on_the_host_inside_another_devices_default(small_slices):
    def shifted(x):
        return x + torch.ones(x.shape[1:], dtype=x.dtype)  # a factory without a device

    x = torch.arange(400.0).view(200, 2)
    with torch.device("meta"):  # stands for the GPU solve's default device
        with pytest.raises((RuntimeError, NotImplementedError)):
            shifted(x)  # what the function would meet without on_host's own default
        for rows in (False, True):
            out = _host.on_host(shifted, x, rows=rows)
            assert out.device.type == "cpu" and torch.equal(out, x + 1)
