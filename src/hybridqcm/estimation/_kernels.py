"""Compiled loops (numba) for the estimation layers' recursions, on the CPU: the Euler recursion with its
tangents, the modal basis' scan, the exact model's state recursion and, for the few samples the modal path leaves,
its state-and-tangent recursion and Van Loan maps with tangents; the Van Loan maps of the line search's outputs (the
exponential and the folded sub-steps, batch innermost: vectorised across samples); and the per-sample setup of the modal evaluation (the
modes' hold weights, the balancing, the eigenvectors' inverse and order, and the coefficients of the basis: V^-1 dA_j V,
the Sylvester terms and the real form's weights), whose torch form is tens of small ops a call, the cost of a line
search's trial at a few recordings (the coefficients: ~60 ops over [b, 1 + m, 2, K, o, W] complex tensors); the
channel delay's four-tap interpolation of the held input (a gather of the whole fine span in torch); and the noise
model's frequency response of a one-output, one-input model (the road-free seat) with its derivatives, per sample
and frequency (in torch [b, F, n^2] complex tensors and their batched products).

Why: in torch each step of these recursions is a few small ops over the whole batch, each bound by its own
dispatch and a pass over the chunk's memory (sensitivity.py: ~8 ops a step; _modal._scan and
exact._primal_states: one or two per step and state, where the occupant selection's calls hold 1-16
recordings). Here the loops run over one sample's (or one row's) values with the previous step in cache.
Each loop is the torch code's arithmetic, step by step; the results agree with it to rounding (fused
multiply-adds and summation orders differ), checked in tests/test_sensitivity.py and tests/test_exact.py
against the torch paths. The loops release the GIL, so the solver's chunk threads (SolverConfig.thread_chunks)
run them on several cores at once. They compile at the first call (about a second each; the Van Loan maps 2-3 s,
the modal coefficients about 6 s) into numba's cache beside this file, which later processes load; ``preload`` lets a run
load numba before its solve's clock starts.

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

import functools
import math
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


def preload() -> bool:
    """Import numba and load one loop, so that a run's first solve does not carry the program's start-up: numba's
    import (~0.35 s) and, at the first loop's load, its code generator's set-up (~0.2 s; each further loop then
    loads in milliseconds). What ``compiled_loops`` returns."""
    if not compiled_loops():
        return False
    states = np.zeros((2, 1, 1))
    _kernel("_states_loop")(np.zeros((1, 1, 1)), np.zeros((1, 1, 1)), states)
    return True


def _kernel(name: str):
    if name not in _compiled:
        # error_model "numpy": a division by zero gives inf or NaN, as in torch (a failed trial step's matrix), not an
        # exception
        njit = functools.partial(_numba().njit, nogil=True, error_model="numpy")
        try:
            _compiled[name] = njit(cache=True)(globals()[name])
        except RuntimeError:  # no writable cache beside the module nor in the user's: compile in each process
            _compiled[name] = njit()(globals()[name])
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
    """In place over Z [T, b, R] complex (rows may be strided; stored time or batch first), mu [b, R]: Z[k] <- mu
    Z[k - 1] + Z[k]; with n_slot K > 0 each row is R = groups x (z | dz) x K and dz[k] += h z[k] follows each step.
    The loops run in the order of the storage; each value takes the same operations in either."""
    n_steps, batch, width = Z.shape
    if Z.strides[1] > Z.strides[0]:  # stored batch first: one sample's steps in order, its rows in cache
        for b in range(batch):
            for k in range(1, n_steps):
                for i in range(width):
                    Z[k, b, i] += mu[b, i] * Z[k - 1, b, i]
                if n_slot > 0:
                    for g in range(width // (2 * n_slot)):
                        for s in range(n_slot):
                            Z[k, b, (2 * g + 1) * n_slot + s] += h * Z[k, b, 2 * g * n_slot + s]
        return
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


def _tangent_states_loop(phi, forcing, dphi, X):
    """In place over X [T, b, n, c] (X[0] set): X_(k+1) = Phi X_k, then its first q columns += F_k + dPhi x_k;
    phi [b, n, n], forcing [T-1, b, n, q], dphi [b, n, q, n], x_k = X_k[:, 0] (exact._stacked_sensitivities)."""
    n_steps, batch, n, width = X.shape
    n_q = forcing.shape[3]
    for s in range(batch):
        for k in range(n_steps - 1):
            for i in range(n):
                for c in range(width):
                    acc = 0.0
                    for j in range(n):
                        acc += phi[s, i, j] * X[k, s, j, c]
                    X[k + 1, s, i, c] = acc
                for q in range(n_q):
                    acc = forcing[k, s, i, q]
                    for j in range(n):
                        acc += dphi[s, i, q, j] * X[k, s, j, 0]
                    X[k + 1, s, i, q] += acc


def _hold_loop(lam, tau, zoh, inv_fact, ell, dell):
    """_modal._hold_weights per mode: lam [b, K] complex -> ell, dell [M + 1, b, K] (written); inv_fact[k] = 1/k!
    for k <= the series' last term + 3. The same expressions as there, mode by mode: phi_1..3 by the series
    (Horner, |z| <= 1) or by the downward recurrence, then the folded FOH (or ZOH) weights."""
    m_sub = ell.shape[0] - 1
    batch, n_slot = lam.shape
    terms = inv_fact.shape[0] - 4
    tau2 = tau * tau
    for b in range(batch):
        for s in range(n_slot):
            z = lam[b, s] * tau
            if abs(z) <= 1.0:
                p3 = inv_fact[terms + 3] + 0j
                for r in range(terms - 1, -1, -1):
                    p3 = p3 * z + inv_fact[r + 3]
                p2 = p3 * z + 0.5
                p1 = p2 * z + 1.0
            else:
                p1 = (np.exp(z) - 1.0) / z
                p2 = (p1 - 1.0) / z
                p3 = (p2 - 0.5) / z
            if zoh:
                g0, g1 = tau * p1, 0j
                dg0, dg1 = tau2 * (p1 - p2), 0j
            else:
                g0, g1 = tau * (p1 - p2), tau * p2
                dg0, dg1 = tau2 * (p1 - 2.0 * p2 + 2.0 * p3), tau2 * (p2 - 2.0 * p3)
            phi = np.exp(z)
            power = 1.0 + 0j  # phi^(M - j), from j = M down
            previous = power
            for j in range(m_sub, -1, -1):
                # j < M: phi^(M - 1 - j) (g0 terms), the previous j's power; j >= 1: phi^(M - j) (g1 terms)
                e = 0j
                de = 0j
                if j < m_sub:
                    e += previous * g0
                    de += previous * ((m_sub - 1 - j) * tau * g0 + dg0)
                if j >= 1:
                    e += power * g1
                    de += power * ((m_sub - j) * tau * g1 + dg1)
                ell[j, b, s] = e
                dell[j, b, s] = de
                previous = power
                power = power * phi


def _van_loan_loop(M, d, n, zoh, coef, theta, phi_out, lam_out):
    """_expm.van_loan_maps without tangents, batch innermost: M [N, N, b] the Van Loan matrices (N = n + 2m), d [b, N]
    their balancing -> phi_out [n, n, b], lam_out [M_sub + 1, n, m, b] (written). exp(M) as _expm._expm_inner
    computes it: D^-1 M D, scaled by 2^-s to a 1-norm <= theta (s per sample, so that a sample's maps do not depend
    on its batch mates), degree-11 Taylor by Paterson-Stockmeyer, s squarings, D back; then the sub-steps folded as there. Every product
    runs over the batch innermost (vectorised across samples); a sample whose matrix is not finite gets NaN maps."""
    size, batch = M.shape[0], M.shape[2]
    m = (size - n) // 2
    m_sub = lam_out.shape[0] - 1
    work = np.empty((5, size, size, batch))  # X, X^2, X^3, S (the sum), T (a product)
    X, X2, S, T = work[0], work[1], work[3], work[4]
    column = np.zeros(batch)
    norm = np.zeros(batch)
    for j in range(size):
        for b in range(batch):
            column[b] = 0.0
        for i in range(size):
            for b in range(batch):
                X[i, j, b] = M[i, j, b] * d[b, j] / d[b, i]
                column[b] += abs(X[i, j, b])
        for b in range(batch):
            if column[b] > norm[b] or not np.isfinite(column[b]):
                norm[b] = column[b]
    # s per sample (a sample's maps do not depend on its batch mates); the loop runs the batch's largest s and a
    # sample's S stops changing after its own
    own = np.zeros(batch, dtype=np.int64)
    scale = np.ones(batch)
    squarings = 0
    for b in range(batch):
        if np.isfinite(norm[b]) and norm[b] > theta:
            own[b] = int(math.ceil(math.log2(norm[b] / theta)))
            scale[b] = 2.0 ** -own[b]
            squarings = max(squarings, own[b])
    for i in range(size):
        for j in range(size):
            for b in range(batch):
                X[i, j, b] *= scale[b]
    # The products in order, each (out, left, right) slots of ``work``, written once (each copy of a product's loops
    # costs seconds of compilation): X^2, X^3, then X^3 S per Horner step, then S S per squaring.
    blocks = (coef.shape[0] - 1) // 3
    for op in range(2 + blocks + squarings):
        if op < 2:
            out, left, right = op + 1, op, 0
        elif op < 2 + blocks:
            out, left, right = 4, 2, 3
        else:
            out, left, right = 4, 3, 3
        if op == 2:  # the last block first: S = sum_{r<3} coef[3 blocks + r] X^r
            for i in range(size):
                for j in range(size):
                    a = coef[3 * blocks] if i == j else 0.0
                    for b in range(batch):
                        S[i, j, b] = a + coef[3 * blocks + 1] * X[i, j, b] + coef[3 * blocks + 2] * X2[i, j, b]
        for i in range(size):
            for j in range(size):
                for b in range(batch):
                    work[out, i, j, b] = 0.0
                for k in range(size):
                    for b in range(batch):
                        work[out, i, j, b] += work[left, i, k, b] * work[right, k, j, b]
        if 2 <= op < 2 + blocks:  # S = X^3 S + sum_{r<3} coef[3 block + r] X^r
            block = blocks - 1 - (op - 2)
            for i in range(size):
                for j in range(size):
                    a = coef[3 * block] if i == j else 0.0
                    for b in range(batch):
                        S[i, j, b] = T[i, j, b] + (
                            a + coef[3 * block + 1] * X[i, j, b] + coef[3 * block + 2] * X2[i, j, b]
                        )
        elif op >= 2 + blocks:
            squaring = op - 2 - blocks
            for i in range(size):
                for j in range(size):
                    for b in range(batch):
                        S[i, j, b] = T[i, j, b] if squaring < own[b] else S[i, j, b]
    for i in range(size):
        for j in range(size):
            for b in range(batch):
                S[i, j, b] *= d[b, i] / d[b, j]
    # exp(Van Loan) = [[phi, F1, F2], ...]; FOH: g0 = F1 - F2, g1 = F2; ZOH: g0 = F1, g1 = 0
    G0, G1 = np.empty((n, m, batch)), np.empty((n, m, batch))
    for i in range(n):
        for c in range(m):
            for b in range(batch):
                f1, f2 = S[i, n + c, b], S[i, n + m + c, b]
                G0[i, c, b] = f1 if zoh else f1 - f2
                G1[i, c, b] = 0.0 if zoh else f2
    # Lam_M = g1; with c = g0 + phi g1 and W = [c | g0 | phi] multiplied by phi from the left M - 1 times:
    # Lam_j = phi^(M-1-j) c (W's first columns after M - 1 - j products), Lam_0 = phi^(M-1) g0, Phi = phi^M.
    # (M = 1: Lam = (g0, g1), Phi = phi.) The copies are loops: each numba slice assignment costs ~1 s to compile.
    width = n + 2 * m
    W, W_next = np.empty((n, width, batch)), np.empty((n, width, batch))
    for i in range(n):
        for c in range(m):
            for b in range(batch):
                lam_out[m_sub, i, c, b] = G1[i, c, b]
                W[i, c, b] = G0[i, c, b]
                W[i, m + c, b] = G0[i, c, b]
            if m_sub > 1:
                for k in range(n):
                    for b in range(batch):
                        W[i, c, b] += S[i, k, b] * G1[k, c, b]
        for k in range(n):
            for b in range(batch):
                W[i, 2 * m + k, b] = S[i, k, b]
    for step in range(m_sub):
        if step > 0:
            for i in range(n):
                for j in range(width):
                    for b in range(batch):
                        W_next[i, j, b] = 0.0
                    for k in range(n):
                        for b in range(batch):
                            W_next[i, j, b] += S[i, k, b] * W[k, j, b]
            W, W_next = W_next, W
        for i in range(n):
            for c in range(m):
                for b in range(batch):
                    if step < m_sub - 1:
                        lam_out[m_sub - 1 - step, i, c, b] = W[i, c, b]
                    else:
                        lam_out[0, i, c, b] = W[i, m + c, b]
    for i in range(n):
        for k in range(n):
            for b in range(batch):
                phi_out[i, k, b] = W[i, 2 * m + k, b]


def _van_loan_tangent_loop(M, dM, d, n, zoh, coef, theta, phi_out, lam_out, dphi_out, dlam_out):
    """_expm.van_loan_maps_batch_first per sample: M [b, N, N] the Van Loan matrices (N = n + 2m), dM [b, P, N, N] their
    derivatives in the P parameters, d [b, N] the balancing of M -> phi_out [b, n, n], lam_out [b, M_sub + 1, n, m],
    dphi_out [b, P, n, n], dlam_out [b, P, M_sub + 1, n, m] (written). exp(M) and its Frechet derivatives by the
    scheme of _expm._expm_inner (balanced, scaled to a 1-norm <= theta per sample, degree-11 Paterson-Stockmeyer,
    squarings), every product carrying its tangents (d(A B) = dA B + A dB); then the sub-steps folded as there.
    For the few samples the modal path leaves: one sample's matrices stay in cache."""
    batch, size = M.shape[0], M.shape[1]
    n_p = dM.shape[1]
    m = (size - n) // 2
    m_sub = lam_out.shape[1] - 1
    blocks = (coef.shape[0] - 1) // 3
    # slots: X, X^2, X^3, S, T (a product); tangents likewise, per parameter
    work = np.empty((5, size, size))
    dwork = np.empty((5, n_p, size, size))
    width = n + 2 * m
    W, W_next = np.empty((n, width)), np.empty((n, width))
    dW, dW_next = np.empty((n_p, n, width)), np.empty((n_p, n, width))
    for b in range(batch):
        norm = 0.0
        for j in range(size):
            column = 0.0
            for i in range(size):
                work[0, i, j] = M[b, i, j] * d[b, j] / d[b, i]
                column += abs(work[0, i, j])
                for q in range(n_p):
                    dwork[0, q, i, j] = dM[b, q, i, j] * d[b, j] / d[b, i]
            norm = max(norm, column)
        if not np.isfinite(norm):
            for i in range(n):
                for k in range(n):
                    phi_out[b, i, k] = np.nan
                    for q in range(n_p):
                        dphi_out[b, q, i, k] = np.nan
                for j in range(m_sub + 1):
                    for c in range(m):
                        lam_out[b, j, i, c] = np.nan
                        for q in range(n_p):
                            dlam_out[b, q, j, i, c] = np.nan
            continue
        squarings = 0
        if norm > theta:
            squarings = int(math.ceil(math.log2(norm / theta)))
        scale = 2.0**-squarings
        for i in range(size):
            for j in range(size):
                work[0, i, j] *= scale
                for q in range(n_p):
                    dwork[0, q, i, j] *= scale
        # the products in order, (out, left, right) slots, written once: X^2, X^3, X^3 S per Horner step, S S per
        # squaring; with tangents d(out) = d(left) right + left d(right)
        for op in range(2 + blocks + squarings):
            if op < 2:
                out, left, right = op + 1, op, 0
            elif op < 2 + blocks:
                out, left, right = 4, 2, 3
            else:
                out, left, right = 4, 3, 3
            if op == 2:  # the last block first: S = sum_{r<3} coef[3 blocks + r] X^r
                for i in range(size):
                    for j in range(size):
                        a = coef[3 * blocks] if i == j else 0.0
                        work[3, i, j] = a + coef[3 * blocks + 1] * work[0, i, j] + coef[3 * blocks + 2] * work[1, i, j]
                        for q in range(n_p):
                            dwork[3, q, i, j] = (
                                coef[3 * blocks + 1] * dwork[0, q, i, j] + coef[3 * blocks + 2] * dwork[1, q, i, j]
                            )
            for i in range(size):
                for j in range(size):
                    acc = 0.0
                    for k in range(size):
                        acc += work[left, i, k] * work[right, k, j]
                    work[out, i, j] = acc
                    for q in range(n_p):
                        acc = 0.0
                        for k in range(size):
                            acc += dwork[left, q, i, k] * work[right, k, j] + work[left, i, k] * dwork[right, q, k, j]
                        dwork[out, q, i, j] = acc
            if 2 <= op < 2 + blocks:  # S = X^3 S + sum_{r<3} coef[3 block + r] X^r
                block = blocks - 1 - (op - 2)
                for i in range(size):
                    for j in range(size):
                        a = coef[3 * block] if i == j else 0.0
                        work[3, i, j] = work[4, i, j] + (
                            a + coef[3 * block + 1] * work[0, i, j] + coef[3 * block + 2] * work[1, i, j]
                        )
                        for q in range(n_p):
                            dwork[3, q, i, j] = dwork[4, q, i, j] + (
                                coef[3 * block + 1] * dwork[0, q, i, j] + coef[3 * block + 2] * dwork[1, q, i, j]
                            )
            elif op >= 2 + blocks:
                for i in range(size):
                    for j in range(size):
                        work[3, i, j] = work[4, i, j]
                        for q in range(n_p):
                            dwork[3, q, i, j] = dwork[4, q, i, j]
        for i in range(size):  # D back: F = D exp(X) D^-1
            for j in range(size):
                ratio = d[b, i] / d[b, j]
                work[3, i, j] *= ratio
                for q in range(n_p):
                    dwork[3, q, i, j] *= ratio
        # exp(Van Loan) = [[phi, F1, F2], ...]; FOH: g0 = F1 - F2, g1 = F2; ZOH: g0 = F1, g1 = 0. W = [c | g0 | phi]
        # with c = g0 + phi g1 (M > 1; M = 1: Lam = (g0, g1)), then W times phi from the left M - 1 times (folding).
        S, dS = work[3], dwork[3]
        for i in range(n):
            for c in range(m):
                f1, f2 = S[i, n + c], S[i, n + m + c]
                g0 = f1 if zoh else f1 - f2
                g1 = 0.0 if zoh else f2
                lam_out[b, m_sub, i, c] = g1
                W[i, c] = g0
                W[i, m + c] = g0
                if m_sub > 1:
                    for k in range(n):
                        W[i, c] += S[i, k] * (0.0 if zoh else S[k, n + m + c])
                for q in range(n_p):
                    df1, df2 = dS[q, i, n + c], dS[q, i, n + m + c]
                    dg0 = df1 if zoh else df1 - df2
                    dg1 = 0.0 if zoh else df2
                    dlam_out[b, q, m_sub, i, c] = dg1
                    dW[q, i, c] = dg0
                    dW[q, i, m + c] = dg0
                    if m_sub > 1 and not zoh:
                        for k in range(n):
                            dW[q, i, c] += dS[q, i, k] * S[k, n + m + c] + S[i, k] * dS[q, k, n + m + c]
            for k in range(n):
                W[i, 2 * m + k] = S[i, k]
                for q in range(n_p):
                    dW[q, i, 2 * m + k] = dS[q, i, k]
        for step in range(m_sub):
            if step > 0:
                for i in range(n):
                    for j in range(width):
                        acc = 0.0
                        for k in range(n):
                            acc += S[i, k] * W[k, j]
                        W_next[i, j] = acc
                        for q in range(n_p):
                            acc = 0.0
                            for k in range(n):
                                acc += dS[q, i, k] * W[k, j] + S[i, k] * dW[q, k, j]
                            dW_next[q, i, j] = acc
                W, W_next = W_next, W
                dW, dW_next = dW_next, dW
            for i in range(n):
                for c in range(m):
                    row = m_sub - 1 - step if step < m_sub - 1 else 0
                    col = c if step < m_sub - 1 else m + c
                    lam_out[b, row, i, c] = W[i, col]
                    for q in range(n_p):
                        dlam_out[b, q, row, i, c] = dW[q, i, col]
        for i in range(n):
            for k in range(n):
                phi_out[b, i, k] = W[i, 2 * m + k]
                for q in range(n_p):
                    dphi_out[b, q, i, k] = dW[q, i, 2 * m + k]


