"""Plots people would rather look at than read: sorted predictions, overlays, histograms.

All functions return a matplotlib Figure (for TensorBoard's add_figure) and, given `path`,
also save it as PNG. The Agg backend is used so nothing needs a display.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hybridqcm.atomic import replacing  # noqa: E402


def save_figure(fig, path: str | Path | None):
    """``fig`` as a PNG at ``path`` (none: not saved), whole or not at all: drawn into a temporary file of its own
    beside it (atomic.replacing: two plots of one name never share it, a stop leaves none), then renamed."""
    if path is not None:
        with replacing(path, ".png") as tmp:  # the suffix tells matplotlib the format
            fig.savefig(tmp, dpi=110, bbox_inches="tight")
    return fig


def plot_sorted_predictions(
    pred: np.ndarray,
    target: np.ndarray,
    name: str,
    path: str | Path | None = None,
    title: str | None = None,
    max_points: int = 20000,
):
    """Samples ordered by true value: the true curve, predictions, ±10 % and ±25 % bands."""
    pred, target = np.asarray(pred, dtype=float).ravel(), np.asarray(target, dtype=float).ravel()
    order = np.argsort(target)
    if order.size > max_points:  # keep the figure light; an even subsample shows the same picture
        order = order[np.linspace(0, order.size - 1, max_points).astype(int)]
    t, p = target[order], pred[order]
    x = np.arange(t.size)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.fill_between(x, 0.75 * t, 1.25 * t, color="tab:orange", alpha=0.15, label="±25 %")
    ax.fill_between(x, 0.9 * t, 1.1 * t, color="tab:green", alpha=0.25, label="±10 %")
    ax.plot(x, p, ".", ms=1.5, color="tab:blue", alpha=0.6, label="estimate")
    ax.plot(x, t, "-", lw=1.2, color="black", label="true")
    ax.set_xlabel("sample (sorted by true value)")
    ax.set_ylabel(name)
    ax.set_title(title or f"{name}: sorted predictions")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    return fig


def plot_overlays(
    time: np.ndarray,
    curves: dict[str, np.ndarray],
    path: str | Path | None = None,
    title: str = "",
    ylabel: str = "acceleration [m/s²]",
):
    """A few example signals on top of each other, one panel per row of the arrays [examples, time]."""
    n = next(iter(curves.values())).shape[0]
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.8 * n + 0.6), sharex=True, squeeze=False)
    for i in range(n):
        for label, values in curves.items():
            axes[i, 0].plot(time, values[i], lw=1, label=label)
        axes[i, 0].set_ylabel(ylabel, fontsize=7)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path)
    return fig


def plot_histogram(
    values: np.ndarray, path: str | Path | None = None, title: str = "", xlabel: str = "", log_x: bool = True
):
    """Histogram of per-sample values (log-spaced bins for errors spanning decades)."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if values.size:
        if log_x and (values > 0).all():
            bins = np.logspace(np.log10(values.min()), np.log10(values.max()) + 1e-12, 50)
            ax.set_xscale("log")
        else:
            bins = 50
        ax.hist(values, bins=bins, color="tab:blue", alpha=0.8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("samples")
    ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path)
    return fig


def plot_rank_histograms(
    ranks: np.ndarray, names: Sequence[str], n_posterior: int, path=None, title=None, bins: int = 20
):
    """SBC rank histograms [B, P] (one panel per parameter) with the uniform band (mean ± 2 std of a bin count)."""
    ranks = np.asarray(ranks, dtype=float)
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 2.8), squeeze=False)
    expected = ranks.shape[0] / bins
    band = 2 * np.sqrt(expected * (1 - 1 / bins))
    for ax, name, column in zip(axes[0], names, ranks.T):
        ax.axhspan(expected - band, expected + band, color="0.85")
        ax.hist(column, bins=bins, range=(0, n_posterior), color="C0")
        ax.set_title(name)
        ax.set_xlabel("rank")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def plot_tarp_curve(ecp: np.ndarray, alpha: np.ndarray, path=None, title=None):
    """TARP: expected coverage probability against credibility level (the diagonal is calibrated)."""
    fig, ax = plt.subplots(figsize=(3.6, 3.4))
    ax.plot([0, 1], [0, 1], color="0.5", linestyle="--", label="calibrated")
    ax.plot(np.asarray(alpha, dtype=float), np.asarray(ecp, dtype=float), color="C1", label="posterior")
    ax.set_xlabel("credibility level")
    ax.set_ylabel("expected coverage")
    ax.legend(loc="upper left")
    if title:
        ax.set_title(title)
    return save_figure(fig, path)


def close(fig) -> None:
    plt.close(fig)


__all__: Sequence[str] = [
    "plot_sorted_predictions",
    "plot_overlays",
    "plot_histogram",
    "plot_rank_histograms",
    "plot_tarp_curve",
    "close",
]


def plot_apparent_mass(
    freq_measured: np.ndarray,
    measured: np.ndarray,
    freq: np.ndarray,
    fitted: np.ndarray,
    apparent_mass: np.ndarray,
    path: str | Path | None = None,
    title: str | None = None,
):
    """A seated occupant at a glance: the seat's transmissibility a3/a2 measured (cross-spectral H1
    estimate, complex [F_m] at freq_measured [Hz]) beside the fitted model's, and the fitted apparent
    mass AM/M (magnitude and phase); fitted, apparent_mass: complex [F] at freq [Hz]."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].plot(freq_measured, np.abs(measured), ".", color="0.5", label="measured (H1)")
    axes[0].plot(freq, np.abs(fitted), "-", color="C0", label="fitted")
    axes[0].set(xlabel="frequency [Hz]", ylabel="|a3 / a2|", title="transmissibility")
    axes[0].legend(fontsize=8)
    axes[1].plot(freq, np.abs(apparent_mass), color="C1")
    axes[1].axhline(1.0, color="0.7", lw=0.8)
    axes[1].set(xlabel="frequency [Hz]", ylabel="|AM| / static mass", title="apparent mass (fitted)")
    axes[2].plot(freq, np.degrees(np.angle(apparent_mass)), color="C1")
    axes[2].set(xlabel="frequency [Hz]", ylabel="phase [deg]", title="apparent-mass phase")
    for ax in axes:
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_running_estimate(
    segments: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    skipped: np.ndarray | None = None,
    path: str | Path | None = None,
    title: str | None = None,
    ylabel: str = "m3 [kg]",
):
    """A drive's running estimate: per segment (time [n], estimate [n], low [n], high [n]) a step line with its
    95 % band (an infinite bound is left open), one colour each; ``skipped``: times of windows not used (x)."""
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for k, (t, m, low, high) in enumerate(segments):
        high = np.where(np.isfinite(high), high, np.nan)
        ax.fill_between(t, low, high, step="post", alpha=0.25, color=f"C{k}")
        ax.step(t, m, where="post", color=f"C{k}", label=f"segment {k}")
    if skipped is not None and len(skipped):
        ax.plot(skipped, np.full(len(skipped), ax.get_ylim()[0]), "kx", ms=4, label="window not used")
    ax.set_xlabel("time in the recording [s] (end of each window)")
    ax.set_ylabel(f"{ylabel}, 95 % band")
    ax.grid(alpha=0.3)
    ax.set_title(title or "running estimate")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)
