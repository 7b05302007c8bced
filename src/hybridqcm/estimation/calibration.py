"""Seat calibration (issue 31): the mass scale of a real seat from drives with known loads.

The road-free seat model (SPEC § 9) identifies p2 = K3 / M and p1 = C3 / M, M the static mass on the seat
spring; the mass itself only through K3. A foam seat stiffens under load and its pan moves with the
occupant, so no single K3 fits all occupants. The law fitted here:

    K3(M) = K3_ref (M / M_ref)^e,   C3(M) = C3_ref (M / M_ref)^e_c,   M = load + m_pan,   M_ref = 80 kg,

from drives with known loads L_i (ballast; 0 = the empty seat), each recording's fitted p2_i with its
standard deviation σ_i:

    ln p2_i = ln K3_ref - e ln M_ref + (e - 1) ln(L_i + m_pan)        θ = (ln K3_ref, e, m_pan)

a weighted nonlinear least-squares problem (weights 1/σ_rel,i, σ_rel,i = σ_i / p2_i, floored at
``rel_floor``: the exact model's own p2 error on noise-free data), solved by Gauss-Newton with a
Levenberg damping, started from the linear seat (e = 0: 1/p2 = (L + m_pan)/K3 is a straight line in L).
The law's complexity is the data's choice (``law="auto"``): of the nested laws (NESTED: e and / or m_pan
held at 0, down to K3 alone, the reference seat's form) the simplest whose misfit the most complex one the
loads determine does not beat by the nested F-test at level alpha (a seat driven empty keeps its pan: its
spring carries nothing else); the fit reports every candidate's χ² and p-value and which it chose.
``law="power"`` / ``"linear"`` / ... fit that one. The covariance is the chosen law's Gauss-Newton
(JᵀWJ)⁻¹ over its free parameters (0 for the held ones) widened by the Birge factor max(1, χ²/dof) where
the recordings scatter more than their σ say; then the scale is an estimate and an occupant's interval adds
the calibration's part with the Student-t quantile at that dof. Not narrowed where they scatter less: the
road-free fits state σ too wide at heavy loads and too narrow at light ones (one-window errors heavy-tailed
there), and χ²/dof, dominated by the heavy loads, then understates the pan's and exponent's errors (measured:
docs/measurements/calibration.md). With m_pan fixed, C3's law is a weighted linear fit of ln p1 in ln M.

An estimate inverts the law at each recording's p2: M solves p2 = K3(M)/M, in closed form for the power law,

    M = (K3_ref / (p2 M_ref^e))^(1 / (1 - e)),     occupant = M - m_pan,

with ∂ln M/∂ln K3_ref = 1/(1-e), ∂ln M/∂ln p2 = -1/(1-e), ∂ln M/∂e = (ln M - ln M_ref)/(1-e), ∂occ/∂m_pan = -1;
the occupant's 95 % interval joins the image of p2's interval and the calibration's delta-method standard
deviation in quadrature on each side.

The seat file is JSON (never executed, never unpickled): ``format``, the law, its covariance, the loads used,
the fit's residuals and leave-one-load-out errors, and a sha256 over its own content, so a file from
another tool or one edited by hand is refused in one line (SeatFileError).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hybridqcm.errors import HybridQCMError

FORMAT = "hybridqcm.seat/1"
REFERENCE_LOAD = 80.0  # kg: K3_ref, C3_ref are the seat's at this static load
PARAMETERS = ("K3_ref", "exponent", "pan_mass")
# The nested laws, most complex first, by which of PARAMETERS they fit (the others held at 0): power
# K3_ref (M/80)^e with a pan; linear: e = 0 (K3 constant) with a pan; power_without_pan; proportional: K3
# constant and no pan, the reference seat's form (m3 = K3 / p2).
NESTED = {
    "power": (True, True, True),
    "linear": (True, False, True),
    "power_without_pan": (True, True, False),
    "proportional": (True, False, False),
}
LAWS = ("auto", *NESTED)  # what qcm-calibrate's law= may name; auto chooses among NESTED (fit_seat_law)
MAX_FILE_BYTES = 1 << 20


class CalibrationError(HybridQCMError):
    """Calibration data that cannot determine the seat (one line)."""


class SeatFileError(HybridQCMError):
    """A seat file that is not ours, tampered or malformed (one line)."""


@dataclass
class SeatLaw:
    """K3(M) = K3_ref (M / reference_load)^exponent with a seat pan of pan_mass kg; covariance [3, 3] over
    PARAMETERS (K3_ref [N/m], exponent, pan_mass [kg]). C3's law (C3_ref, c3_exponent) is informational."""

    K3_ref: float
    exponent: float
    pan_mass: float
    covariance: np.ndarray
    law: str = "power"
    reference_load: float = REFERENCE_LOAD
    C3_ref: float | None = None
    c3_exponent: float | None = None
    loads: list = field(default_factory=list)  # the calibration's distinct loads [kg]
    dof: int | None = None  # the calibration's dof where its scale was estimated (Birge > 1): Student-t intervals

    @property
    def free(self) -> list[str]:
        """The parameters this law fitted (NESTED); the others are held at 0 (their covariance rows are 0)."""
        return [name for name, fitted in zip(PARAMETERS, NESTED[self.law]) if fitted]

    def k3(self, total_mass):
        """K3 [N/m] at the static load ``total_mass`` (pan + occupant) [kg], any shape."""
        return self.K3_ref * (np.asarray(total_mass, float) / self.reference_load) ** self.exponent

    def total_mass(self, p2):
        """The static mass M on the spring [kg] with p2 = K3(M)/M (closed form), any shape; nan where p2 <= 0."""
        p2 = np.asarray(p2, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = self.K3_ref / (np.where(p2 > 0, p2, np.nan) * self.reference_load**self.exponent)
            return ratio ** (1.0 / (1.0 - self.exponent))

    def occupant_mass(self, p2):
        """The occupant alone [kg]: M(p2) - pan_mass."""
        return self.total_mass(p2) - self.pan_mass

    def calibration_std(self, p2):
        """The occupant mass's standard deviation [kg] from the law's covariance alone (delta method)."""
        M = self.total_mass(p2)
        e = self.exponent
        grad = np.stack(
            [
                M / ((1 - e) * self.K3_ref),
                M * (np.log(M) - math.log(self.reference_load)) / (1 - e),
                -np.ones_like(M),
            ],
            axis=-1,
        )
        return np.sqrt(np.maximum(np.einsum("...i,ij,...j->...", grad, self.covariance, grad), 0.0))

    def occupant_interval(self, p2, p2_low, p2_high, z: float = 1.96):
        """(occupant [kg], low, high) from p2 and its interval [p2_low, p2_high] (the data's) and the law's
        covariance (the calibration's), joined in quadrature on each side. p2_low <= 0: high = inf. The
        calibration's half-width is its standard deviation times the Student-t quantile at its dof (where its
        covariance carries the residuals' scale, an estimate), the normal's z without a dof."""
        occ = self.occupant_mass(p2)
        cal = self.calibration_quantile(z) * self.calibration_std(p2)
        low_data = occ - self.occupant_mass(p2_high)
        high_data = np.where(np.asarray(p2_low) > 0, self.occupant_mass(np.maximum(p2_low, 1e-300)) - occ, np.inf)
        return occ, occ - np.hypot(low_data, cal), occ + np.hypot(high_data, cal)

    def calibration_quantile(self, z: float = 1.96) -> float:
        """The calibration's multiplier of the same coverage as the normal's ±z: t at its dof (z without)."""
        if not self.dof:
            return z
        from scipy.stats import norm, t

        return float(t.ppf(norm.cdf(z), self.dof))

    def occupant_relative_sd(self, p2, sd_ln_p2, calibration: bool = True):
        """σ of the occupant mass over the occupant [any shape] at p2 whose ln has the standard deviation
        ``sd_ln_p2`` (e.g. a Cramér–Rao bound): ∂occ/∂ln p2 = -M/(1-e), joined in quadrature with the
        calibration's delta-method standard deviation where ``calibration``."""
        M = self.total_mass(p2)
        occ = M - self.pan_mass
        var = (M / (1 - self.exponent) * np.asarray(sd_ln_p2, float)) ** 2
        if calibration:
            var = var + self.calibration_std(p2) ** 2
        return np.sqrt(var) / occ

    def covers(self, occupant) -> np.ndarray:
        """True where ``occupant`` [kg] lies within the calibration's loads (no extrapolation)."""
        occupant = np.asarray(occupant, float)
        return (occupant >= min(self.loads)) & (occupant <= max(self.loads))


# ------------------------------------------------------------------------------------------------ fitting
def _model(theta, loads):
    """ln p2 [n] and its Jacobian [n, 3] in θ = (ln K3_ref, e, m_pan)."""
    a, e, m = theta
    total = loads + m
    ln_total = np.log(total)
    pred = a - e * math.log(REFERENCE_LOAD) + (e - 1) * ln_total
    J = np.stack([np.ones_like(loads), ln_total - math.log(REFERENCE_LOAD), (e - 1) / total], axis=1)
    return pred, J


def _start(loads, y, w, free) -> np.ndarray:
    """The linear seat's θ: 1/p2 = (L + m)/K3, a straight line in L (weighted by p2's relative error); with
    the pan fixed at 0 the weighted mean of ln K3 = ln p2 + ln L."""
    if not free[2]:
        lnK = float(np.sum(w**2 * (y + np.log(loads))) / np.sum(w**2))
        return np.array([lnK, 0.0, 0.0])
    A = np.stack([loads, np.ones_like(loads)], axis=1) * w[:, None]
    slope, intercept = np.linalg.lstsq(A, np.exp(-y) * w, rcond=None)[0]
    K = 1.0 / slope if slope > 0 else float(np.exp(np.median(y)) * np.median(loads + 1.0))
    m = intercept * K
    if not m > -loads.min():
        m = max(1.0, -loads.min() + 1.0)
    return np.array([math.log(K), 0.0, m])


def _solve(loads, y, w, free, theta0=None, iterations: int = 200):
    """Weighted least squares of ln p2: θ minimising Σ w_i² (y_i - pred_i)² over the ``free`` [3] bool entries
    (the others held at theta0's, the linear seat's 0 without theta0), by Levenberg-damped Gauss-Newton."""
    free = np.asarray(free, bool)
    theta = np.array(_start(loads, y, w, free) if theta0 is None else theta0, float)
    theta[~free] = 0.0
    lam = 1e-3

    def cost(t):
        if not np.all(loads + t[2] > 0) or t[1] >= 1:
            return math.inf
        return float(np.sum((w * (y - _model(t, loads)[0])) ** 2))

    current = cost(theta)
    for _ in range(iterations):
        pred, J = _model(theta, loads)
        Jw, rw = J[:, free] * w[:, None], w * (y - pred)
        H, g = Jw.T @ Jw, Jw.T @ rw
        improved = False
        for _ in range(30):
            step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-300), g)
            trial = theta.copy()
            trial[free] += step
            new = cost(trial)
            if new < current:
                theta, lam, improved = trial, max(lam / 10, 1e-12), True
                break
            lam *= 10
        if not improved or abs(current - new) <= 1e-15 * max(current, 1e-300):
            current = min(current, new) if improved else current
            break
        current = new
    return theta, current