def _balance_loop(M, sweeps, damping, d):
    """_expm.balance per sample: M [b, N, N] -> d [b, N] (written), the same damped simultaneous updates."""
    batch, n = M.shape[0], M.shape[1]
    log_d = np.zeros(n)
    col = np.zeros(n)
    row = np.zeros(n)
    for b in range(batch):
        log_d[:] = 0.0
        for _ in range(sweeps):
            col[:] = 0.0
            row[:] = 0.0
            for i in range(n):
                di = np.exp2(log_d[i])
                for j in range(n):
                    if i != j:
                        scaled = abs(M[b, i, j]) * np.exp2(log_d[j]) / di
                        col[j] += scaled
                        row[i] += scaled
            for i in range(n):
                if col[i] > 0 and row[i] > 0:
                    log_d[i] += damping * np.log2(row[i] / col[i])
        for i in range(n):
            d[b, i] = np.exp2(np.rint(log_d[i]))


def _modes_loop(lam_in, Vb, scale, sort, work, lam, V, V_inv, cond, ok, n_first):
    """_modal._decompose per sample after LAPACK's eigen-decomposition of the balanced D^-1 A D: lam_in [b, n], Vb
    [b, n, n] (complex), scale [b, n] = D -> (written) lam, V = D Vb, V^-1 = Vb^-1 D^-1 with the modes in LAPACK's
    order or, with ``sort``, the upper members of the conjugate pairs first, then the real eigenvalues, then the
    lower members (a stable order: torch's argsort there); cond [b] the 1-norm condition number of Vb; ok [b]: Vb
    invertible (no zero pivot), cond finite, the complex eigenvalues in pairs; n_first [b] the upper and real
    ones. Vb^-1 by Gauss-Jordan elimination with partial pivoting on work [n, 2n] = (Vb | I)."""
    batch, n = lam_in.shape
    order = np.empty(n, dtype=np.int64)
    for b in range(batch):
        upper = 0
        lower = 0
        for i in range(n):
            if lam_in[b, i].imag > 0:
                upper += 1
            elif lam_in[b, i].imag < 0:
                lower += 1
        n_first[b] = n - upper
        slot = 0
        for key in range(3 if sort else 1):
            for i in range(n):
                im = lam_in[b, i].imag
                if not sort or key == (0 if im > 0 else (1 if im == 0 else 2)):
                    order[slot] = i
                    slot += 1
        for i in range(n):
            for j in range(n):
                work[i, j] = Vb[b, i, j]
                work[i, n + j] = 1.0 if i == j else 0.0
        invertible = True
        for c in range(n):
            pivot = c
            for r in range(c + 1, n):
                if abs(work[r, c]) > abs(work[pivot, c]):
                    pivot = r
            if work[pivot, c] == 0:
                invertible = False
                break
            if pivot != c:
                for j in range(2 * n):
                    work[c, j], work[pivot, j] = work[pivot, j], work[c, j]
            inv = 1.0 / work[c, c]
            for j in range(2 * n):
                work[c, j] *= inv
            for r in range(n):
                f = work[r, c]
                if r != c and f != 0:
                    for j in range(2 * n):
                        work[r, j] -= f * work[c, j]
        norm = 0.0
        norm_inv = 0.0
        for j in range(n):
            col = 0.0
            col_inv = 0.0
            for i in range(n):
                col += abs(Vb[b, i, j])
                col_inv += abs(work[i, n + j])
            norm = max(norm, col)
            norm_inv = max(norm_inv, col_inv)
        cond[b] = norm * norm_inv if invertible else np.inf
        ok[b] = invertible and np.isfinite(cond[b]) and upper == lower
        for s in range(n):
            k = order[s]
            lam[b, s] = lam_in[b, k]
            for i in range(n):
                V[b, i, s] = Vb[b, i, k] * scale[b, i]
                if scale[b, i] != 0:
                    V_inv[b, s, i] = (work[k, n + i] if invertible else 0.0) / scale[b, i]
                else:  # a balancing underflowed by a wild trial's matrix (not ok there): numba's complex division raises
                    V_inv[b, s, i] = complex(np.nan, np.nan)


