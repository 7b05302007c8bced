"""Continuous-time linear models  dx/dt = A(p) x + B(p) w(t),  y = C(p) x + E(p) w.

One class per vehicle model the estimator can fit; ``estimation.exact`` discretises any of them
exactly. Shapes (b = batch, P = n_params, n = n_state, m = n_input, o = n_output)::

    matrices(p [b, P])            -> A [b, n, n], B [b, n, m], C [b, o, n], E [b, o, m]
    matrix_derivatives(p [b, P])  -> dA [b, P, n, n], dB [b, P, n, m], dC [b, P, o, n], dE [b, P, o, m]

All three models below are *linear* in p (every entry of A, B, C, E is a fixed linear
combination of the p_j plus a constant), so their derivatives are the constant matrices
M(e_j) - M(0): computed once per call from P + 1 evaluations and expanded over the batch
(no copy). A non-linear subclass sets ``linear_in_params = False`` and gets torch.func.jacfwd, unless it
is *multi-affine* (``multi_affine = True``: every entry affine in each p_j alone, as a person's body on a
seat, whose products R p1, r c, r k never hold one parameter twice): then d M / d p_j = M(p; p_j = 1) -
M(p; p_j = 0) exactly, all 2P evaluations in one call of matrices (jacfwd's vmap cost ~2 ms a call, as
much as a small batch's whole loss evaluation).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybridqcm.physics.parameters import CHANNELS, PARAM_NAMES, params_to_matrices, road_gain, system_matrix


class LinearModel:
    """Continuous-time LTI model  dx/dt = A(p) x + B(p) w(t),  y = C(p) x + E(p) w  (w: inputs).

    Subclasses set: name, param_names (tuple, len n_params), state_names (n_state),
    input_names (n_input), output_names (n_output), and implement matrices(p).
    """

    name: str = "linear"
    param_names: tuple[str, ...] = ()
    state_names: tuple[str, ...] = ()
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    linear_in_params: bool = False
    multi_affine: bool = False  # every entry affine in each parameter alone (module docstring)
    # parameters whose zero is a smaller model of the set (a body mode's r_i) -> the parameters and states that
    # model lacks (at r_i = 0 the output depends on neither: the mode's k_i, c_i and its dy_i, y_i)
    nested_at_zero: dict[str, tuple[str, ...]] = {}

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def n_state(self) -> int:
        return len(self.state_names)

    @property
    def n_input(self) -> int:
        return len(self.input_names)

    @property
    def n_output(self) -> int:
        return len(self.output_names)

    def check_params(self, p: Tensor) -> None:
        if p.ndim != 2 or p.shape[-1] != self.n_params:
            raise ValueError(
                f"{self.name}: params must be [batch, {self.n_params}] "
                f"({', '.join(self.param_names)}), got {tuple(p.shape)}"
            )

    def matrices(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """p [batch, n_params] -> A [b, n, n], B [b, n, m], C [b, o, n], E [b, o, m]."""
        raise NotImplementedError

    def matrix_derivatives(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """p [b, P] -> dA [b, P, n, n], dB [b, P, n, m], dC [b, P, o, n], dE [b, P, o, m];
        [:, j] = d/dp_j. Linear models: constant, returned as expanded (read-only) views."""
        self.check_params(p)
        batch, n_params = p.shape
        if self.linear_in_params:
            basis = torch.cat(
                [
                    torch.zeros(1, n_params, dtype=p.dtype, device=p.device),
                    torch.eye(n_params, dtype=p.dtype, device=p.device),
                ]
            )
            return tuple((m[1:] - m[:1]).unsqueeze(0).expand(batch, *m[1:].shape) for m in self.matrices(basis))
        if self.multi_affine:  # M(p; p_j = 1) - M(p; p_j = 0), every (sample, j, end) in one call
            eye = torch.eye(n_params, dtype=torch.bool, device=p.device)
            ends = p[:, None, None, :].expand(batch, n_params, 2, n_params).clone()  # [b, j, (1, 0), P]
            ends[:, :, 0] = torch.where(eye, torch.ones_like(ends[:, :, 0]), ends[:, :, 0])
            ends[:, :, 1] = torch.where(eye, torch.zeros_like(ends[:, :, 1]), ends[:, :, 1])
            return tuple(
                (lambda m: (m[:, :, 0] - m[:, :, 1]).contiguous())(m.view(batch, n_params, 2, *m.shape[1:]))
                for m in self.matrices(ends.view(-1, n_params))
            )
        jac = torch.func.vmap(torch.func.jacfwd(lambda q: tuple(m[0] for m in self.matrices(q[None]))))(p)
        return tuple(d.movedim(-1, 1).contiguous() for d in jac)  # [b, ..., P] -> [b, P, ...]


class QuarterCarRoad(LinearModel):
    """The full quarter car driven by the road (SPEC § 1, § 9).

    state (v3, v2, v1, q3, q2, q1) (the order of ``/split/state0``), A = [[D, S], [I, 0]];
    input: road u in metres, B = p_u e_v1 with p_u = p10 - p9, or, with ``scaled_road``, the
    wheel forcing f = p_u u itself, B = e_v1; outputs (a3, a2, a1) = D v + S q + (0, 0, f):
    C = [D, S], E = B's top half.
    """

    linear_in_params = True
    param_names = PARAM_NAMES
    state_names = ("v3", "v2", "v1", "q3", "q2", "q1")
    output_names = CHANNELS

    def __init__(self, scaled_road: bool = False) -> None:
        self.scaled_road = bool(scaled_road)
        self.name = "quarter_car_scaled_road" if self.scaled_road else "quarter_car_road"
        self.input_names = ("f",) if self.scaled_road else ("u",)

    def matrices(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        self.check_params(p)
        A = system_matrix(p)
        D, S = params_to_matrices(p)
        gain = torch.ones_like(p[:, 0]) if self.scaled_road else road_gain(p)
        zero = torch.zeros_like(gain)
        B = torch.stack([zero, zero, gain, zero, zero, zero], -1)[..., None]  # out of place: vmap/jacfwd-safe
        return A, B, torch.cat([D, S], -1), B[:, :3].clone()


class SeatBaseExcitation(LinearModel):
    """Road-free seat model (SPEC § 9): the chassis acceleration a2 drives the seat, a3 is read.

    z = q3 - q2, state (dz/dt, z), params (p1, p2):  z'' = a3 - a2,  a3 = -p1 z' - p2 z, so
    A = [[-p1, -p2], [1, 0]], B = (-1, 0), C = [-p1, -p2], E = 0 and
    A3(s)/A2(s) = (p1 s + p2)/(s^2 + p1 s + p2).
    """

    name = "seat_base_excitation"
    linear_in_params = True
    param_names = ("p1", "p2")
    state_names = ("dz", "z")
    input_names = ("a2",)
    output_names = ("a3",)

    def matrices(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        self.check_params(p)
        p1, p2 = p.unbind(-1)
        zero, one = torch.zeros_like(p1), torch.ones_like(p1)
        A = torch.stack([torch.stack([-p1, -p2], -1), torch.stack([one, zero], -1)], -2)
        B = torch.stack([-one, zero], -1)[..., None]
        C = torch.stack([-p1, -p2], -1)[:, None, :]
        return A, B, C, zero[:, None, None]


class SprungBaseExcitation(LinearModel):
    """Road-free sprung part (SPEC § 9): the wheel acceleration a1 drives seat and chassis.

    State relative to the wheel, w3 = q3 - q1, w2 = q2 - q1, ordered (dw3, dw2, w3, w2);
    params p1..p6. From SPEC § 1 (v3 - v2 = dw3 - dw2, v2 - v1 = dw2, q2 - q1 = w2):

        a3 = -p1 (dw3 - dw2) - p2 (w3 - w2)
        a2 =  p3 (dw3 - dw2) + p5 (w3 - w2) - p4 dw2 - p6 w2
        w3'' = a3 - a1,   w2'' = a2 - a1

    so C = the first two rows of A, B = (-1, -1, 0, 0), E = 0; outputs (a3, a2).
    """

    name = "sprung_base_excitation"
    linear_in_params = True
    param_names = tuple(f"p{i}" for i in range(1, 7))
    state_names = ("dw3", "dw2", "w3", "w2")
    input_names = ("a1",)
    output_names = ("a3", "a2")

    def matrices(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        self.check_params(p)
        p1, p2, p3, p4, p5, p6 = p.unbind(-1)
        zero, one = torch.zeros_like(p1), torch.ones_like(p1)
        C = torch.stack(
            [
                torch.stack([-p1, p1, -p2, p2], -1),
                torch.stack([p3, -(p3 + p4), p5, -(p5 + p6)], -1),
            ],
            -2,
        )
        kinematics = torch.stack(
            [torch.stack([one, zero, zero, zero], -1), torch.stack([zero, one, zero, zero], -1)], -2
        )
        A = torch.cat([C, kinematics], -2)
        B = torch.stack([-one, -one, zero, zero], -1)[..., None]
        return A, B, C, torch.zeros(p.shape[0], 2, 1, dtype=p.dtype, device=p.device)


class SeatOccupantBaseExcitation(LinearModel):
    """Road-free seat model with a seated person (SPEC § 10, physics/occupant.py): the chassis
    acceleration a2 drives the seat pan, a3 is the pan's acceleration; the occupant is a rigid part
    with ``n_modes`` (1 or 2) body modes hung on it. params (p1, p2, r1, k1, c1[, r2, k2, c2]),
    state (dz, dy1[, dy2], z, y1[, y2]) with z = q_pan - q2 and y_i = q_i - q_pan:

        a3 = R (-p1 dz - p2 z) + Σ r_i (c_i dy_i + k_i y_i),   R = 1 + Σ r_i
        dz' = a3 - a2,   dy_i' = -(c_i dy_i + k_i y_i) - a3

    Not linear in the parameters (R p1, r_i k_i): derivatives by torch.func.jacfwd. n_modes = 0 is
    SeatBaseExcitation.
    """

    linear_in_params = False
    multi_affine = True  # R p1, r c, r k: products of different parameters
    input_names = ("a2",)
    output_names = ("a3",)

    def __init__(self, n_modes: int = 1) -> None:
        from hybridqcm.physics.occupant import occupant_param_names

        if n_modes not in (1, 2):
            raise ValueError(f"seat occupant: n_modes must be 1 or 2 (0 is SeatBaseExcitation), got {n_modes!r}")
        self.n_modes = int(n_modes)
        self.name = f"seat_body{self.n_modes}_base_excitation"
        self.param_names = occupant_param_names(self.n_modes)
        modes = range(1, self.n_modes + 1)
        self.nested_at_zero = {f"r{i}": (f"k{i}", f"c{i}", f"dy{i}", f"y{i}") for i in modes}  # r_i = 0: no mass
        self.state_names = ("dz",) + tuple(f"dy{i}" for i in modes) + ("z",) + tuple(f"y{i}" for i in modes)

    def matrices(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        self.check_params(p)
        n, b = self.n_modes, p.shape[0]
        modes = p[:, 2:].reshape(b, n, 3)
        r, k, c = modes[..., 0], modes[..., 1], modes[..., 2]
        R = 1.0 + r.sum(-1)
        # a3 = C x, x = (dz, dy, z, y): the pan's acceleration
        C = torch.cat([(-R * p[:, 0])[:, None], r * c, (-R * p[:, 1])[:, None], r * k], -1)  # [b, 2 + 2n]
        # dy_i' = -(c_i dy_i + k_i y_i) - a3: row i is -C with the mode's own terms added
        own = torch.cat(
            [
                torch.zeros(b, n, 1, dtype=p.dtype, device=p.device),
                torch.diag_embed(c),
                torch.zeros(b, n, 1, dtype=p.dtype, device=p.device),
                torch.diag_embed(k),
            ],
            -1,
        )
        rows_dy = -C[:, None, :].expand(b, n, -1) - own
        kinematics = torch.cat(
            [
                torch.eye(1 + n, dtype=p.dtype, device=p.device).expand(b, -1, -1),
                torch.zeros(b, 1 + n, 1 + n, dtype=p.dtype, device=p.device),
            ],
            -1,
        )
        A = torch.cat([C[:, None, :], rows_dy, kinematics], -2)
        B = torch.zeros(b, 2 + 2 * n, 1, dtype=p.dtype, device=p.device)
        B = torch.cat([-torch.ones(b, 1, 1, dtype=p.dtype, device=p.device), B[:, 1:]], -2)  # out of place (vmap)
        return A, B, C[:, None, :], torch.zeros(b, 1, 1, dtype=p.dtype, device=p.device)


def _hang_body(A: Tensor, B: Tensor, C: Tensor, E: Tensor, body: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """A rigid-occupant model's matrices with the person's body modes hung on its seat pan (SPEC § 10).

    The rigid model (A [b, 2v, 2v], B [b, 2v, m], C [b, o, 2v], E [b, o, m]) must have the state
    (v velocities, then their v displacements), the pan's velocity first, output 0 = a3 = C[0] x with
    E[0] = 0, and A's pan row equal to C[0] (the pan's velocity state moves with a3, less a driving
    acceleration through B). body [b, 3n]: (r_i, k_i, c_i) per mode (physics/occupant.py). Returns the
    matrices of the state (v velocities, dy_1..dy_n, v displacements, y_1..y_n), y_i = q_i - q_pan:

        a3  = R C[0] x + Σ r_i (c_i dy_i + k_i y_i),     R = 1 + Σ r_i
        dy_i' = -(c_i dy_i + k_i y_i) - a3,   y_i' = dy_i

    every other row and output as the rigid model's (none of them sees the body but through the pan).
    Built out of place (torch.func.jacfwd/vmap differentiate it)."""
    b, N = A.shape[0], A.shape[-1]
    v, n = N // 2, body.shape[-1] // 3
    modes = body.reshape(b, n, 3)
    r, k, c = modes[..., 0], modes[..., 1], modes[..., 2]
    R = 1.0 + r.sum(-1)

    def widen(rows: Tensor) -> Tensor:  # [b, k, 2v] -> [b, k, 2v + 2n]: zero columns for (dy, y)
        zeros = rows.new_zeros(rows.shape[0], rows.shape[1], n)
        return torch.cat([rows[..., :v], zeros, rows[..., v:], zeros], -1)

    pan = widen(R[:, None, None] * C[:, :1])  # [b, 1, 2v + 2n]
    pan = pan + torch.cat([pan.new_zeros(b, 1, v), (r * c)[:, None], pan.new_zeros(b, 1, v), (r * k)[:, None]], -1)
    own = torch.cat(
        [A.new_zeros(b, n, v), torch.diag_embed(c), A.new_zeros(b, n, v), torch.diag_embed(k)], -1
    )  # [b, n, 2v + 2n]
    kinematics = torch.cat(
        [torch.eye(v + n, dtype=A.dtype, device=A.device).expand(b, -1, -1), A.new_zeros(b, v + n, v + n)], -1
    )
    A_new = torch.cat([pan, widen(A[:, 1:v]), -pan.expand(b, n, -1) - own, kinematics], -2)
    zeros_in = B.new_zeros(b, n, B.shape[-1])
    B_new = torch.cat([B[:, :v], zeros_in, B[:, v:], zeros_in], -2)
    C_new = torch.cat([pan, widen(C[:, 1:])], -2)
    return A_new, B_new, C_new, E


class _PersonOnPan(LinearModel):
    """A rigid-occupant model (``rigid``) with a seated person of ``n_modes`` body modes on its pan:
    params (rigid's p, r1, k1, c1[, r2, k2, c2]) (physics/occupant.py's body parameters after the
    vehicle's), state (velocities, dy1[, dy2], displacements, y1[, y2]) (_hang_body)."""

    linear_in_params = False
    multi_affine = True  # the rigid model's rows (linear in its p) times R, plus r c, r k (_hang_body)

    def __init__(self, rigid: LinearModel, n_modes: int, name: str) -> None:
        from hybridqcm.physics.occupant import MODE_PARAMS

        if n_modes not in (1, 2):
            raise ValueError(f"{name}: n_modes must be 1 or 2 (0 is the rigid occupant: {rigid.name}), got {n_modes!r}")
        self.rigid, self.n_modes = rigid, int(n_modes)
        self.name = name
        modes = range(1, self.n_modes + 1)
        self.param_names = tuple(rigid.param_names) + tuple(f"{k}{i}" for i in modes for k in MODE_PARAMS)
        self.nested_at_zero = {f"r{i}": (f"k{i}", f"c{i}", f"dy{i}", f"y{i}") for i in modes}  # r_i = 0: no mass
        v = rigid.n_state // 2
        self.state_names = (
            tuple(rigid.state_names[:v])
            + tuple(f"dy{i}" for i in modes)
            + tuple(rigid.state_names[v:])
            + tuple(f"y{i}" for i in modes)
        )
        self.input_names = tuple(rigid.input_names)
        self.output_names = tuple(rigid.output_names)

    def matrices(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        self.check_params(p)
        P = self.rigid.n_params
        return _hang_body(*self.rigid.matrices(p[:, :P]), p[:, P:])


class SprungOccupantBaseExcitation(_PersonOnPan):
    """Road-free sprung part (SprungBaseExcitation: a1 drives chassis + seat, outputs a3, a2) with a
    seated person of ``n_modes`` body modes on the seat pan; params (p1..p6, r1, k1, c1[, r2, k2, c2]),
    state (dw3, dw2, dy1[, dy2], w3, w2, y1[, y2]), w3 = q_pan - q1, w2 = q2 - q1, y_i = q_i - q_pan.

    Newton per body (z = w3 - w2 the pan's deflection on the seat spring; masses m_s (pan + the body's
    rigid part), m_i (body modes), M = m_s + Σ m_i the static mass; k_i, c_i per unit m_i):

        m_s a3    = -C3 z' - K3 z + Σ m_i (c_i y_i' + k_i y_i)     (pan: seat spring below, bodies above)
        m_i a_i   = -m_i (c_i y_i' + k_i y_i)                      (body i, a_i = a3 + y_i'')
        m2 a2     = C3 z' + K3 z - C2 w2' - K2 w2                  (chassis: the seat spring's force only)

    Divided by m_s = M/R, by m_i and by m2, with p1 = C3/M, p2 = K3/M, p3 = C3/m2, p5 = K3/m2 (their
    meaning kept: the chassis sees C3 z' + K3 z, whatever rides on the pan), r_i = m_i/m_s:

        a3 = R (-p1 z' - p2 z) + Σ r_i (c_i y_i' + k_i y_i)
        a2 = p3 z' + p5 z - p4 w2' - p6 w2
        w3'' = a3 - a1,  w2'' = a2 - a1,  y_i'' = -(c_i y_i' + k_i y_i) - a3

    Its seat part is SeatOccupantBaseExcitation's; r_i -> 0 is SprungBaseExcitation.
    """

    def __init__(self, n_modes: int = 1) -> None:
        super().__init__(SprungBaseExcitation(), n_modes, f"sprung_body{int(n_modes)}_base_excitation")


class QuarterCarOccupantRoad(_PersonOnPan):
    """The road-driven quarter car (QuarterCarRoad) with a seated person of ``n_modes`` body modes on the
    seat pan; params (p1..p10, r1, k1, c1[, r2, k2, c2]), state (v3, v2, v1, dy1[, dy2], q3, q2, q1,
    y1[, y2]), index 3 the pan, y_i = q_i - q3; input u (or f = p_u u with ``scaled_road``); outputs
    (a3, a2, a1), a3 the pan's acceleration.

    Newton per body (z = q3 - q2; as SprungOccupantBaseExcitation, the wheel as in SPEC § 1):

        m_s a3 = -C3 z' - K3 z + Σ m_i (c_i y_i' + k_i y_i)
        m_i a_i = -m_i (c_i y_i' + k_i y_i)                       (a_i = a3 + y_i'')
        m2 a2  = C3 z' + K3 z - C2 (v2 - v1) - K2 (q2 - q1)
        m1 a1  = C2 (v2 - v1) + K2 (q2 - q1) - C1 v1 - K1 (q1 - u)

    so a3 = R (-p1 z' - p2 z) + Σ r_i (c_i y_i' + k_i y_i), the chassis and wheel rows are SPEC § 1's
    (p3 = C3/m2, p5 = K3/m2 on the pan's deflection), y_i'' = -(c_i y_i' + k_i y_i) - a3: the matrix of
    physics/seated.py (qcm-simulate occupant=body1|body2) with the states reordered.
    r_i -> 0 is QuarterCarRoad.
    """

    def __init__(self, n_modes: int = 1, scaled_road: bool = False) -> None:
        rigid = QuarterCarRoad(scaled_road=scaled_road)
        self.scaled_road = rigid.scaled_road
        suffix = "_scaled_road" if self.scaled_road else "_road"
        super().__init__(rigid, n_modes, f"quarter_car_body{int(n_modes)}{suffix}")