def _candidates(law: str, loads) -> list[str]:
    """The nested laws ``law`` may choose from, most complex (the reference of the test) first: those the loads
    determine (as many distinct loads as free parameters; no law without a pan where the seat was driven empty:
    nothing would be on its spring)."""
    names = list(NESTED) if law == "auto" else [law]
    distinct = np.unique(loads).size
    return [n for n in names if sum(NESTED[n]) <= distinct and (NESTED[n][2] or loads.min() > 0)]


def _select(fits: dict, n: int, alpha: float) -> tuple[str, list]:
    """The simplest law whose misfit the reference's (the first, most complex) does not beat significantly:
    the nested F-test (Δχ²/Δk) / (χ²_ref / dof_ref) against F(Δk, dof_ref) at level alpha, the scale taken from
    the reference's own residuals (the recordings' σ may be off by a common factor); with dof_ref = 0 the
    likelihood-ratio test Δχ² against χ²(Δk) at the stated σ. Ties in size: the smaller χ²."""
    from scipy.stats import chi2 as chi2_dist
    from scipy.stats import f as f_dist

    names = list(fits)
    ref = names[0]
    k_ref, chi2_ref = sum(NESTED[ref]), fits[ref][1]
    dof_ref = n - k_ref
    table = []
    for name in names:
        k, chi2 = sum(NESTED[name]), fits[name][1]
        nested = all(r or not f for f, r in zip(NESTED[name], NESTED[ref]))
        if name == ref or not nested:
            p = 1.0 if name == ref else None
        elif dof_ref > 0:
            ratio = max(chi2 - chi2_ref, 0.0) / (k_ref - k) / max(chi2_ref / dof_ref, 1e-300)
            p = float(f_dist.sf(ratio, k_ref - k, dof_ref))
        else:
            p = float(chi2_dist.sf(max(chi2 - chi2_ref, 0.0), k_ref - k))
        table.append({"law": name, "free": [q for q, f in zip(PARAMETERS, NESTED[name]) if f], "chi2": chi2,
                      "dof": n - k, "p_value": p})  # fmt: skip
    accepted = [row for row in table if row["p_value"] is not None and row["p_value"] > alpha]
    chosen = min(accepted, key=lambda row: (len(row["free"]), row["chi2"]))["law"]
    for row in table:
        row["chosen"] = row["law"] == chosen
    return chosen, table