def _coefficients_loop(lam, V, V_inv, cond, B, C, E, dA, dB, dC, dE, x0, has_x0, with_x0, omega, n_t, limit,
                       limit_real, coef_all, ok):  # fmt: skip
    """_modal._coefficients per sample (its notation): lam [b, n], V, V_inv [b, n, n] (complex), cond [b]; B, C, E
    and dA, dB, dC, dE with a leading dimension of b, or of 1 where one value serves every sample (a linear
    model's derivatives); x0 [b or 1, n] (read where has_x0); omega [b, K] -> coef_all [b, width, o n_col] and ok
    [b] (in: _modes' flags; out: and the spread test and finite coefficients). dA_j is sparse (a parameter enters a
    few entries of A): its zero entries and rows are skipped, which changes no sum."""
    batch, n = lam.shape
    m, o, n_p = B.shape[2], C.shape[1], dA.shape[1]
    n_slot = omega.shape[1]
    n_col = 1 + n_p + (n if with_x0 else 0)
    width, n_out = coef_all.shape[1], coef_all.shape[2]
    n_real = 4 * n_slot * (m + 1)
    beta = np.empty((n, m), dtype=np.complex128)
    gamma = np.empty((o, n), dtype=np.complex128)
    dAV = np.empty((n, n), dtype=np.complex128)
    rows = np.empty(n, dtype=np.int64)  # the rows of dA_j with a non-zero entry
    K = np.empty((n_p, n, n), dtype=np.complex128)  # [j, i, l] = (V^-1 dA_j V)_il
    S = np.empty((n_p, n, n), dtype=np.complex128)
    xi0 = np.zeros(n, dtype=np.complex128)
    R = np.empty((1 + m, 2, n_slot, n_col), dtype=np.complex128)
    Q = np.empty((1 + m, n_slot), dtype=np.complex128)
    Gam = np.empty((o, n_p, n_slot), dtype=np.complex128)
    for b in range(batch):
        bB = b if B.shape[0] > 1 else 0
        bC = b if C.shape[0] > 1 else 0
        bE = b if E.shape[0] > 1 else 0
        bA = b if dA.shape[0] > 1 else 0
        bdB = b if dB.shape[0] > 1 else 0
        bdC = b if dC.shape[0] > 1 else 0
        bdE = b if dE.shape[0] > 1 else 0
        bx = b if x0.shape[0] > 1 else 0
        # cond(V) max|lambda| / |lambda_i - lambda_l| within the limits (a NaN fails, as in torch)
        good = ok[b]
        largest = 0.0
        for i in range(n):
            largest = max(largest, abs(lam[b, i]))
        numerator = cond[b] * largest
        for i in range(n):
            for l in range(n):
                if i != l:
                    both_real = lam[b, i].imag == 0 and lam[b, l].imag == 0
                    if not numerator / abs(lam[b, i] - lam[b, l]) <= (limit_real if both_real else limit):
                        good = False
        for i in range(n):
            for c in range(m):
                acc = 0j
                for j in range(n):
                    acc += V_inv[b, i, j] * B[bB, j, c]
                beta[i, c] = acc
        for r in range(o):
            for i in range(n):
                acc = 0j
                for j in range(n):
                    acc += C[bC, r, j] * V[b, j, i]
                gamma[r, i] = acc
        for p in range(n_p):
            n_used = 0
            for j in range(n):
                for l in range(n):
                    dAV[j, l] = 0j
                used = False
                for q in range(n):
                    a = dA[bA, p, j, q]
                    if a != 0.0:
                        used = True
                        for l in range(n):
                            dAV[j, l] += a * V[b, q, l]
                if used:
                    rows[n_used] = j
                    n_used += 1
            for i in range(n):
                for l in range(n):
                    acc = 0j
                    for u in range(n_used):
                        acc += V_inv[b, i, rows[u]] * dAV[rows[u], l]
                    K[p, i, l] = acc
                    gap = lam[b, i] - lam[b, l]
                    if i == l:
                        S[p, i, l] = 0j
                    elif gap != 0:
                        S[p, i, l] = -(acc / gap)
                    else:  # a double eigenvalue (the spread test has failed): numba's complex division would raise
                        S[p, i, l] = complex(np.nan, np.nan)
        if has_x0:
            for i in range(n):
                acc = 0j
                for j in range(n):
                    acc += V_inv[b, i, j] * x0[bx, j]
                xi0[i] = acc
        R[:] = 0j
        Q[:] = 0j
        for k in range(n_slot):
            if has_x0:
                R[0, 0, k, 0] = xi0[k]
                Q[0, k] = xi0[k]
                for p in range(n_p):
                    acc = 0j
                    for l in range(n):
                        acc += S[p, k, l] * xi0[l]
                    R[0, 0, k, 1 + p] = -acc
                    R[0, 1, k, 1 + p] = K[p, k, k] * xi0[k]
            if with_x0:
                for j in range(n):
                    R[0, 0, k, 1 + n_p + j] = V_inv[b, k, j]
            for c in range(m):
                R[1 + c, 0, k, 0] = beta[k, c]
                Q[1 + c, k] = beta[k, c]
                for p in range(n_p):
                    acc = 0j
                    for l in range(n):
                        acc += V_inv[b, k, l] * dB[bdB, p, l, c]
                    sylvester = 0j
                    for l in range(n):
                        sylvester += S[p, k, l] * beta[l, c]
                    R[1 + c, 0, k, 1 + p] = acc - sylvester
                    R[1 + c, 1, k, 1 + p] = K[p, k, k] * beta[k, c]
        for r in range(o):
            for p in range(n_p):
                for k in range(n_slot):
                    acc = 0j
                    for q in range(n):
                        acc += dC[bdC, p, r, q] * V[b, q, k]
                    sylvester = 0j
                    for i in range(n):
                        sylvester += gamma[r, i] * S[p, i, k]
                    Gam[r, p, k] = acc + sylvester
        for row in range(width):
            for col in range(n_out):
                coef_all[b, row, col] = 0.0
        for ch in range(1 + m):
            for kind in range(2):
                for k in range(n_slot):
                    row = ((ch * 2 + kind) * n_slot + k) * 2
                    w = omega[b, k]
                    for r in range(o):
                        g = gamma[r, k].conjugate() * w
                        for col in range(n_col):
                            value = g * R[ch, kind, k, col].conjugate()
                            if kind == 0 and 1 <= col <= n_p:
                                value += Gam[r, col - 1, k].conjugate() * w * Q[ch, k].conjugate()
                            coef_all[b, row, r * n_col + col] = value.real
                            coef_all[b, row + 1, r * n_col + col] = value.imag
        for c in range(m):
            for r in range(o):
                coef_all[b, n_real + c, r * n_col] = E[bE, r, c]
                for p in range(n_p):
                    coef_all[b, n_real + c, r * n_col + 1 + p] = dE[bdE, p, r, c]
        for r in range(n_t):
            coef_all[b, n_real + m + r, r * n_col] = -1.0
        total = 0.0
        for row in range(width):
            for col in range(n_out):
                total += coef_all[b, row, col]
        ok[b] = good and np.isfinite(total)


