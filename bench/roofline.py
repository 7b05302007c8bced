"""Roofline of one Gauss-Newton iteration: FLOPs and bytes counted from the shapes, beside the machine's limits.

    PYTHONPATH=src /work/main/.venv/bin/python bench/roofline.py [--samples 17000] [--steps 100]
        [--threads 1 2] [--repeats 3] [--substeps 16] [--margin 8] [--chunk 512] [--quick]
    PYTHONPATH=src /work/main/.venv/bin/python bench/roofline.py --floor [--samples 17000] [--repeats 3]

``--floor``: where the exact model's iteration (x0 unknown, the modal Jacobian, one thread) spends its time in
the library calls no rewrite of this algorithm avoids, timed in place during the iteration: LAPACK's
eigen-decompositions (numpy.linalg.eig), the BLAS products (estimation/_blas.batched_matmul: the modal basis'
final and input products, the Gram of (R | J), the rest) with their FLOPs counted from the operands' shapes,
and the line search's outputs per evaluated row. Its floor: the eigen-decompositions as timed, the products
at the machine's batched small-product rate (the faster of torch.bmm and numpy of [B, 18, 18], measured in the
same run) and one trial row per sample at the measured cost of a row; everything else (the modal
coefficients, the scan, the step, the glue) counted as free. That floor beside the issue's target for the
iteration (0.33 x its 1.97 s at one thread).

Setup: bench/bench_exact.py's ``--gn`` cases (``gn_cases``: synthetic thesis-prior samples, start 10 % off
the reference vehicle, x0 unknown for the exact model, the Euler model from rest as there, and here also
the Euler model with x0 unknown, "euler x0", W = 17 columns like the exact model's), one GN
iteration of the solver (max_iterations=1, all samples active), timed as ``result.seconds[0]``, best of
--repeats, the cases alternating. The models' calls are recorded during the timed runs (batch sizes,
parameters, which samples the modal path left to the recursion; a list append per call) and the FLOPs
and bytes are counted afterwards from those shapes with the formulas below. In the same run, at the
same thread count: torch float64 GEMM (2048²), batched small float64 products ([B, 18, 18] @ [B, 18, 18],
torch.bmm and numpy's matmul, the path of estimation/_blas.batched_matmul) and a large memory copy
(512 MiB, read + write counted). Printed: achieved GFLOP/s and GB/s, their ratios to the limits,
arithmetic intensity I = FLOP/byte against the machine balance (GEMM GFLOP/s / copy GB/s) and which roof
the iteration sits under (memory if I < balance, else compute) with the fraction of that roof reached.

Notation: b samples of a call, T window steps, o = 3 outputs (a3, a2, a1), n = 6 states, m = 1 input,
P = 10 parameters, W columns of (prediction | J) (Euler from rest 11, exact with x0 17), M sub-steps per
interval (--substeps), N = n + 2m Van Loan size, s squarings of the exponential (per call, from the
parameters as estimation/_expm computes it), K propagated modes of the modal path (per call: n minus
the eigenvalues with Im > 0, the batch's largest). A multiply-add is 2 FLOPs, a complex multiply-add 8,
a complex product 6. FLOPs are the ones the code executes (dense products with their zero entries
included), per sample:

Euler recursion (estimation/sensitivity.py), per step with width W (W = 1 for the outputs):
    c = Coef x: [10, 7] @ [7, W] 140 W; p_j c_j 10 W; explicit slots 10 (tangents only);
    row sum [3, 10] @ [10, W] 60 W; v += h a, q += h v 12 W          -> T (222 W + 10 [tangents])
    The compiled loop that runs instead on the CPU in float64 (estimation/_kernels.py) does the
    non-zeros alone: a3 5, a2 11, a1 9 (7 with a scaled road: c9, c10 without u), v and q 12 per column;
    explicit terms 18 (16 scaled; tangents only), the scaled road's forcing 1
                                                          -> T (37 W + 18 [tangents]), scaled T (35 W + 16 + 1)
Normal equations (problems.data_normal_equations): Gram of (R | J) [oT, W]: 2 W² oT (all W² entries,
    numpy's matmul); residual column oT. Step (solver._step, pseudo_inverse_solve): Cholesky n_f³/3,
    solve 2 n_f², scaling 3 n_f² (n_f = W - 1 free entries; the eigen fallback is not counted).
Line search (problems.loss_at), per evaluated sample: the model's outputs plus residual and ½Σr² 3 oT.
Exact, Van Loan maps (_expm.van_loan_maps): a product S [r, k] T [k, c] with tangents dS [r', P, k],
    dT [k', P, c] costs r c (2k - 1) + r' P c (2k - 1) + 2 r' P c k' (without tangents the first term);
    the exponential takes 5 + s products with r = k = c = N, r' = k' = n (Paterson-Stockmeyer degree 11,
    s squarings), balancing ≈ 2 sweeps x 6 N², the Horner blocks' sums 19 N² (+ 15 n P N with
    tangents); the fold of the M sub-steps 1 product [n, n] [n, m] and
    M - 1 products [n, n] [n, n + 2m].
Exact outputs, recursion (exact._recursion_outputs): maps (no tangents); forcing 2 (T-1) M n m + 2 (T-1) n m;
    states 2 (T-1) n²; outputs T o (2 (n + m) - 1).
Exact outputs, modal (exact_outputs in torch for b <= 160 samples, _modal.modal_outputs): eigen-decomposition
    ≈ 25 n³ (real nonsymmetric, with vectors; Golub & Van Loan's estimate), complex inverse 8 n³
    (these two are LAPACK calls, estimated, not checked by tests/test_roofline.py), gamma, xi0, beta of
    the kept modes 8 (o n K + K n + K n m), the hold's weights ≈ 200 K + 44 (M+1) K, forcing of the psi
    channels [T, m(M+1)] @ [m(M+1), 2Km]: 2 T m (M+1) 2Km (e has none); recursion (T-1) 8 K (1+m) (blocked,
    about twice that, where a call's row is small: scan_flops);
    final [T, 2K(1+m) + m + m%2] @ [., o]: 2 T (2K(1+m) + m + m%2) o.
Exact sensitivities, modal (_modal.modal_sensitivities, the default): eigen-decomposition and inverse as
    above; V^-1 dA_j V 16 P n³ (two complex products); beta, gamma, xi0, beta''_j, Gam_j and their
    Sylvester corrections 8 (n² m + o n² + n² + P K n + 2 P K n m + 2 P o n K); S_j 11 P n² (complex
    division); the hold's weights as above; coefficients 6 (1+m) 2 K o W + 6 P o K (1+m);
    forcing of the (psi, chi) channels [T, m(M+1)] @ [m(M+1), 4Km]: 2 T m (M+1) 4Km; recursion (T-1) 20 K (1+m)
    (scan_flops, as above);
    final [T, 8K + m + m%2] @ [., o W]: 2 T (8K + m + m%2) o W. Samples the modal path leaves to the
    recursion (ok False) are counted again at the recursion's cost.
Exact sensitivities, recursion (exact._recursion_sensitivities): maps with tangents; forcing and states
    as for the outputs, primal outputs T o (2 (n + m) - 1); per step k >= 1 the tangents
    dx = dPhi x + Phi dx + sum_j dLam_j s_j: 2 n P (2n + (M+1) m), C dx 2 n o P, H = H Phi 2 o n²;
    explicit dC x + dE w 2 o P (n + m) per step.

Bytes: every tensor the code materialises per sample, in float64 element bytes (8 per number), written
once and read once by each consumer (a lower bound of the traffic: cache-line granularity, strided
column access and per-step temporaries in cache are not counted):
    Jacobian pass: (prediction | J) 8 T o W written; input 8 T (Euler) or the held input 8 m (M T + 1) (exact); modal: the
        forcing rows 2·8 T m (M+1), the basis buffer 2·8 T (8K + 2), the coefficients 2·8 (8K + 2) o W;
        recursion: forcing 2·8 (T-1) n, states 2·8 T n, primal 2·8 T o, explicit terms 2·8 o P T,
        maps' tangents 2·8 (n P n + (M+1) n P m).
    Normal equations: (R | J) read by the Gram 8 T o W, residual column read + written 2·8 T o, targets 8 T o.
    Line search, per evaluated sample: y written and read 2·8 T o, targets 8 T o, residual written and
        read 2·8 T o, the input as above; exact recursion: forcing and states as above; modal: forcing
        rows and basis buffer (width 2K(1+m) + 2) as above.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch

from hybridqcm.estimation import _kernels

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_exact  # noqa: E402  (the --gn setup: gn_cases)

N_STATE, N_IN, N_OUT, N_PARAMS = 6, 1, 3, 10
F64 = 8  # bytes per float64


# ----------------------------------------------------------------------------- FLOP and byte formulas
def euler_recursion_flops(batch: int, steps: int, width: int, tangents: bool) -> dict[str, int]:
    """The Euler recursion's FLOPs, split into its matrix products ("mm") and elementwise ops."""
    mm = steps * (2 * 10 * 7 * width + 2 * 3 * 10 * width)
    elementwise = steps * (10 * width + 12 * width + (10 if tangents else 0))
    return {"mm": batch * mm, "elementwise": batch * elementwise}


