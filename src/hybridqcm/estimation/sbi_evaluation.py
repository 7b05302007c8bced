"""Evaluation of the SBI peer (estimation/sbi_peer.py): posterior summaries and intervals, the rows of its
table, rank statistics (calibration) and its speed."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from hybridqcm.physics.parameters import PARAM_NAMES, REFERENCE_VEHICLE

from .sbi_peer import SBIPeer, import_sbi


def central_interval(samples: Tensor, level: float = 0.95) -> tuple[Tensor, Tensor]:
    """(low, high) [B, ...] of samples [S, B, ...]: the central `level` interval of each marginal."""
    tail = (1 - level) / 2
    q = torch.quantile(samples.double(), torch.tensor([tail, 1 - tail], dtype=torch.float64), dim=0)
    return q[0], q[1]


def posterior_summary(
    peer: SBIPeer, x: Tensor, n_samples: int = 1000, K3: float = REFERENCE_VEHICLE.K3, chunk: int = 256
) -> dict:
    """Per recording x [B, C, window]: posterior medians, means and central 95 % intervals of the
    peer's parameters ([B, P] each) and of m3 = K3/p2 ([B]) when p2 is among them. Medians are the
    point estimates (m3 = K3/p2 is monotone, so m3's median is K3 / p2's median)."""
    out: dict[str, list] = {
        k: [] for k in ("median", "mean", "low", "high", "m3_median", "m3_mean", "m3_low", "m3_high")
    }
    j2 = peer.settings.params.index("p2") if "p2" in peer.settings.params else None
    for start in range(0, x.shape[0], chunk):
        s = peer.sample_params(n_samples, x[start : start + chunk], chunk=chunk)  # [S, b, P]
        low, high = central_interval(s)
        out["median"].append(s.median(0).values)
        out["mean"].append(s.mean(0))
        out["low"].append(low)
        out["high"].append(high)
        if j2 is not None:
            m3 = K3 / s[..., j2]
            m3_low, m3_high = central_interval(m3)
            out["m3_median"].append(m3.median(0).values)
            out["m3_mean"].append(m3.mean(0))
            out["m3_low"].append(m3_low)
            out["m3_high"].append(m3_high)
    return {k: torch.cat(v) for k, v in out.items() if v}


def evaluation_row(
    summary: Mapping[str, Tensor], true: Tensor, names: Sequence[str], K3: float = REFERENCE_VEHICLE.K3
) -> dict:
    """Metrics of one posterior summary against the true params [B, 10]; column names as qcm-estimate's summary.

    m3_* errors use the posterior median; coverage: fraction of truths inside the central 95 % interval;
    interval width relative to the truth (median over samples)."""
    row: dict = {"n": int(true.shape[0])}
    true = true.to(torch.float64)
    for j, name in enumerate(names):
        t = true[:, PARAM_NAMES.index(name)]
        err = (summary["median"][:, j] - t).abs() / t
        row[f"{name}_mean_rel_err"] = float(err.mean())
        row[f"{name}_coverage_95"] = float(((summary["low"][:, j] <= t) & (t <= summary["high"][:, j])).double().mean())
        row[f"{name}_interval_median_rel_width"] = float(((summary["high"][:, j] - summary["low"][:, j]) / t).median())
    if "m3_median" in summary:
        t = K3 / true[:, 1]
        err = (summary["m3_median"] - t).abs() / t
        row["m3_mean_rel_err"] = float(err.mean())
        row["m3_p95_rel_err"] = float(err.quantile(0.95))
        row["m3_within_1pct"] = float((err <= 0.01).double().mean())
        row["m3_coverage_95"] = float(((summary["m3_low"] <= t) & (t <= summary["m3_high"])).double().mean())
        row["m3_interval_median_rel_width"] = float(((summary["m3_high"] - summary["m3_low"]) / t).median())
    return row


def rank_statistics(peer: SBIPeer, x: Tensor, z_true: Tensor, n_samples: int = 500) -> dict:
    """SBC ranks [B, P] (sbi's run_sbc) and TARP (ecp, alpha) (sbi's run_tarp) on held-out (z_true [B, P], x).

    Also the checks: KS p-values of rank uniformity per parameter, C2ST of the data-averaged
    posterior vs the prior (sbi's check_sbc), and TARP's ATC and KS p-value (check_tarp)."""
    import_sbi()
    from sbi.diagnostics import check_sbc, check_tarp, run_sbc, run_tarp

    z_true = z_true.float()
    ranks, dap = run_sbc(z_true, x, peer, num_posterior_samples=n_samples, show_progress_bar=False)
    sbc = check_sbc(ranks, z_true, dap, num_posterior_samples=n_samples)
    ecp, alpha = run_tarp(z_true, x, peer, num_posterior_samples=n_samples, show_progress_bar=False)
    atc, ks = check_tarp(ecp, alpha)
    return {
        "ranks": ranks,
        "ks_pvals": sbc["ks_pvals"],
        "c2st_ranks": sbc["c2st_ranks"],
        "c2st_dap": sbc["c2st_dap"],
        "ecp": ecp,
        "alpha": alpha,
        "tarp_atc": float(atc),
        "tarp_ks_pval": float(ks),
    }


def seconds_per_1000(peer: SBIPeer, x: Tensor, n_samples: int = 1000, K3: float = REFERENCE_VEHICLE.K3) -> float:
    """Wall time of `posterior_summary` (embedding, n_samples draws, intervals) per 1 000 recordings."""
    t0 = time.perf_counter()
    posterior_summary(peer, x, n_samples=n_samples, K3=K3)
    return (time.perf_counter() - t0) * 1000.0 / x.shape[0]


def as_numpy_rows(rows: Sequence[Mapping], columns: Sequence[str]) -> list[list]:
    """Rows for atomic_write_csv: one list per mapping in `columns` order (repr for floats)."""
    return [
        [repr(float(r[c])) if isinstance(r.get(c), (float, np.floating)) else r.get(c, "") for c in columns]
        for r in rows
    ]


__all__ = [
    "central_interval",
    "posterior_summary",
    "evaluation_row",
    "rank_statistics",
    "seconds_per_1000",
    "as_numpy_rows",
]