def _taps_loop(wide, first, w, lead, held):
    """delay.DelayedResponse._held per sample: wide [b, m, W_wide], first [b] the index of tap 0 of fine sample 0, w
    [b, 4] the Lagrange weights (or their derivatives) -> held [b, m, lead + n_fine]: ``lead`` zeros, then
    sum_t w_t wide[first + f + t]."""
    batch, n_in, width = held.shape
    for b in range(batch):
        f0 = first[b]
        w0, w1, w2, w3 = w[b, 0], w[b, 1], w[b, 2], w[b, 3]
        for c in range(n_in):
            row = wide[b, c, f0:]
            out = held[b, c, lead:]
            held[b, c, :lead] = 0.0
            for f in range(width - lead):
                out[f] = row[f] * w0 + row[f + 1] * w1 + row[f + 2] * w2 + row[f + 3] * w3


def _response_loop(lam, CV, WB, E, omega, K, dB, dC, dE, derivatives, H, dH):
    """noise._response_modal for one output and one input, per sample and frequency: lam, CV = (C V)_i, WB = (V^-1 B)_i
    [b, n]; E [b]; omega [F]; with ``derivatives`` K [b, P, n, n] = V^-1 dA_j V, dB [b, P, n] = V^-1 dB_j, dC [b, P, n]
    = dC_j V, dE [b, P] -> H [b, F] and dH [b, P, F] (complex). With g_i = 1 / (j w - lambda_i):
    H = E + sum_i CV_i WB_i g_i, and dH_j = dE_j + sum_(i<=l) M_j,il g_i g_l + sum_i N_j,i g_i with, per sample,
    M_j,il = CV_i K_j,il WB_l + CV_l K_j,li WB_i (i < l; CV_i K_j,ii WB_i on the diagonal: g_i g_l is symmetric)
    and N_j,i = CV_i dB_j,i + dC_j,i WB_i."""
    batch, n = lam.shape
    n_f = omega.shape[0]
    n_p = K.shape[1]
    n_pairs = n * (n + 1) // 2
    r = np.empty(n, dtype=np.complex128)
    g = np.empty(n, dtype=np.complex128)
    G = np.empty(n_pairs, dtype=np.complex128)
    M = np.empty((n_p, n_pairs), dtype=np.complex128)
    N = np.empty((n_p, n), dtype=np.complex128)
    for b in range(batch):
        for i in range(n):
            r[i] = CV[b, i] * WB[b, i]
        if derivatives:
            for p in range(n_p):
                t = 0
                for i in range(n):
                    N[p, i] = CV[b, i] * dB[b, p, i] + dC[b, p, i] * WB[b, i]
                    for l in range(i, n):
                        M[p, t] = CV[b, i] * K[b, p, i, l] * WB[b, l]
                        if l != i:
                            M[p, t] += CV[b, l] * K[b, p, l, i] * WB[b, i]
                        t += 1
        for k in range(n_f):
            real = 0.0
            imag = 0.0
            for i in range(n):
                re = -lam[b, i].real
                im = omega[k] - lam[b, i].imag
                inv = 1.0 / (re * re + im * im)
                real += (r[i].real * re + r[i].imag * im) * inv
                imag += (r[i].imag * re - r[i].real * im) * inv
                g[i] = complex(re * inv, -im * inv)
            H[b, k] = complex(real, imag) + E[b]
            if derivatives:
                t = 0
                for i in range(n):
                    for l in range(i, n):
                        G[t] = g[i] * g[l]
                        t += 1
                for p in range(n_p):
                    acc = complex(dE[b, p], 0.0)
                    for t in range(n_pairs):
                        acc += M[p, t] * G[t]
                    for i in range(n):
                        acc += N[p, i] * g[i]
                    dH[b, p, k] = acc


