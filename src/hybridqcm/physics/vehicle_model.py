"""The half car and the full car as linear models, from their energies (source ch. 2.2.3-2.2.4).

Generalised coordinates x (physics/vehicle_geometry.py: seats z3, chassis heave z2, wheels z1<w>,
pitch α, roll β). Every spring-damper pair e stretches by a linear function of x (and of the road):

    seat s:        δ = z3_s − (z2 + x_s α + y_s β)                   k3_s, c3_s
    suspension w:  δ = (z2 + x_w α + y_w β) − z1w                    k2w,  c2w
    tyre w:        δ = z1w − u_w                                     k1w,  c1w

Written δ_e = g_eᵀ x − r_e u with g_e the element's coefficient vector, the energies are

    T = ½ ẋᵀ M ẋ,   M = diag(m3_s, m2, m1w, I_pitch, I_roll)
    V = ½ Σ_e k_e (g_eᵀ x − r_e u)²,   U = ½ Σ_e c_e (g_eᵀ ẋ − r_e u̇)²     (Rayleigh)

and Lagrange's equations d/dt ∂T/∂ẋ + ∂U/∂ẋ + ∂V/∂x = 0 give

    M ẍ + C ẋ + K x = F u + G u̇,   K = Σ_e k_e g_e g_eᵀ,  C = Σ_e c_e g_e g_eᵀ,
    F = Σ_tyres k1w e_z1w e_wᵀ,     G = Σ_tyres c1w e_z1w e_wᵀ.

Static equilibrium is the reference (gravity drops out of the linear equations). For the half car
with its seat at x_s = −l_b this is the source's HCM with its printed pitch row corrected (SPEC
§ 10): I α̈ = −(L_b²(C3 + C2b) + L_f² C2f) α̇ − (L_b²(K3 + K2b) + L_f² K2f) α + ... ;
tests/test_vehicle_model.py derives the same equations independently from T, V, U with sympy.

As a LinearModel (physics/linear_models.py): state (v, q) = (ẋ, x), inputs the wheels' road
heights u<w> [m] (and, with damped tyres, their velocities du<w> [m/s]), outputs every
acceleration ẍ:

    A = [[−M⁻¹C, −M⁻¹K], [I, 0]],   B = [[M⁻¹F (, M⁻¹G)], [0]],   C_out = A[:n_dof],  E = B[:n_dof].

The model's parameters are the layout's physical ones (less the tyre dampings where tyres are
undamped); A is not linear in them (1/m, k l², ...), so derivatives come from torch.func.jacfwd.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybridqcm.physics.linear_models import LinearModel
from hybridqcm.physics.vehicle_geometry import VehicleLayout, columns, point_motion, seat_position, unit, wheel_position


def _elements(layout: VehicleLayout, values) -> tuple[Tensor, Tensor, Tensor]:
    """(g [b, E, n_dof], k [b, E], c [b, E]) of every spring-damper pair: seats, suspensions, tyres."""
    g, k, c = [], [], []
    like = values["m2"]
    for seat in layout.seat_names:
        x, y = seat_position(layout, values, seat)
        g.append(unit(layout, layout.seat_dof(seat), like) - point_motion(layout, x, y))
        k.append(values[layout.seat_param("k3", seat)])
        c.append(values[layout.seat_param("c3", seat)])
    for wheel in layout.wheels:
        x, y = wheel_position(layout, values, wheel)
        g.append(point_motion(layout, x, y) - unit(layout, layout.wheel_dof(wheel), like))
        k.append(values[f"k2{wheel}"])
        c.append(values[f"c2{wheel}"])
    for wheel in layout.wheels:
        g.append(unit(layout, layout.wheel_dof(wheel), like))
        k.append(values[f"k1{wheel}"])
        c.append(values.get(f"c1{wheel}", torch.zeros_like(like)))
    return torch.stack(g, -2), torch.stack(k, -1), torch.stack(c, -1)


def _masses(layout: VehicleLayout, values) -> Tensor:
    """diag(M) [b, n_dof] in state order."""
    entries = [values[layout.seat_param("m3", s)] for s in layout.seat_names] + [values["m2"]]
    entries += [values[f"m1{w}"] for w in layout.wheels] + [values["I_pitch"]]
    if layout.full:
        entries.append(values["I_roll"])
    return torch.stack(entries, -1)


def vehicle_matrices(layout: VehicleLayout, physical: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """(M, C, K [b, n, n], F, G [b, n, n_wheels]) of M ẍ + C ẋ + K x = F u + G u̇ for physical [b, P]
    (the layout's param_names, tyre dampings included)."""
    values = columns(layout.param_names, physical)
    return _assemble(layout, values)


def _assemble(layout: VehicleLayout, values) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    g, k, c = _elements(layout, values)
    K = torch.einsum("be,bei,bej->bij", k, g, g)
    C = torch.einsum("be,bei,bej->bij", c, g, g)
    M = torch.diag_embed(_masses(layout, values))
    n_w = len(layout.wheels)
    tyres = g[:, -n_w:, :].transpose(1, 2)  # [b, n, n_w]: e_z1w per wheel column
    F = tyres * k[:, None, -n_w:]
    G = tyres * c[:, None, -n_w:]
    return M, C, K, F, G


class VehicleModel(LinearModel):
    """The half car or full car of ``layout`` driven by its wheels' road inputs (module docstring).

    params [b, P] in the order of ``param_names`` (layout.model_param_names); state (v_<dof>, q_<dof>);
    inputs u<w> (and du<w> with damped tyres); outputs a_<dof> (every acceleration)."""

    linear_in_params = False

    def __init__(self, layout: VehicleLayout) -> None:
        self.layout = layout
        self.name = f"{layout.kind}_road"
        self.param_names = layout.model_param_names
        dofs = layout.dofs
        self.state_names = tuple(f"v_{d}" for d in dofs) + tuple(f"q_{d}" for d in dofs)
        self.input_names = tuple(f"u{w}" for w in layout.wheels) + (
            tuple(f"du{w}" for w in layout.wheels) if layout.tyre_damping else ()
        )
        self.output_names = tuple(f"a_{d}" for d in dofs)
        # the seats' coordinates may take either sign (estimation/response.py reads this)
        self.signed_params = tuple(n for n in self.param_names if n in layout.signed_names)

    def physical(self, p: Tensor) -> Tensor:
        """The full physical vector [b, len(layout.param_names)] (tyre dampings 0 where undamped)."""
        if self.layout.tyre_damping:
            return p
        names = self.layout.param_names
        zero = torch.zeros_like(p[:, 0])
        given = {n: p[:, j] for j, n in enumerate(self.param_names)}
        return torch.stack([given.get(n, zero) for n in names], -1)

    def model_params(self, physical: Tensor) -> Tensor:
        """physical [b, len(layout.param_names)] -> the model's params [b, P]."""
        index = [self.layout.param_names.index(n) for n in self.param_names]
        return physical[:, index]

    def matrices(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        self.check_params(p)
        values = {n: p[:, j] for j, n in enumerate(self.param_names)}
        M, C, K, F, G = _assemble(self.layout, values)
        inverse = 1.0 / torch.diagonal(M, dim1=-2, dim2=-1)  # [b, n]
        n = self.layout.n_dof
        top = -torch.cat([C, K], -1) * inverse[:, :, None]  # [b, n, 2n]
        kinematics = torch.cat(
            [torch.eye(n, dtype=p.dtype, device=p.device), torch.zeros(n, n, dtype=p.dtype, device=p.device)], -1
        ).expand(p.shape[0], n, 2 * n)
        A = torch.cat([top, kinematics], -2)
        forcing = torch.cat([F, G], -1) if self.layout.tyre_damping else F
        B_top = forcing * inverse[:, :, None]
        B = torch.cat([B_top, torch.zeros_like(B_top)], -2)
        return A, B, top, B_top

    def matrix_derivatives(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Analytic derivatives (see _derivative_plan): M⁻¹ X(θ) with X = [C K | F G] affine in each
        stiffness and damping and bilinear in (k, c) and the geometry, so

            d/dm_i:        row i of every top block times -1/m_i
            d/dk_e, dc_e:  -M⁻¹ [0 | g_e g_eᵀ], -M⁻¹ [g_e g_eᵀ | 0] (tyres: also +M⁻¹ in B)
            d/d(geometry): -M⁻¹ [dC | dK],  dK = Σ_e k_e (dg_e g_eᵀ + g_e dg_eᵀ), dg_e constant.

        Same values as torch.func.jacfwd of ``matrices`` (tests), about twice as fast."""
        self.check_params(p)
        plan = _derivative_plan(self.layout, self.param_names, p.dtype, p.device)
        values = {n: p[:, j] for j, n in enumerate(self.param_names)}
        g, k, c = _elements(self.layout, values)  # [b, E, n], [b, E]
        masses = _masses(self.layout, values)  # [b, n]
        inverse = 1.0 / masses
        A, B, top, B_top = self.matrices(p)
        outer = g[:, :, :, None] * g[:, :, None, :]  # [b, E, n, n]
        # stiffness / damping parameters: g_e g_eᵀ; geometry: Σ_e k_e (dg g + g dg)
        dK = torch.einsum("pe,beij->bpij", plan["k_select"], outer)
        dC = torch.einsum("pe,beij->bpij", plan["c_select"], outer)
        if plan["has_geometry"]:
            cross_k = torch.einsum("be,pei,bej->bpij", k, plan["dg"], g)
            cross_c = torch.einsum("be,pei,bej->bpij", c, plan["dg"], g)
            dK = dK + cross_k + cross_k.transpose(-1, -2)
            dC = dC + cross_c + cross_c.transpose(-1, -2)
        d_top = -torch.cat([dC, dK], -1) * inverse[:, None, :, None]  # [b, P, n, 2n]
        n_w = len(self.layout.wheels)
        d_forcing = plan["b_select"][None] * inverse[:, None, :, None]  # [b, P, n, m]
        # masses: row i of top (and of B_top) times -1/m_i
        mass_rows = plan["mass_select"]  # [P, n] one-hot rows of the mass parameters
        scale = -mass_rows[None] * inverse[:, None, :]  # [b, P, n]
        d_top = d_top + scale[..., None] * top[:, None]
        d_forcing = d_forcing + scale[..., None] * B_top[:, None]
        del n_w
        n = self.layout.n_dof
        dA = torch.cat([d_top, torch.zeros_like(d_top)], -2)
        dB = torch.cat([d_forcing, torch.zeros_like(d_forcing)], -2)
        assert dA.shape[-2:] == (2 * n, 2 * n)
        return dA, dB, d_top, d_forcing


_PLANS: dict = {}


def _derivative_plan(layout: VehicleLayout, names: tuple[str, ...], dtype, device) -> dict:
    """Constant pieces of the derivatives, per parameter j: which element's stiffness/damping it is
    (k_select, c_select [P, E]), which mass row it scales (mass_select [P, n]), where it enters B
    (b_select [P, n, m]) and the derivative of every element's coefficient vector (dg [P, E, n])."""
    key = (layout, names, dtype, str(device))
    if key in _PLANS:
        return _PLANS[key]
    seats, wheels = layout.seat_names, layout.wheels
    n, n_w = layout.n_dof, len(wheels)
    elements = [("seat", s) for s in seats] + [("suspension", w) for w in wheels] + [("tyre", w) for w in wheels]
    index = {e: i for i, e in enumerate(elements)}
    P, E = len(names), len(elements)
    m = n_w * (2 if layout.tyre_damping else 1)
    k_select = torch.zeros(P, E, dtype=dtype)
    c_select = torch.zeros(P, E, dtype=dtype)
    mass_select = torch.zeros(P, n, dtype=dtype)
    b_select = torch.zeros(P, n, m, dtype=dtype)
    dg = torch.zeros(P, E, n, dtype=dtype)
    pitch = layout.angle_dof("pitch")
    roll = layout.angle_dof("roll") if layout.full else None
    mass_rows = {layout.seat_param("m3", s): layout.seat_dof(s) for s in seats}
    mass_rows.update({"m2": layout.chassis_dof, "I_pitch": pitch})
    mass_rows.update({f"m1{w}": layout.wheel_dof(w) for w in wheels})
    if layout.full:
        mass_rows["I_roll"] = roll
    for j, name in enumerate(names):
        if name in mass_rows:
            mass_select[j, mass_rows[name]] = 1.0
            continue
        for s in seats:
            if name == layout.seat_param("k3", s):
                k_select[j, index[("seat", s)]] = 1.0
            elif name == layout.seat_param("c3", s):
                c_select[j, index[("seat", s)]] = 1.0
            elif name == layout.seat_param("x_s", s):
                dg[j, index[("seat", s)], pitch] = -1.0
            elif layout.full and name == layout.seat_param("y_s", s):
                dg[j, index[("seat", s)], roll] = -1.0
        for i, w in enumerate(wheels):
            if name == f"k2{w}":
                k_select[j, index[("suspension", w)]] = 1.0
            elif name == f"c2{w}":
                c_select[j, index[("suspension", w)]] = 1.0
            elif name == f"k1{w}":
                k_select[j, index[("tyre", w)]] = 1.0
                b_select[j, layout.wheel_dof(w), i] = 1.0
            elif name == f"c1{w}":
                c_select[j, index[("tyre", w)]] = 1.0
                b_select[j, layout.wheel_dof(w), n_w + i] = 1.0
            # suspension points: x = l_f (front) or -l_b (back), y = w_r (right) or -w_l (left)
            elif name == "l_f" and w.startswith("f"):
                dg[j, index[("suspension", w)], pitch] = 1.0
            elif name == "l_b" and w.startswith("b"):
                dg[j, index[("suspension", w)], pitch] = -1.0
            elif name == "w_r" and w.endswith("r") and layout.full:
                dg[j, index[("suspension", w)], roll] = 1.0
            elif name == "w_l" and w.endswith("l") and layout.full:
                dg[j, index[("suspension", w)], roll] = -1.0
    plan = {
        "k_select": k_select.to(device),
        "c_select": c_select.to(device),
        "mass_select": mass_select.to(device),
        "b_select": b_select.to(device),
        "dg": dg.to(device),
        "has_geometry": bool(dg.abs().sum() > 0),
    }
    _PLANS[key] = plan
    return plan


__all__ = ["VehicleModel", "vehicle_matrices"]
