"""bench/roofline.py's FLOP formulas against an independent count: the operations torch actually dispatches
while the layers run on a tiny batch (torch.utils.flop_counter.FlopCounterMode for the matrix products of
the Euler recursion and the Gram, and a dispatch-level counter of every product and elementwise op for the
exact layers, with the layers' numpy products routed through torch so that they are seen)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from hybridqcm.estimation import _expm, _modal, exact, hold
from hybridqcm.estimation.hold import held_input
from hybridqcm.estimation.problems import LeastSquaresProblem, ProblemEvaluation
from hybridqcm.estimation.sensitivity import euler_accelerations, euler_sensitivities
from hybridqcm.physics.linear_models import QuarterCarRoad
from hybridqcm.testing import synthetic_samples

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="module")
def roofline():
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("roofline", BENCH / "roofline.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCH))


# ops that move or view data (no arithmetic), and comparisons/selections whose cost the formulas leave out
_FREE = {
    "copy_", "fill_", "zero_", "zeros", "empty", "empty_like", "new_zeros", "view", "_unsafe_view", "t",
    "permute", "unsqueeze", "select", "slice", "expand", "as_strided", "clone", "transpose", "detach", "alias",
    "unbind", "index_put_", "_to_copy", "lift_fresh", "reshape", "contiguous", "split", "squeeze", "stack",
    "cat", "diagonal", "arange", "lift_fresh_copy", "index", "full", "eye", "new_empty", "empty_strided",
    "zeros_like", "ones_like", "view_as_real", "view_as_complex", "_reshape_alias", "unflatten", "flatten",
    "resolve_conj", "resolve_neg", "masked_fill", "_local_scalar_dense", "scalar_tensor", "where", "gather",
    "abs", "neg", "_conj", "eq", "ne", "lt", "le", "gt", "ge", "bitwise_and", "bitwise_and_", "all", "amax",
    "max", "sum", "sort", "ones", "full_like", "clamp_min", "exp", "exp2", "log2", "round", "rsub",
    "reciprocal", "cumprod", "linalg_eig", "linalg_inv_ex",
}  # fmt: skip


class DispatchCounter(TorchDispatchMode):
    """FLOPs of the dispatched ops: mm/bmm 2 M K N (x4 complex), add/sub 1 (2 with alpha; complex 2/4),
    mul/div 1 (complex 6/11), addcmul 2 (complex 8) per output element; any other op is recorded."""

    def __init__(self):
        super().__init__()
        self.flops = {"mm": 0, "elementwise": 0}
        self.unknown: set[str] = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = func.overloadpacket.__name__
        result = out[0] if isinstance(out, (tuple, list)) else out
        if not isinstance(result, torch.Tensor) or not (result.is_floating_point() or result.is_complex()):
            return out  # index arithmetic is no FLOP
        cx, n = result.is_complex(), result.numel()
        if name in ("mm", "bmm"):
            a, b = args[0], args[1]
            batch = a.shape[0] if name == "bmm" else 1
            self.flops["mm"] += 2 * batch * a.shape[-2] * a.shape[-1] * b.shape[-1] * (4 if cx else 1)
        elif name in ("add", "add_", "sub", "sub_"):
            alpha = kwargs.get("alpha", args[2] if len(args) > 2 else 1)
            self.flops["elementwise"] += n * (2 if cx else 1) * (1 if alpha == 1 else 2)
        elif name in ("mul", "mul_"):
            self.flops["elementwise"] += n * (6 if cx else 1)
        elif name in ("div", "div_"):
            self.flops["elementwise"] += n * (11 if cx else 1)
        elif name in ("addcmul", "addcmul_"):
            self.flops["elementwise"] += n * (8 if cx else 2)
        elif name not in _FREE:
            self.unknown.add(name)
        return out


@pytest.mark.parametrize("with_x0", [False, True])
def test_euler_recursion_flops_match_the_dispatched_ops(roofline, with_x0, monkeypatch):
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")  # the torch recursion (the compiled loop: the next test)
    b, T = 3, 7
    g = torch.Generator().manual_seed(0)
    params = 0.5 + torch.rand(b, 10, generator=g, dtype=torch.float64)
    road = torch.randn(b, T, generator=g, dtype=torch.float64)
    x0 = 1e-3 * torch.randn(b, 6, generator=g, dtype=torch.float64) if with_x0 else None
    width = 17 if with_x0 else 11
    for fn, w, tangents in (
        (lambda: euler_sensitivities(params, road, 0.01, x0=x0, with_x0=with_x0), width, True),
        (lambda: euler_accelerations(params, road, 0.01, x0=x0), 1, False),
    ):
        flop_counter, counter = FlopCounterMode(display=False), DispatchCounter()
        with flop_counter, counter:
            fn()
        expected = roofline.euler_recursion_flops(b, T, w, tangents)
        assert not counter.unknown
        assert flop_counter.get_total_flops() == expected["mm"]
        assert counter.flops == expected


class _Counted(float):
    """A float whose arithmetic counts its FLOPs (negation is free, as in the formulas)."""

    count = 0

    def _op(self, other, fn):
        _Counted.count += 1
        return _Counted(fn(float(self), float(other)))

    def __add__(self, o):
        return self._op(o, lambda a, b: a + b)

    def __radd__(self, o):
        return self._op(o, lambda a, b: b + a)

    def __sub__(self, o):
        return self._op(o, lambda a, b: a - b)

    def __rsub__(self, o):
        return self._op(o, lambda a, b: b - a)

    def __mul__(self, o):
        return self._op(o, lambda a, b: a * b)

    def __rmul__(self, o):
        return self._op(o, lambda a, b: b * a)

    def __neg__(self):
        return _Counted(-float(self))


@pytest.mark.parametrize("width, scaled", [(11, False), (17, False), (1, False), (11, True), (1, True)])
def test_euler_kernel_flops_match_its_counted_arithmetic(roofline, width, scaled):
    """The compiled loop's source run as Python on counting floats: the FLOPs of one more step (after the
    first, every operand is counted) equal euler_kernel_flops of one step."""
    import numpy as np

    from hybridqcm.estimation import _kernels

    b, tangents, with_x0 = 2, width > 1, width == 17

    def counted(shape, value):
        a = np.empty(shape, dtype=object)
        a.flat = [_Counted(value + 0.1 * i) for i in range(a.size)]
        return a

    def run(steps):
        _Counted.count = 0
        out = np.empty((b, steps, 3, width), dtype=object)
        state, accel = np.empty((7, width), dtype=object), np.empty((3, width), dtype=object)
        _kernels._euler_loop(counted((b, 10), 1.0), counted((b, steps), 0.01), 0.01, scaled, counted((b, 6), 0.0),
                            True, with_x0, counted((b, steps, 3), 0.0), False, state, accel, out)  # fmt: skip
        return _Counted.count

    assert run(6) - run(5) == roofline.euler_kernel_flops(b, 1, width, tangents, scaled)


def test_gram_flops_match_the_normal_equations(roofline, monkeypatch):
    """The Gram of (R | J) as the solver forms it (_blas.gram_matrix: one torch.matmul, its path on an Intel CPU;
    numpy's elsewhere, with the same FLOPs); the compiled Euler loop dispatches no product, so the Gram is all the
    counter sees."""
    from hybridqcm.estimation import _blas

    monkeypatch.setattr(_blas, "_GRAM_BY_TORCH", True)
    b, T = 4, 6
    data = synthetic_samples(b, n_steps=T, seed=3)
    problem = LeastSquaresProblem(data["accel"].to(torch.float64), data["road"].to(torch.float64), 0.01)
    evaluation = ProblemEvaluation(problem, chunk_size=b)
    flop_counter = FlopCounterMode(display=False)
    with flop_counter:
        evaluation.data_normal_equations(data["params"].to(torch.float64), torch.arange(b))
    assert flop_counter.get_total_flops() == roofline.gram_flops(b, 3 * T, 11)


def test_exact_layer_flops_match_the_dispatched_ops(roofline, monkeypatch):
    """Within 1 % for the step recursion and 8 % for the modal path (whose small setup ops are summarised);
    the LAPACK eigen-decomposition and inverse are estimates, left out of the comparison. The basis' scan in
    torch (the compiled loop's steps are counted by the same formula's plain branch)."""
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    for module in (exact, _modal, _expm, hold):
        monkeypatch.setattr(module, "_matmul", torch.matmul)
    model, b, T, M, margin = QuarterCarRoad(), 3, 40, 16, 2
    data = synthetic_samples(b, n_steps=T + 2 * margin, seed=0)
    params = data["params"].to(torch.float64)
    inputs = data["road"].to(torch.float64)[..., None]
    held = held_input(inputs, "spline", M, margin, T)  # prepared once per solve, as the solver does
    x0 = 1e-3 * torch.randn(b, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    squarings = roofline._squarings(params, 0.01, M)
    K = roofline._modes(model.matrices(params)[0])
    window = dict(start=margin, n_steps=T, held=held)
    for method, tolerance in (("recursion", 0.01), ("modal", 0.08)):
        for kind in ("sensitivities", "outputs"):
            counter = DispatchCounter()
            with counter:
                if kind == "sensitivities":
                    exact.exact_sensitivities(model, params, x0, inputs, 0.01, "spline", M, method=method, **window)
                else:
                    exact.exact_outputs(model, params, x0, inputs, 0.01, "spline", M, method=method, **window)
            formula = getattr(roofline, f"exact_{kind}_flops")(method, T, M, squarings, K=K, batch=b)
            if method == "modal":
                formula -= roofline._eig_flops()
            counted = sum(counter.flops.values())
            assert not counter.unknown, (method, kind, counter.unknown)
            assert abs(counted / (b * formula) - 1) < tolerance, (method, kind, counted, b * formula)


@pytest.mark.parametrize("threads", [1, 2])
def test_the_iterations_are_timed_and_counted_on_chunk_threads(roofline, threads):
    """time_iterations end to end on a small batch: every case timed and counted, the modal path's records
    (eigenvalues, fallback samples) matched to their own call where the chunk threads interleave them."""
    import argparse

    args = argparse.Namespace(samples=48, steps=12, margin=4, substeps=4, chunk=8, repeats=1)
    best, terms = roofline.time_iterations(args, threads)
    assert set(best) == set(terms) == {"euler", "euler x0", "exact recursion", "exact modal"}
    for name, term in terms.items():
        assert all(seconds > 0 for seconds in best.values())
        assert term["jacobian"]["flops"] > 0 and term["line_search"]["flops"] > 0, name
    assert terms["euler"]["jacobian"]["flops"] == roofline.euler_kernel_flops(48, 12, 11, True)


def test_product_flops_match_the_dispatched_products(roofline):
    """_product_flops (the --floor table's count of a batched product) against torch's own FLOP counter for real
    operands, broadcast included; a complex multiply-add is 8 real FLOPs, 4x a real one (2)."""
    for a_shape, b_shape in (((5, 7, 3), (5, 3, 4)), ((2, 5, 7, 3), (3, 6)), ((7, 3), (4, 3, 2))):
        a, b = torch.randn(a_shape, dtype=torch.float64), torch.randn(b_shape, dtype=torch.float64)
        counter = FlopCounterMode(display=False)
        with counter:
            torch.matmul(a, b)
        assert roofline._product_flops(a, b) == counter.get_total_flops()
    a, b = torch.randn(5, 7, 3, dtype=torch.complex128), torch.randn(5, 3, 4, dtype=torch.complex128)
    assert roofline._product_flops(a, b) == 5 * 7 * 4 * 3 * 8


def test_the_floor_is_the_sum_of_its_parts_and_leaves_no_wrapper_behind(roofline, capsys):
    """--floor end to end on a small batch: the library calls it times were seen inside the iteration, its floor is
    the products' FLOPs at the small-product rate plus the eigen-decompositions plus one trial row a sample (the
    products made within a trial row not counted again), and every function it wrapped is the original again
    afterwards."""
    import argparse

    import numpy as np

    from hybridqcm.estimation import _blas
    from hybridqcm.estimation.solver import GaussNewton

    originals = (np.linalg.eig, _blas.batched_matmul, _modal._matmul, exact._recursion_outputs, GaussNewton._iterate)
    threads = torch.get_num_threads()
    args = argparse.Namespace(samples=40, steps=20, margin=4, substeps=4, chunk=16, repeats=1, quick=True)
    best = roofline.floor(args)
    assert (np.linalg.eig, _blas.batched_matmul, _modal._matmul, exact._recursion_outputs, GaussNewton._iterate) == (
        originals
    )
    assert torch.get_num_threads() == threads
    for part in ("LAPACK eig", "modal basis products", "Gram of (R | J)", "trial outputs"):
        assert best[f"s:{part}"] > 0, part
    assert best["r:trial outputs"] >= 40  # each searching sample is tried at least once
    products = sum(v for k, v in best.items() if k.startswith("f:") and " within " not in k)  # not twice
    assert any(" within trial outputs" in k for k in best)  # the forcing's products: in the trial rows' time
    one_row = best["s:trial outputs"] / best["r:trial outputs"] * 40
    expected = best["s:LAPACK eig"] + one_row + products / 1e9 / best["rate"]
    assert best["floor"] == pytest.approx(expected, rel=1e-12)
    assert best["floor"] < best["seconds"]
    assert "the exact iteration's floor" in capsys.readouterr().out