def _check(name: str, got, want) -> None:
    """The loops index without bounds checks (numba's default): a shape that does not match is refused here."""
    if tuple(got) != tuple(want):
        raise ValueError(f"_kernels: {name} must be {list(want)}, got {list(got)}")


def _per_sample(t: Tensor) -> np.ndarray:
    """A [b, ...] float64 argument for the loops that index it per sample: one row where every sample shares it (an
    expanded view, stride 0), else contiguous."""
    if t.shape[0] > 1 and t.stride(0) == 0:
        t = t[:1]
    return _numpy(t)


def modal_coefficients(lam, V, V_inv, cond, ok, matrices, derivatives, x0, with_x0, omega, n_t, width, limits):
    """_modal._coefficients (its arguments; ``limits`` = (_LIMIT, _LIMIT_REAL)) -> (coef_all [b, width, o n_col], ok
    [b]) as _coefficients_loop writes them."""
    _, B, C, E = matrices
    dA, dB, dC, dE = derivatives
    batch, n = lam.shape
    m, o, n_p = B.shape[2], C.shape[1], dA.shape[1]
    n_slot = omega.shape[1]
    _check("V", V.shape, (batch, n, n))
    _check("V_inv", V_inv.shape, (batch, n, n))
    _check("B", B.shape, (batch, n, m))
    _check("C", C.shape, (batch, o, n))
    _check("E", E.shape, (batch, o, m))
    _check("dA", dA.shape, (batch, n_p, n, n))
    _check("dB", dB.shape, (batch, n_p, n, m))
    _check("dC", dC.shape, (batch, n_p, o, n))
    _check("dE", dE.shape, (batch, n_p, o, m))
    if x0 is not None:
        _check("x0", x0.shape, (batch, n))
    if omega.shape[0] != batch or n_slot > n or width < 4 * n_slot * (m + 1) + m + n_t:
        raise ValueError(f"_kernels: omega {list(omega.shape)} or width {width} do not fit lam {list(lam.shape)}")
    n_col = 1 + n_p + (n if with_x0 else 0)
    coef_all = np.empty((batch, width, o * n_col))
    flags = ok.to(torch.bool).clone().numpy()
    complex_values = (t.detach().to(torch.complex128).contiguous().numpy() for t in (lam, V, V_inv))
    _kernel("_coefficients_loop")(
        *complex_values, _numpy(cond), *(_per_sample(t) for t in (B, C, E, dA, dB, dC, dE)),
        np.zeros((1, n)) if x0 is None else _numpy(x0), x0 is not None, bool(with_x0), _numpy(omega), int(n_t),
        float(limits[0]), float(limits[1]), coef_all, flags,
    )  # fmt: skip
    return torch.from_numpy(coef_all), torch.from_numpy(flags)