def fit_seat_law(
    loads, p2, p2_std, p1=None, p1_std=None, law: str = "auto", rel_floor: float = 1e-4, alpha: float = 0.05
) -> dict:
    """The seat law from recordings with known loads [n] kg and their fitted p2 [n] ± p2_std [n] (and p1 ± p1_std
    for C3). ``law``: "auto" chooses among the nested laws (NESTED) by the F-test at level ``alpha`` (_select);
    "power" / "linear" fit that one. Returns {"law": SeatLaw, "chi2", "dof", "scale", "residual_kg" [n],
    "loo": {load: error_kg [k]}, "selection": [per candidate law: free, chi2, dof, p_value, chosen]}.
    CalibrationError (one line) where the loads cannot determine it."""
    if law not in LAWS:
        raise CalibrationError(f"law={law!r}: choose one of {list(LAWS)}")
    loads, p2, p2_std = (np.asarray(x, float).ravel() for x in (loads, p2, p2_std))
    if not (loads.size == p2.size == p2_std.size) or loads.size == 0:
        raise CalibrationError(f"calibration: {loads.size} loads for {p2.size} p2 values")
    bad = np.flatnonzero(~np.isfinite(loads) | (loads < 0))
    if bad.size:
        raise CalibrationError(
            f"calibration: known_mass[{int(bad[0])}] = {float(loads[bad[0]])!r} kg: give loads >= 0 kg"
        )
    if np.any(~np.isfinite(p2) | (p2 <= 0)):
        raise CalibrationError("calibration: a fitted p2 is not a positive number (leave such recordings out)")
    distinct = np.unique(loads)
    names = _candidates(law, loads)
    if distinct.size >= 2 and not names and loads.min() == 0 and not NESTED[law][2]:
        raise CalibrationError(
            f"calibration: law={law} has no seat pan, but the seat was driven empty (load 0 kg): nothing would be "
            "on its spring; choose a law with a pan (law=auto)"
        )
    if distinct.size < 2 or not names:
        n_free = 2 if law == "auto" else sum(NESTED[law])
        what = "all loads are equal" if distinct.size == 1 else f"{distinct.size} distinct loads"
        raise CalibrationError(
            f"calibration: {what} ({[float(x) for x in distinct]} kg): the {law} law needs at least {n_free} "
            "different loads (e.g. 0, 40, 80, 120 kg)"
        )
    rel = np.maximum(np.where(np.isfinite(p2_std), p2_std / p2, np.inf), rel_floor)
    w, y = 1.0 / rel, np.log(p2)
    fits = {name: _solve(loads, y, w, NESTED[name]) for name in names}
    chosen, selection = _select(fits, loads.size, alpha) if len(names) > 1 else (names[0], [])
    free = np.array(NESTED[chosen])
    theta, chi2 = fits[chosen]
    dof = loads.size - int(free.sum())
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0  # the Birge factor (module docstring: never below 1)
    _, J = _model(theta, loads)
    Jw = J[:, free] * w[:, None]
    cov_theta = np.zeros((3, 3))
    cov_theta[np.ix_(free, free)] = np.linalg.inv(Jw.T @ Jw) * scale
    K3_ref = math.exp(theta[0])
    T = np.diag([K3_ref, 1.0, 1.0])  # d(K3_ref, e, m) / d(ln K3_ref, e, m)
    seat = SeatLaw(
        K3_ref, float(theta[1]), float(theta[2]), T @ cov_theta @ T, law=chosen, loads=distinct.tolist(),
        dof=dof if scale > 1.0 else None,  # the scale estimated from the residuals: Student-t
    )  # fmt: skip
    if p1 is not None:
        seat.C3_ref, seat.c3_exponent = _fit_c3(loads + seat.pan_mass, np.asarray(p1, float), p1_std, rel_floor)
    residual = seat.occupant_mass(p2) - loads
    loo = {}
    for load in distinct:
        keep = loads != load
        if np.unique(loads[keep]).size < free.sum():
            continue
        t, _ = _solve(loads[keep], y[keep], w[keep], free, theta0=theta)
        other = SeatLaw(math.exp(t[0]), float(t[1]), float(t[2]), np.zeros((3, 3)), law=chosen)
        loo[float(load)] = other.occupant_mass(p2[~keep]) - load
    return {
        "law": seat,
        "chi2": float(chi2),
        "dof": int(dof),
        "scale": float(scale),
        "residual_kg": residual,
        "loo": loo,
        "selection": selection,
    }


