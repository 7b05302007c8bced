"""Compiled loops (numba) for the estimation layers' recursions, on the CPU: the Euler recursion with its
tangents, the modal basis' scan and the exact model's state recursion.

Why: in torch each step of these recursions is a few small ops over the whole batch, each bound by its own
dispatch and a pass over the chunk's memory (sensitivity.py: ~8 ops a step; _modal._scan and
exact._primal_states: one or two per step and state, where the occupant selection's calls hold 1-16
recordings). Here the loops run over one sample's (or one row's) values with the previous step in cache.
Each loop is the torch code's arithmetic, step by step; the results agree with it to rounding (fused
multiply-adds and summation orders differ), checked in tests/test_sensitivity.py and tests/test_exact.py
against the torch paths. The loops release the GIL, so the solver's chunk threads (SolverConfig.thread_chunks)
run them on several cores at once. They compile at the first call (about a second each) into numba's cache
beside this file, which later processes load.

``HYBRIDQCM_KERNELS=torch`` in the environment turns them off (the torch code everywhere); where numba is
absent or does not import the torch code runs as well, with one warning.

The Euler recursion (sensitivity.py's convention): one sample's state (v3, v2, v1, q3, q2, q1, u) x (primal,
tangents), [7, width], stays in L1 for all of its steps; c_j from the state, the sums of p_j c_j into
(a3, a2, a1) written on their non-zeros, the explicit terms ∂a/∂p_j += c_j (primal) on the tangent columns
(after the row's sum here, before it in torch), then v += h a, q += h v, and the residual a - targets on the
primal column after the update; each step's [3, width] block goes straight into the sample's contiguous rows
of the output [batch, time, 3, width].
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import torch
from torch import Tensor

N_PARAMS = 10
_compiled: dict[str, object] = {}
_numba_module: list = []  # [numba] once imported, [None] where it cannot be


def _numba():
    """numba, imported at the first use (0.25 s: not on every start of the console scripts); None where it is
    absent or does not import (a platform without its wheels): the torch code runs, with one warning."""
    if not _numba_module:
        try:
            import numba
        except Exception as error:  # noqa: BLE001 - any failure to import means: no compiled loops
            numba = None
            warnings.warn(f"hybridqcm: numba does not import ({error}); the slower torch recursions run", stacklevel=3)
        _numba_module.append(numba)
    return _numba_module[0]


def applies(tensor: Tensor) -> bool:
    """Whether the loops run for this tensor: on the CPU in float64 or complex128, not turned off, numba present."""
    return (
        tensor.device.type == "cpu"
        and tensor.dtype in (torch.float64, torch.complex128)
        and os.environ.get("HYBRIDQCM_KERNELS", "") != "torch"
        and _numba() is not None
    )


def compiled_loops() -> bool:
    """Whether this process's CPU solves in float64 run the compiled loops (what a run's summary.json records)."""
    return applies(torch.zeros(1, dtype=torch.float64))


def _kernel(name: str):
    if name not in _compiled:
        njit = _numba().njit
        try:
            _compiled[name] = njit(nogil=True, cache=True)(globals()[name])
        except RuntimeError:  # no writable cache beside the module nor in the user's: compile in each process
            _compiled[name] = njit(nogil=True)(globals()[name])
    return _compiled[name]


def _numpy(t: Tensor) -> np.ndarray:
    return t.detach().to(torch.float64).contiguous().numpy()


def _euler_loop(params, road, h, scaled, x0, has_x0, with_x0, targets, has_targets, state, accel, out):
    """params [b, 10], road [b, T], x0 [b, 6] (read where has_x0), targets [b, T, 3] (where has_targets);
    scratch state [7, W], accel [3, W]; writes out [b, T, 3, W]."""
    batch, n_steps = road.shape
    width = out.shape[3]
    for s in range(batch):
        for i in range(7):
            for w in range(width):
                state[i, w] = 0.0
        if has_x0:
            for i in range(6):
                state[i, 0] = x0[s, i]
        if with_x0:  # ∂x_0/∂x0_i = e_i
            for i in range(6):
                state[i, N_PARAMS + 1 + i] = 1.0
        p1, p2, p3, p4, p5 = params[s, 0], params[s, 1], params[s, 2], params[s, 3], params[s, 4]
        p6, p7, p8, p9, p10 = params[s, 5], params[s, 6], params[s, 7], params[s, 8], params[s, 9]
        for k in range(n_steps):
            state[6, 0] = road[s, k]
            for w in range(width):
                v3 = state[0, w]
                v2 = state[1, w]
                v1 = state[2, w]
                q3 = state[3, w]
                q2 = state[4, w]
                q1 = state[5, w]
                u = state[6, w]
                c9 = q2 if scaled else q2 - u
                c10 = -q1 if scaled else u - q1
                accel[0, w] = p1 * (v2 - v3) + p2 * (q2 - q3)
                accel[1, w] = p3 * (v3 - v2) + p4 * (v1 - v2) + p5 * (q3 - q2) + p6 * (q1 - q2)
                accel[2, w] = p7 * v2 + p8 * -v1 + p9 * c9 + p10 * c10
            if width > 1:  # the explicit terms ∂a/∂p_j += c_j of the primal, on column j
                accel[0, 1] += state[1, 0] - state[0, 0]
                accel[0, 2] += state[4, 0] - state[3, 0]
                accel[1, 3] += state[0, 0] - state[1, 0]
                accel[1, 4] += state[2, 0] - state[1, 0]
                accel[1, 5] += state[3, 0] - state[4, 0]
                accel[1, 6] += state[5, 0] - state[4, 0]
                accel[2, 7] += state[1, 0]
                accel[2, 8] += -state[2, 0]
                accel[2, 9] += state[4, 0] if scaled else state[4, 0] - state[6, 0]
                accel[2, 10] += -state[5, 0] if scaled else state[6, 0] - state[5, 0]
            if scaled:
                accel[2, 0] += road[s, k]
            for w in range(width):
                for r in range(3):
                    state[r, w] += h * accel[r, w]
                for r in range(3):
                    state[3 + r, w] += h * state[r, w]
            if has_targets:  # the residual on the primal column, after the update (sensitivity.py)
                for r in range(3):
                    accel[r, 0] -= targets[s, k, r]
            for r in range(3):
                for w in range(width):
                    out[s, k, r, w] = accel[r, w]


def _scan_loop(Z, mu, h, n_slot):
    """In place over Z [T, b, R] complex (rows may be strided), mu [b, R]: Z[k] <- mu Z[k - 1] + Z[k]; with
    n_slot K > 0 each row is R = groups x (z | dz) x K and dz[k] += h z[k] follows each step."""
    n_steps, batch, width = Z.shape
    for k in range(1, n_steps):
        for b in range(batch):
            for i in range(width):
                Z[k, b, i] += mu[b, i] * Z[k - 1, b, i]
            if n_slot > 0:
                for g in range(width // (2 * n_slot)):
                    for s in range(n_slot):
                        Z[k, b, (2 * g + 1) * n_slot + s] += h * Z[k, b, 2 * g * n_slot + s]


def _states_loop(phi, forcing, states):
    """In place over states [T, n, b] (states[0] set): x_(k+1) = Phi x_k + F_k, phi [n, n, b], forcing [T-1, n, b]."""
    n_steps, n, batch = states.shape
    for k in range(n_steps - 1):
        for i in range(n):
            for b in range(batch):
                states[k + 1, i, b] = forcing[k, i, b]
            for j in range(n):
                for b in range(batch):
                    states[k + 1, i, b] += phi[i, j, b] * states[k, j, b]


def _check(name: str, got, want) -> None:
    """The loops index without bounds checks (numba's default): a shape that does not match is refused here."""
    if tuple(got) != tuple(want):
        raise ValueError(f"_kernels: {name} must be {list(want)}, got {list(got)}")


def linear_states(phi: Tensor, forcing: Tensor, states: Tensor) -> None:
    """exact._primal_states' recursion in place over states [T, n, b] (contiguous, states[0] set)."""
    n_steps, n, batch = states.shape
    _check("phi", phi.shape, (n, n, batch))
    _check("forcing", forcing.shape, (n_steps - 1, n, batch))
    _kernel("_states_loop")(_numpy(phi), _numpy(forcing), states.numpy())


def euler_recursion(
    params: Tensor,
    road: Tensor,
    h: float,
    scaled_road: bool,
    width: int,
    x0: Tensor | None = None,
    with_x0: bool = False,
    targets: Tensor | None = None,
) -> Tensor:
    """sensitivity._recursion's result [batch, time, 3, width] (inputs validated there)."""
    batch, n_steps = road.shape
    _check("params", params.shape, (batch, N_PARAMS))
    if x0 is not None:
        _check("x0", x0.shape, (batch, 6))
    if targets is not None:
        _check("targets", targets.shape, (batch, n_steps, 3))
    x = np.zeros((1, 6)) if x0 is None else _numpy(x0)
    t = np.zeros((1, 1, 3)) if targets is None else _numpy(targets)
    out = np.empty((batch, n_steps, 3, width))
    state, accel = np.empty((7, width)), np.empty((3, width))
    _kernel("_euler_loop")(
        _numpy(params), _numpy(road), float(h), bool(scaled_road), x, x0 is not None, bool(with_x0), t,
        targets is not None, state, accel, out,
    )  # fmt: skip
    return torch.from_numpy(out)


def modal_scan(Z: Tensor, rate: Tensor, h: float | None) -> None:
    """_modal._scan in place: Z [T, b, *rest] complex128 (a view of the basis buffer), rate [b, *rest] (with
    ``h``, rest ends in (2, K): the pairs (z, dz))."""
    n_steps, batch = Z.shape[:2]
    rows = Z.reshape(n_steps, batch, -1)  # a view: the rest is contiguous in the basis buffer
    if rows.data_ptr() != Z.data_ptr():
        raise RuntimeError("_kernels.modal_scan: the basis rows are not a view of the buffer")
    _check("rate", rate.shape, Z.shape[1:])
    mu = torch.exp(rate).reshape(batch, -1).contiguous()
    _kernel("_scan_loop")(rows.numpy(), mu.numpy(), 0.0 if h is None else float(h), 0 if h is None else rate.shape[-1])