def delay_taps(wide: Tensor, first: Tensor, w: Tensor, dw: Tensor | None, lead: int, n_fine: int):
    """delay.DelayedResponse._held's four-tap interpolation: wide [b, m, W_wide] float64, first [b] (int) the index of
    tap 0 of the first fine sample, w and dw [b, 4] -> (held, dheld or None) [b, m, lead + n_fine] with ``lead``
    leading zeros. Every tap inside wide (the caller clamps): checked here, as the loop indexes without checks."""
    batch, n_in, n_wide = wide.shape
    _check("w", w.shape, (batch, 4))
    if dw is not None:
        _check("dw", dw.shape, (batch, 4))
    first_np = first.detach().to(torch.int64).contiguous().numpy()
    if batch and (first_np.min() < 0 or first_np.max() + n_fine + 3 > n_wide):
        raise ValueError(
            f"_kernels: delay taps from {first_np.min()} to {first_np.max() + n_fine + 2} outside 0..{n_wide - 1}"
        )
    wide_np = _numpy(wide)
    out = []
    for weights in (w,) if dw is None else (w, dw):
        values = np.empty((batch, n_in, lead + n_fine))
        _kernel("_taps_loop")(wide_np, first_np, _numpy(weights), int(lead), values)
        out.append(torch.from_numpy(values))
    return out[0], (out[1] if dw is not None else None)