def _fit_c3(total, p1, p1_std, rel_floor: float) -> tuple[float, float]:
    """(C3_ref, e_c) from ln p1 = ln C3_ref - e_c ln M_ref + (e_c - 1) ln M, weighted linear least squares."""
    std = np.zeros_like(p1) if p1_std is None else np.asarray(p1_std, float)  # none given: equal weights
    w = 1.0 / np.maximum(np.where(np.isfinite(std) & (p1 > 0), std / np.abs(p1), np.inf), rel_floor)
    ok = p1 > 0
    A = np.stack([np.ones(ok.sum()), np.log(total[ok]) - math.log(REFERENCE_LOAD)], axis=1) * w[ok, None]
    b = (np.log(p1[ok]) + np.log(total[ok])) * w[ok]  # ln C3(M) = ln p1 + ln M = ln C3_ref + e_c (ln M - ln M_ref)
    (a, e_c), *_ = np.linalg.lstsq(A, b, rcond=None)
    return float(math.exp(a)), float(e_c)


# ------------------------------------------------------------------------------------------------ the file
def _checksum(payload: dict) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def seat_document(seat: SeatLaw, extra: dict) -> str:
    """The seat file's JSON text: the law, its covariance, ``extra`` (loads, fit quality, provenance) and a
    sha256 over all of it."""
    payload = {
        "format": FORMAT,
        "law": seat.law,
        "reference_load_kg": seat.reference_load,
        "parameters": list(PARAMETERS),
        "K3_ref": seat.K3_ref,
        "exponent": seat.exponent,
        "pan_mass": seat.pan_mass,
        "covariance": np.asarray(seat.covariance, float).tolist(),
        "C3_ref": seat.C3_ref,
        "c3_exponent": seat.c3_exponent,
        "loads_kg": [float(x) for x in seat.loads],
        "calibration_dof": seat.dof,
        **extra,
    }
    _finite_tree(payload, "seat")  # never a NaN written as a number (json writes NaN, which is not JSON)
    payload["sha256"] = _checksum(payload)
    return json.dumps(payload, indent=1, sort_keys=False) + "\n"