def euler_kernel_flops(batch: int, steps: int, width: int, tangents: bool, scaled: bool = False) -> int:
    """The compiled Euler loop's FLOPs (module docstring; a negation is no FLOP)."""
    per_step = (35 if scaled else 37) * width + ((16 if scaled else 18) if tangents else 0) + (1 if scaled else 0)
    return batch * steps * per_step


def gram_flops(batch: int, rows: int, width: int) -> int:
    """AᵀA of A [rows, width] per sample (all width² entries, as numpy's matmul computes them)."""
    return batch * 2 * width * width * rows


def normal_equations_bytes(steps: int, width: int, o=N_OUT) -> int:
    """Per sample: (R | J) read by the Gram, the residual column read + written, the targets read."""
    return F64 * (steps * o * width + 2 * steps * o + steps * o)


def step_flops(batch: int, n_free: int) -> int:
    return batch * (n_free**3 // 3 + 5 * n_free * n_free)


def _iprod(r: int, k: int, c: int, r_t: int = 0, n_dir: int = 0, k_t: int = 0) -> int:
    """S [r, k] T [k, c] with tangents dS [r_t, n_dir, k] and dT [k_t, n_dir, c] (_expm._iprod)."""
    return r * c * (2 * k - 1) + (r_t * n_dir * c * (2 * k - 1) + 2 * r_t * n_dir * c * k_t if n_dir else 0)


def van_loan_flops(substeps: int, squarings: int, tangents: bool, n=N_STATE, m=N_IN, P=N_PARAMS) -> int:
    """One sample's exponential of the Van Loan matrix and the fold of the sub-steps (per sample)."""
    N, nd = n + 2 * m, (P if tangents else 0)
    expm = (5 + squarings) * _iprod(N, N, N, n, nd, n) + 12 * N * N + 19 * N * N + 15 * n * nd * N
    fold = _iprod(n, n, m, n, nd, n) + (substeps - 1) * _iprod(n, n, n + 2 * m, n, nd, n)
    return expm + fold


def _eig_flops(n=N_STATE) -> int:
    """The eigen-decomposition and the inverse of the eigenvectors (LAPACK; an estimate)."""
    return 25 * n**3 + 8 * n**3


def _hold_weights_flops(K: int, substeps: int) -> int:
    """_modal._hold_weights: phi_1..3 by Horner (18 complex terms) and the M + 1 weights and their derivatives."""
    return 200 * K + 44 * (substeps + 1) * K


def scan_flops(steps: int, E: int, pair: bool, batch: int | None = None) -> int:
    """Per sample: _modal._scan over T = ``steps`` rows of E complex numbers a sample (``pair``: (z, dz) halves,
    each step also dz += h z), counted as the dispatched ops are. Blocked (L = isqrt(T), nb = T // L blocks)
    where the call's row, ``batch`` E, is at most _modal._SCAN_ROW; else (or ``batch`` None, or where the
    compiled loop runs, estimation/_kernels.py: the same steps) the plain steps (T - 1) (8 E, + 4 E/2 with
    pairs)."""
    from hybridqcm.estimation._modal import _SCAN_ROW

    T, half = steps, E // 2
    step = 8 * E + (4 * half if pair else 0)  # addcmul (complex 8), and dz += h z (complex add with alpha: 4)
    L = max(1, math.isqrt(T))
    nb = T // L if batch is not None and batch * E <= _SCAN_ROW and not _kernels.compiled_loops() else 0
    if nb < 2:
        return (T - 1) * step
    carry = 6 * E + 2 * E + (8 * half if pair else 0)  # mu^i c, its add, and (pairs) i h z's product and add
    full = nb * L
    return (
        (4 * (nb - 1) * half if pair else 0)  # the blocks' first rows: dz += h z
        + (L - 1) * nb * step  # within the blocks
        + 6 * L * E  # the powers' exponent, i rate
        + (nb - 1) * carry  # the blocks' ends
        + (nb - 1) * (L - 1) * carry  # every row's share
        + (T - full) * step  # the rows after the last block
    )


def exact_outputs_flops(
    method: str, steps, substeps, squarings=0, K=N_STATE, n=N_STATE, m=N_IN, o=N_OUT, batch: int | None = None
) -> int:
    """Per sample (``batch``: the call's samples, which decide _modal._scan's form; None: the plain steps)."""
    T, M = steps, substeps
    if method == "recursion":
        return (
            van_loan_flops(M, squarings, False)
            + 2 * (T - 1) * M * n * m
            + 2 * (T - 1) * n * m
            + 2 * (T - 1) * n * n
            + T * o * (2 * (n + m) - 1)
        )
    basis = 2 * K * (1 + m)
    setup = _eig_flops(n) + 8 * (o * n * K + K * n + K * n * m) + _hold_weights_flops(K, M)
    forcing = 2 * T * m * (M + 1) * 2 * K * m  # the psi channels' columns alone (e has no forcing)
    return setup + forcing + scan_flops(T, K * (1 + m), False, batch) + 2 * T * (basis + m + m % 2) * o


def exact_sensitivities_flops(
    method: str, steps, substeps, squarings=0, K=N_STATE, n=N_STATE, m=N_IN, o=N_OUT, P=N_PARAMS, batch=None
) -> int:
    """Per sample, x0 unknown (W = 1 + P + n columns); ``batch`` as for exact_outputs_flops."""
    T, M, W = steps, substeps, 1 + P + n
    if method == "recursion":
        primal = exact_outputs_flops("recursion", T, M, 0, n=n, m=m, o=o) - van_loan_flops(M, 0, False)
        per_step = 2 * n * P * (2 * n + (M + 1) * m) + 2 * n * o * P + 2 * o * n * n
        return van_loan_flops(M, squarings, True) + primal + (T - 1) * per_step + T * 2 * o * P * (n + m)
    basis = 4 * K * (1 + m)
    products = 16 * P * n**3 + 8 * (n * n * m + o * n * n + n * n + P * K * n + 2 * P * K * n * m + 2 * P * o * n * K)
    setup = (
        _eig_flops(n)
        + products
        + _hold_weights_flops(K, M)
        + 11 * P * n * n
        + 6 * (1 + m) * 2 * K * o * W
        + 6 * P * o * K * (1 + m)
    )
    forcing = 2 * T * m * (M + 1) * 4 * K * m  # the (psi, chi) channels' columns alone
    return setup + forcing + scan_flops(T, 2 * K * (1 + m), True, batch) + 2 * T * (basis + m + m % 2) * o * W


def jacobian_bytes(kind: str, steps, width, substeps=1, K=N_STATE, n=N_STATE, m=N_IN, o=N_OUT, P=N_PARAMS) -> int:
    """Per sample: a Jacobian chunk's tensors and the Gram's read (module docstring)."""
    T, M = steps, substeps
    common = F64 * T * o * width
    if kind == "euler":
        return common + F64 * T
    held = F64 * m * (M * T + 1)
    if kind == "modal":
        return common + held + F64 * (2 * T * m * (M + 1) + 2 * T * (8 * K + 2) + 2 * (8 * K + 2) * o * width)
    return (
        common
        + held
        + F64 * (2 * (T - 1) * n + 2 * T * n + 2 * T * o + 2 * o * P * T + 2 * (n * P * n + (M + 1) * n * P * m))
    )


def output_bytes(kind: str, steps, substeps=1, K=N_STATE, n=N_STATE, m=N_IN, o=N_OUT) -> int:
    """Per evaluated sample of the line search."""
    T, M = steps, substeps
    common = F64 * 5 * T * o
    if kind == "euler":
        return common + F64 * T
    held = F64 * m * (M * T + 1)
    if kind == "modal":
        return common + held + F64 * (2 * T * m * (M + 1) + 2 * T * (2 * K * (1 + m) + 2))
    return common + held + F64 * (2 * (T - 1) * n + 2 * T * n)


# ----------------------------------------------------------------------------- what the models were asked
class Recorder:
    """Wraps the response layers' entry points (module attributes the response models and exact.py look
    up at call time) and records each call's kind, method, batch, window length and parameters."""

    def __init__(self):
        self.calls: list[dict] = []
        self._saved: list[tuple] = []
        self._local = threading.local()

    def _wrap(self, module, name, kind, method=None):
        original = getattr(module, name)
        calls, local = self.calls, self._local

        def wrapper(*args, **kwargs):
            if kind in ("modal_sens", "modal_out"):
                out, ok = original(*args, **kwargs)
                current = local.record  # this thread's call (the chunk threads interleave their records)
                current["n_bad"] = int((~ok).sum())
                current["A"] = args[0][0]
                return out, ok
            params = args[0] if kind.startswith("euler") else args[1]
            record = {"kind": kind, "batch": params.shape[0], "params": params[:, :N_PARAMS].clone()}
            record["method"] = kwargs.get("method", getattr(original, "keywords", {}).get("method", method))
            record["kernel"] = kind.startswith("euler") and _kernels.applies(params)
            calls.append(record)
            local.record = record
            result = original(*args, **kwargs)
            out = result[0] if isinstance(result, tuple) else result  # (out, fallback rows) with defer_fallback
            record["steps"] = out.shape[1]
            record["width"] = out.shape[-1] if out.ndim == 4 else 1
            return result

        self._saved.append((module, name, original))
        setattr(module, name, wrapper)

    def __enter__(self):
        import hybridqcm.estimation.exact as exact
        import hybridqcm.estimation.response as response

        self._wrap(response, "euler_sensitivities", "euler_sens")
        self._wrap(response, "euler_accelerations", "euler_out")
        self._wrap(response, "exact_sensitivities", "exact_sens", "modal")
        self._wrap(response, "exact_outputs", "exact_out", "auto")
        self._wrap(exact, "modal_sensitivities", "modal_sens")
        self._wrap(exact, "modal_outputs", "modal_out")
        return self

    def __exit__(self, *exc):
        for module, name, original in reversed(self._saved):
            setattr(module, name, original)
        self._saved.clear()


def _squarings(params: torch.Tensor, h: float, substeps: int) -> int:
    """s of _expm._expm_inner for this batch (the same balanced norm)."""
    from hybridqcm.estimation._expm import _TAYLOR_THETA, _van_loan, balance
    from hybridqcm.physics.linear_models import QuarterCarRoad

    A, B, _, _ = QuarterCarRoad().matrices(params)
    M = _van_loan(A, B, h / substeps).permute(2, 0, 1)
    d = balance(M)
    norm = float((M * (d[:, None, :] / d[:, :, None])).abs().sum(1).amax())
    return max(0, math.ceil(math.log2(norm / _TAYLOR_THETA))) if norm > _TAYLOR_THETA else 0


def _modes(A: torch.Tensor) -> int:
    lam = torch.linalg.eigvals(A)
    return int((A.shape[-1] - (lam.imag > 0).sum(1)).max())


def _euler_flops(call: dict, tangents: bool) -> int:
    """A recorded Euler call's FLOPs: the compiled loop's where it ran, else the torch recursion's."""
    b, T, W = call["batch"], call["steps"], call["width"]
    if call["kernel"]:
        return euler_kernel_flops(b, T, W, tangents)
    return sum(euler_recursion_flops(b, T, W, tangents).values())


def count(calls: list[dict], substeps: int, h: float = 0.01, n_obs: int = N_OUT) -> dict[str, dict[str, float]]:
    """{term: {"flops", "bytes"}} of the recorded calls of one iteration (terms: jacobian, normal_equations,
    step, line_search)."""
    terms = {t: {"flops": 0.0, "bytes": 0.0} for t in ("jacobian", "normal_equations", "step", "line_search")}
    for c in calls:
        b, T, W = c["batch"], c["steps"], c["width"]
        if c["kind"] in ("euler_sens", "exact_sens"):
            rows = T * n_obs
            terms["normal_equations"]["flops"] += gram_flops(b, rows, W) + b * rows
            terms["normal_equations"]["bytes"] += b * normal_equations_bytes(T, W, n_obs)
            terms["step"]["flops"] += step_flops(b, W - 1)
        if c["kind"] == "euler_sens":
            terms["jacobian"]["flops"] += _euler_flops(c, True)
            terms["jacobian"]["bytes"] += b * jacobian_bytes("euler", T, W)
        elif c["kind"] == "euler_out":
            terms["line_search"]["flops"] += _euler_flops(c, False) + 3 * b * T * n_obs
            terms["line_search"]["bytes"] += b * output_bytes("euler", T)
        elif c["kind"] == "exact_sens":
            bad = c.get("n_bad", b) if c["method"] == "modal" else b
            if c["method"] == "modal":
                K = _modes(c["A"])
                terms["jacobian"]["flops"] += b * exact_sensitivities_flops("modal", T, substeps, K=K, batch=b)
                terms["jacobian"]["bytes"] += b * jacobian_bytes("modal", T, W, substeps, K=K)
            if bad:
                s = _squarings(c["params"], h, substeps)
                terms["jacobian"]["flops"] += bad * exact_sensitivities_flops("recursion", T, substeps, s)
                terms["jacobian"]["bytes"] += bad * jacobian_bytes("recursion", T, W, substeps)
        elif c["kind"] == "exact_out":
            modal = "A" in c
            bad = c.get("n_bad", b) if modal else b
            if modal:
                K = _modes(c["A"])
                terms["line_search"]["flops"] += b * exact_outputs_flops("modal", T, substeps, K=K, batch=b)
                terms["line_search"]["bytes"] += b * output_bytes("modal", T, substeps, K=K)
            if bad:
                s = _squarings(c["params"], h, substeps)
                terms["line_search"]["flops"] += bad * exact_outputs_flops("recursion", T, substeps, s)
                terms["line_search"]["bytes"] += bad * output_bytes("recursion", T, substeps)
            terms["line_search"]["flops"] += 3 * b * T * n_obs
    return terms


# ----------------------------------------------------------------------------- the machine's limits
def _best(fn, repeats: int, min_seconds: float = 0.2) -> float:
    """Best seconds per call of fn over repeats rounds, each long enough to time."""
    fn()
    best = math.inf
    for _ in range(repeats):
        calls, t0 = 0, time.perf_counter()
        while True:
            fn()
            calls += 1
            elapsed = time.perf_counter() - t0
            if elapsed >= min_seconds:
                break
        best = min(best, elapsed / calls)
    return best


def machine_limits(quick: bool, repeats: int) -> dict[str, float]:
    """GEMM GFLOP/s (2048², float64), batched [B, 18, 18] products (torch.bmm, numpy matmul) GFLOP/s and
    a large copy's GB/s (read + write), at torch's current thread count."""
    g = torch.Generator().manual_seed(0)
    n = 512 if quick else 2048
    a, b = (torch.randn(n, n, generator=g, dtype=torch.float64) for _ in range(2))
    gemm = 2 * n**3 / _best(lambda: torch.mm(a, b), repeats) / 1e9
    B = 4096
    x, y = (torch.randn(B, 18, 18, generator=g, dtype=torch.float64) for _ in range(2))
    out = torch.empty(B, 18, 18, dtype=torch.float64)
    small_torch = 2 * 18**3 * B / _best(lambda: torch.bmm(x, y, out=out), repeats) / 1e9
    xn, yn, on = x.numpy(), y.numpy(), out.numpy()
    small_numpy = 2 * 18**3 * B / _best(lambda: np.matmul(xn, yn, out=on), repeats) / 1e9
    size = (16 if quick else 512) * 2**20 // F64
    src = torch.rand(size, generator=g, dtype=torch.float64)
    dst = torch.empty_like(src)
    copy = 2 * size * F64 / _best(lambda: dst.copy_(src), repeats) / 1e9
    return {"gemm": gemm, "gemm_n": n, "bmm18": small_torch, "np18": small_numpy, "copy": copy}


# ----------------------------------------------------------------------------- the iteration
def _mark(boundary: list, calls: list, *_) -> None:
    boundary.append(len(calls))


def time_iterations(args, threads: int) -> tuple[dict[str, float], dict[str, dict]]:
    """Best seconds of one GN iteration per case, and the counted terms of each (recorded in the timed runs)."""
    import hybridqcm.estimation.response as response
    from hybridqcm.estimation.exact import exact_sensitivities
    from hybridqcm.estimation.problems import LeastSquaresProblem
    from hybridqcm.estimation.response import EulerResponse
    from hybridqcm.estimation.solver import GaussNewton, SolverConfig

    gn_args = argparse.Namespace(
        samples=args.samples, steps=args.steps, margin=args.margin, hold="spline", substeps=args.substeps
    )
    cases = bench_exact.gn_cases(gn_args)
    # the Euler model with x0 unknown too (θ = p, x0: the exact model's 17 columns), beside bench_exact's from rest
    problem, init = cases["euler"]
    euler_x0 = EulerResponse(0.01, initial_state="unknown")
    theta0 = torch.cat([init, torch.zeros(init.shape[0], 6, dtype=torch.float64)], 1)
    cases = {
        "euler": cases["euler"],
        "euler x0": (LeastSquaresProblem(problem.targets, problem.inputs, 0.01, model=euler_x0), theta0),
        **{k: v for k, v in cases.items() if k != "euler"},
    }
    solver = GaussNewton(SolverConfig(max_iterations=1, num_threads=threads, chunk_size=args.chunk))
    original = response.exact_sensitivities
    best: dict[str, float] = {}
    terms: dict[str, dict] = {}
    try:
        for _ in range(args.repeats):
            for name, (problem, start) in cases.items():
                method = "recursion" if "recursion" in name else "modal"
                response.exact_sensitivities = functools.partial(exact_sensitivities, method=method)
                boundary = []  # the callback runs after the iteration's timing: calls after it are the final report's
                with Recorder() as recorder:
                    result = solver.solve(problem, start, functools.partial(_mark, boundary, recorder.calls))
                best[name] = min(best.get(name, math.inf), result.seconds[0])
                if name not in terms:
                    kept = recorder.calls[: boundary[0]]
                    terms[name] = count(kept, args.substeps)
    finally:
        response.exact_sensitivities = original
    return best, terms


def _row(label, seconds, flops, nbytes, limits) -> str:
    gflops, gbs = flops / seconds / 1e9, nbytes / seconds / 1e9
    intensity = flops / nbytes
    balance = limits["gemm"] / limits["copy"]
    small = max(limits["bmm18"], limits["np18"])
    if intensity < balance:
        bound, roof = "memory", intensity * limits["copy"]
    else:
        bound, roof = "compute", limits["gemm"]
    ratios = {"GEMM": gflops / limits["gemm"], "small": gflops / small, "copy": gbs / limits["copy"]}
    nearest = max(ratios, key=ratios.get)
    return (
        f"| {label} | {seconds:.3f} | {flops / 1e9:.2f} | {nbytes / 1e6:.0f} | {gflops:.2f} | "
        f"{ratios['GEMM']:.3f} | {ratios['small']:.3f} | {gbs:.2f} | {ratios['copy']:.3f} | "
        f"{intensity:.1f} | {bound} | {gflops / roof:.3f} | {nearest} |"
    )


# ----------------------------------------------------------------------------- the floor of the exact iteration
class _Clock:
    """Seconds and counts of wrapped library calls (module attributes looked up at call time), by label; a call
    made inside a call wrapped with ``encloses`` is labelled "<label> within <outer label>" (one thread)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.flops: dict[str, float] = {}
        self.rows: dict[str, int] = {}
        self._saved: list[tuple] = []
        self._inside: list[str] = []

    def wrap(self, module, name, label_of, flops_of=None, rows_of=None, encloses=False):
        original = getattr(module, name)

        def wrapper(*args, **kwargs):
            label = label_of(*args)
            if self._inside:
                label = f"{label} within {self._inside[-1]}"
            if encloses:
                self._inside.append(label)
            t0 = time.perf_counter()
            try:
                result = original(*args, **kwargs)
            finally:
                if encloses:
                    self._inside.pop()
            self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - t0
            if flops_of is not None:
                self.flops[label] = self.flops.get(label, 0.0) + flops_of(*args)
            if rows_of is not None:
                self.rows[label] = self.rows.get(label, 0) + rows_of(*args)
            return result

        self._saved.append((module, name, original))
        setattr(module, name, wrapper)

    def clear(self):
        self.seconds.clear(), self.flops.clear(), self.rows.clear()

    def restore(self):
        for module, name, original in reversed(self._saved):
            setattr(module, name, original)


def _product_flops(a, b, *_) -> float:
    """2 m k n per matrix of a [..., m, k] @ b [..., k, n] (broadcast), x 4 for complex operands."""
    batch = math.prod(torch.broadcast_shapes(a.shape[:-2], b.shape[:-2]))
    scale = 4 if a.is_complex() or b.is_complex() else 1
    return 2.0 * scale * batch * a.shape[-2] * a.shape[-1] * b.shape[-1]


def _product_label(module_name: str, steps: int):
    """What a product of ``module_name`` is: the Gram (the only caller of _blas's own batched_matmul), the modal
    basis' products (rows = window steps: the input product and the final one), or another (the maps, forcing)."""

    def label(a, b, *_):
        if module_name == "_blas":
            return "Gram of (R | J)"
        if module_name == "_modal" and a.shape[-2] in (steps, steps - 1):
            return "modal basis products"
        return f"other products ({module_name})"

    return label


def floor(args) -> dict:
    """The --floor table (module docstring); returns the best iteration's clocks ("seconds", "s:<part>", "f:<part>"
    FLOPs, "r:<part>" rows), its "floor" and the small-product "rate" (GFLOP/s) it used."""
    import hybridqcm.estimation._blas as blas
    import hybridqcm.estimation._expm as expm
    import hybridqcm.estimation._modal as modal
    import hybridqcm.estimation.exact as exact
    import hybridqcm.estimation.hold as hold
    from hybridqcm.estimation.problems import ProblemEvaluation
    from hybridqcm.estimation.solver import GaussNewton, SolverConfig

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    limits = machine_limits(args.quick, args.repeats)
    small = max(limits["bmm18"], limits["np18"])
    gn_args = argparse.Namespace(
        samples=args.samples, steps=args.steps, margin=args.margin, hold="spline", substeps=args.substeps
    )
    problem, start = bench_exact.gn_cases(gn_args)["exact modal"]
    clock = _Clock()
    in_iteration: dict = {}
    original_iterate = GaussNewton._iterate

    def iterate(self, *a, **k):  # the clocks of the iteration alone (not the start's or the final report's)
        clock.clear()
        t0 = time.perf_counter()
        result = original_iterate(self, *a, **k)
        in_iteration.update(seconds=time.perf_counter() - t0, **{f"s:{k}": v for k, v in clock.seconds.items()})
        in_iteration.update(
            {f"f:{k}": v for k, v in clock.flops.items()}, **{f"r:{k}": v for k, v in clock.rows.items()}
        )
        return result

    clock.wrap(np.linalg, "eig", lambda values: "LAPACK eig")
    for module in (blas, modal, hold, exact, expm):
        name = "batched_matmul" if module is blas else "_matmul"
        clock.wrap(module, name, _product_label(module.__name__.rsplit(".", 1)[1], args.steps), _product_flops)
    clock.wrap(exact, "_recursion_outputs", lambda *a: "trial outputs", rows_of=lambda *a: a[1].shape[0], encloses=True)
    clock.wrap(ProblemEvaluation, "data_normal_equations", lambda *a: "Jacobian pass")
    clock.wrap(GaussNewton, "_line_search", lambda *a: "line search")
    GaussNewton._iterate = iterate
    best: dict = {}
    try:
        solver = GaussNewton(SolverConfig(max_iterations=1, num_threads=1, chunk_size=args.chunk))
        for _ in range(args.repeats):
            solver.solve(problem, start)
            if in_iteration["seconds"] < best.get("seconds", math.inf):
                best = dict(in_iteration)
    finally:
        GaussNewton._iterate = original_iterate
        clock.restore()
        torch.set_num_threads(before)
    n = args.samples
    print(
        f"\nthe exact iteration's floor: {n} samples x {args.steps} steps, x0 unknown, modal Jacobian, 1 thread, "
        f"chunk {args.chunk}; the iteration of the best of {args.repeats} (wrapped calls timed in place)"
    )
    print(f"batched small products: torch.bmm {limits['bmm18']:.2f} / numpy {limits['np18']:.2f} GFLOP/s ([B, 18, 18])")
    print("\n| part | s in the iteration | GFLOP | GFLOP/s | at the small-product rate, s | in the floor, s |")
    print("|---|---|---|---|---|---|")
    total_floor = 0.0
    labels = sorted({k[2:] for k in best if k.startswith("s:")}, key=lambda k: -best[f"s:{k}"])
    for label in labels:
        seconds = best[f"s:{label}"]
        flops = best.get(f"f:{label}")
        if label in ("Jacobian pass", "line search") or " within " in label:  # in other rows' time already
            print(f"| {label}{' (all of it)' if ' within ' not in label else ''} | {seconds:.3f} | | | | |")
            continue
        if flops is not None:
            at_rate = flops / 1e9 / small
            total_floor += at_rate
            print(
                f"| {label} | {seconds:.3f} | {flops / 1e9:.2f} | {flops / 1e9 / seconds:.1f} | {at_rate:.3f} | {at_rate:.3f} |"
            )
        elif label == "trial outputs":
            rows = best[f"r:{label}"]
            one_row = seconds / rows * n
            total_floor += one_row
            print(
                f"| {label}: {rows} rows, {seconds / rows * 1e6:.1f} µs a row | {seconds:.3f} | | | | {one_row:.3f} (one row a sample) |"
            )
        else:
            total_floor += seconds
            print(f"| {label} | {seconds:.3f} | | | | {seconds:.3f} |")
    print(f"| **the iteration** | **{best['seconds']:.3f}** | | | | **{total_floor:.3f}** |")
    best.update(floor=total_floor, rate=small)
    print(
        f"\nfloor {total_floor:.3f} s = {total_floor / best['seconds']:.2f} x this iteration; the issue's target "
        f"0.33 x 1.97 s = 0.650 s (its tree's iteration on that day's machine) is {0.650 / total_floor:.2f} x the floor"
    )
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=17000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--threads", type=int, nargs="+", default=[1], help="thread counts, e.g. --threads 1 2")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--substeps", type=int, default=16)
    parser.add_argument("--margin", type=int, default=8)
    parser.add_argument("--chunk", type=int, default=512)
    parser.add_argument("--quick", action="store_true", help="small sizes (300 samples, small limits): a smoke run")
    parser.add_argument("--floor", action="store_true", help="the exact iteration's floor (module docstring)")
    args = parser.parse_args()
    if args.quick:
        args.samples, args.repeats = min(args.samples, 300), 1
    if args.floor:
        floor(args)
        return
    before = torch.get_num_threads()
    for threads in args.threads:
        load = ", ".join(f"{x:.2f}" for x in os.getloadavg())  # a shared machine: say how busy it was
        print(f"\nload average before the {threads}-thread run: {load} ({os.cpu_count()} CPUs)")
        torch.set_num_threads(threads)
        limits = machine_limits(args.quick, args.repeats)
        best, terms = time_iterations(args, threads)
        torch.set_num_threads(before)
        balance = limits["gemm"] / limits["copy"]
        print(
            f"\n{threads} thread(s): one GN iteration, {args.samples} samples x {args.steps} steps, margin {args.margin}, "
            f"spline hold, {args.substeps} sub-steps, chunk {args.chunk}, best of {args.repeats}"
        )
        print(
            f"limits: GEMM {limits['gemm_n']}² {limits['gemm']:.1f} GFLOP/s, batched 18x18 torch.bmm {limits['bmm18']:.2f} / "
            f"numpy {limits['np18']:.2f} GFLOP/s, copy {limits['copy']:.1f} GB/s; "
            f"balance {balance:.1f} FLOP/byte (GEMM / copy)"
        )
        print(
            "\n| case | s | GFLOP | MB | GFLOP/s | / GEMM | / small | GB/s | / copy | FLOP/byte | roof | / roof "
            "| nearest |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for name, seconds in best.items():
            t = terms[name]
            flops = sum(v["flops"] for v in t.values())
            nbytes = sum(v["bytes"] for v in t.values())
            print(_row(name, seconds, flops, nbytes, limits))
        print("\nterms (GFLOP / MB):")
        for name, t in terms.items():
            parts = ", ".join(f"{k} {v['flops'] / 1e9:.3f} / {v['bytes'] / 1e6:.0f}" for k, v in t.items())
            print(f"  {name}: {parts}")


if __name__ == "__main__":
    main()