def one_channel_response(lam, CV, WB, E, omega, modal_derivatives=None):
    """noise._response_modal for one output and one input: lam, CV, WB [b, n] complex, E [b], omega [F] (rad/s) and,
    for dH, modal_derivatives = (V^-1 dA_j V [b, P, n, n], V^-1 dB_j [b, P, n], dC_j V [b, P, n], dE_j [b, P]) ->
    (H [b, F], dH [b, P, F] or None) complex128, as _response_loop writes them."""
    batch, n = lam.shape
    _check("CV", CV.shape, (batch, n))
    _check("WB", WB.shape, (batch, n))
    _check("E", E.shape, (batch,))
    cx = lambda t: t.detach().to(torch.complex128).contiguous().numpy()  # noqa: E731
    derivatives = modal_derivatives is not None
    if derivatives:
        K, dB, dC, dE = modal_derivatives
        n_p = K.shape[1]
        _check("V^-1 dA V", K.shape, (batch, n_p, n, n))
        _check("V^-1 dB", dB.shape, (batch, n_p, n))
        _check("dC V", dC.shape, (batch, n_p, n))
        _check("dE", dE.shape, (batch, n_p))
        arrays = (cx(K), cx(dB), cx(dC), _numpy(dE))
    else:
        n_p = 0
        arrays = (np.zeros((1, 1, 1, 1), np.complex128), np.zeros((1, 1, 1), np.complex128),
                  np.zeros((1, 1, 1), np.complex128), np.zeros((1, 1)))  # fmt: skip
    H = np.empty((batch, omega.shape[0]), dtype=np.complex128)
    dH = np.empty((batch, n_p, omega.shape[0]) if derivatives else (1, 1, 1), dtype=np.complex128)
    _kernel("_response_loop")(cx(lam), cx(CV), cx(WB), _numpy(E), _numpy(omega), *arrays, derivatives, H, dH)
    return torch.from_numpy(H), (torch.from_numpy(dH) if derivatives else None)


def linear_states(phi: Tensor, forcing: Tensor, states: Tensor) -> None:
    """exact._primal_states' recursion in place over states [T, n, b] (contiguous, states[0] set)."""
    n_steps, n, batch = states.shape
    _check("phi", phi.shape, (n, n, batch))
    _check("forcing", forcing.shape, (n_steps - 1, n, batch))
    _kernel("_states_loop")(_numpy(phi), _numpy(forcing), states.numpy())


def tangent_states(phi: Tensor, forcing: Tensor, dphi: Tensor, X: Tensor) -> None:
    """exact._stacked_sensitivities' recursion in place over X [T, b, n, c] (contiguous, X[0] set): phi [b, n, n],
    forcing [T-1, b, n, q], dphi [b, n, q, n]."""
    n_steps, batch, n, _ = X.shape
    n_q = forcing.shape[-1]
    _check("phi", phi.shape, (batch, n, n))
    _check("forcing", forcing.shape, (n_steps - 1, batch, n, n_q))
    _check("dphi", dphi.shape, (batch, n, n_q, n))
    if not X.is_contiguous() or n_q > X.shape[3]:
        raise ValueError(f"_kernels: X must be contiguous with at least {n_q} columns, got {list(X.shape)}")
    _kernel("_tangent_states_loop")(_numpy(phi), _numpy(forcing), _numpy(dphi), X.numpy())


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