def _finite_tree(value, where: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise CalibrationError(f"{where}: {value!r} is not a finite number")
    if isinstance(value, dict):
        for k, v in value.items():
            _finite_tree(v, f"{where}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _finite_tree(v, f"{where}[{i}]")


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def load_seat(path: str | Path) -> SeatLaw:
    """The SeatLaw of a seat file written by seat_document; SeatFileError (one line naming the file and key)
    for anything else: not JSON, another tool's, edited (checksum), a missing key, a non-finite number, a
    covariance that is not 3x3 symmetric positive semi-definite, K3_ref <= 0, exponent >= 1."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as error:
        raise SeatFileError(f"seat_file={path}: cannot be read ({error.strerror or error})") from None
    if size > MAX_FILE_BYTES:
        raise SeatFileError(f"seat_file={path}: {size} bytes is not a seat file (at most {MAX_FILE_BYTES})")
    try:
        payload = json.loads(path.read_text(encoding="utf-8"), parse_constant=_reject_constant)
    except (ValueError, UnicodeDecodeError) as error:
        raise SeatFileError(f"seat_file={path}: not a seat file of qcm-calibrate (not JSON: {error})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise SeatFileError(f"seat_file={path}: format={found!r}, not a seat file of qcm-calibrate ({FORMAT})")
    stored = payload.pop("sha256", None)
    if stored != _checksum(payload):
        raise SeatFileError(f"seat_file={path}: sha256 does not match its content (edited or damaged): recalibrate")

    def number(key: str, lo: float = -math.inf, hi: float = math.inf) -> float:
        value = payload.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SeatFileError(f"seat_file={path}: {key}={value!r} is not a finite number")
        if not lo < value < hi:
            raise SeatFileError(f"seat_file={path}: {key}={value!r} lies outside ({lo}, {hi})")
        return float(value)

    law = payload.get("law")
    if law not in NESTED:
        raise SeatFileError(f"seat_file={path}: law={law!r}; known laws {list(NESTED)}")
    cov = payload.get("covariance")
    try:
        cov = np.array(cov, dtype=float)
    except (TypeError, ValueError):
        cov = None
    if cov is None or cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        raise SeatFileError(f"seat_file={path}: covariance is not a 3x3 matrix of finite numbers")
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=0) or np.linalg.eigvalsh(cov).min() < -1e-9 * np.abs(cov).max():
        raise SeatFileError(f"seat_file={path}: covariance is not symmetric positive semi-definite")
    loads = payload.get("loads_kg")
    if not isinstance(loads, list) or not loads or not all(isinstance(x, (int, float)) and x >= 0 for x in loads):
        raise SeatFileError(f"seat_file={path}: loads_kg={loads!r} is not a list of loads >= 0 kg")
    seat = SeatLaw(
        number("K3_ref", 0.0),
        number("exponent", -math.inf, 1.0),
        number("pan_mass"),
        cov,
        law=law,
        reference_load=number("reference_load_kg", 0.0),
        loads=[float(x) for x in loads],
    )
    if payload.get("C3_ref") is not None:
        seat.C3_ref, seat.c3_exponent = number("C3_ref", 0.0), number("c3_exponent")
    if payload.get("calibration_dof") is not None:
        seat.dof = int(number("calibration_dof", 0.0))
    held = [j for j, fitted in enumerate(NESTED[law]) if not fitted]
    if np.any(cov[held] != 0):
        raise SeatFileError(f"seat_file={path}: covariance is not 0 for the parameters law={law!r} holds")
    if any([seat.exponent, seat.pan_mass][j - 1] != 0 for j in held):
        raise SeatFileError(f"seat_file={path}: law={law!r} holds {[PARAMETERS[j] for j in held]} at 0")
    return seat


__all__ = [
    "FORMAT",
    "LAWS",
    "NESTED",
    "PARAMETERS",
    "REFERENCE_LOAD",
    "CalibrationError",
    "SeatFileError",
    "SeatLaw",
    "fit_seat_law",
    "load_seat",
    "seat_document",
]