@functools.lru_cache(maxsize=4)
def _inverse_factorials(count: int) -> np.ndarray:
    """1/k! for k < count (read-only: shared by every call)."""
    values = np.array([1.0 / math.factorial(k) for k in range(count)])
    values.flags.writeable = False
    return values


def hold_weights(lam: Tensor, h: float, hold: str, m_sub: int, series_terms: int) -> tuple[Tensor, Tensor]:
    """_modal._hold_weights: lam [b, K] complex128 -> (l_j, d l_j / d lambda) [M + 1, b, K] each; ``series_terms``
    the degree of its phi_3 series."""
    if lam.ndim != 2:
        raise ValueError(f"_kernels: lam must be [b, K], got {list(lam.shape)}")
    inv_fact = _inverse_factorials(series_terms + 4)
    ell = np.empty((m_sub + 1, *lam.shape), dtype=np.complex128)
    dell = np.empty_like(ell)
    lam_np = lam.detach().to(torch.complex128).contiguous().numpy()
    _kernel("_hold_loop")(lam_np, float(h) / m_sub, hold == "zoh", inv_fact, ell, dell)
    return torch.from_numpy(ell), torch.from_numpy(dell)


def van_loan_maps(M: Tensor, d: Tensor, n: int, zoh: bool, m_sub: int, degree: int, theta: float):
    """_expm.van_loan_maps without tangents from the Van Loan matrices M [N, N, b] (batch innermost) and their
    balancing d [b, N]: (Phi [n, n, b], Lam [m_sub + 1, n, m, b]); ``degree`` and ``theta`` those of _expm's
    Taylor."""
    size, batch = M.shape[0], M.shape[2]
    _check("M", M.shape, (size, size, batch))
    _check("d", d.shape, (batch, size))
    if (size - n) % 2 or size <= n or m_sub < 1 or degree % 3 != 2:
        raise ValueError(f"_kernels: van_loan_maps needs N = n + 2m, m_sub >= 1, degree 3k + 2; got {size}, {n}, "
                         f"{m_sub}, {degree}")  # fmt: skip
    m = (size - n) // 2
    phi, lam = np.empty((n, n, batch)), np.empty((m_sub + 1, n, m, batch))
    coef = _inverse_factorials(degree + 1)
    _kernel("_van_loan_loop")(_numpy(M), _numpy(d), int(n), bool(zoh), coef, float(theta), phi, lam)
    return torch.from_numpy(phi), torch.from_numpy(lam)


def van_loan_tangent_maps(M: Tensor, dM: Tensor, d: Tensor, n: int, zoh: bool, m_sub: int, degree: int, theta: float):
    """_expm.van_loan_maps_batch_first from the Van Loan matrices M [b, N, N], their derivatives dM [b, P, N, N] and
    the balancing d [b, N]: (Phi [b, n, n], Lam [b, m_sub + 1, n, m], dPhi [b, P, n, n], dLam [b, P, m_sub + 1, n, m])."""
    batch, size = M.shape[0], M.shape[1]
    n_p = dM.shape[1]
    _check("M", M.shape, (batch, size, size))
    _check("dM", dM.shape, (batch, n_p, size, size))
    _check("d", d.shape, (batch, size))
    if (size - n) % 2 or size <= n or m_sub < 1 or degree % 3 != 2:
        raise ValueError(
            f"_kernels: van_loan_tangent_maps needs N = n + 2m, m_sub >= 1, degree 3k + 2; got {size}, {n}, {m_sub}, "
            f"{degree}"
        )
    m = (size - n) // 2
    phi, lam = np.empty((batch, n, n)), np.empty((batch, m_sub + 1, n, m))
    dphi, dlam = np.empty((batch, n_p, n, n)), np.empty((batch, n_p, m_sub + 1, n, m))
    coef = _inverse_factorials(degree + 1)
    _kernel("_van_loan_tangent_loop")(
        _numpy(M), _numpy(dM), _numpy(d), int(n), bool(zoh), coef, float(theta), phi, lam, dphi, dlam
    )
    return tuple(torch.from_numpy(x) for x in (phi, lam, dphi, dlam))


def balance(M: Tensor, sweeps: int, damping: float) -> Tensor:
    """_expm.balance: M [b, N, N] float64 -> d [b, N]."""
    if M.ndim != 3 or M.shape[1] != M.shape[2]:
        raise ValueError(f"_kernels: M must be [b, N, N], got {list(M.shape)}")
    d = np.empty(M.shape[:2])
    _kernel("_balance_loop")(_numpy(M), int(sweeps), float(damping), d)
    return torch.from_numpy(d)


def modes(lam: Tensor, Vb: Tensor, scale: Tensor, sort: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """_modal._decompose after the eigen-decomposition: lam [b, n], Vb [b, n, n] (complex128), scale [b, n] ->
    (lam, V, V^-1, cond [b], ok [b], n_first [b]) as _modes_loop writes them."""
    batch, n = lam.shape
    _check("Vb", Vb.shape, (batch, n, n))
    _check("scale", scale.shape, (batch, n))
    out_lam = np.empty((batch, n), dtype=np.complex128)
    V, V_inv = np.empty((batch, n, n), dtype=np.complex128), np.empty((batch, n, n), dtype=np.complex128)
    cond, ok, n_first = np.empty(batch), np.empty(batch, dtype=np.bool_), np.empty(batch, dtype=np.int64)
    complex_values = (lam.to(torch.complex128).contiguous().numpy(), Vb.to(torch.complex128).contiguous().numpy())
    work = np.empty((n, 2 * n), dtype=np.complex128)
    _kernel("_modes_loop")(*complex_values, _numpy(scale), bool(sort), work, out_lam, V, V_inv, cond, ok, n_first)
    return tuple(torch.from_numpy(x) for x in (out_lam, V, V_inv, cond, ok, n_first))
