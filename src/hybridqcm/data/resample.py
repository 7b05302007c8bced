"""Irregular samples onto a uniform grid through one continuous low-pass filter (data/two_loggers.py, step 2).

lowpass_resample(t_in [N], x [N], grid [K])   y(t) = sum_i x_i g(t - t_i) w_i / sum_i g(t - t_i) w_i,
                                              g a Kaiser-windowed sinc cut off at the grid's Nyquist frequency,
                                              w_i the trapezoid weights of the irregular samples
band_limited_at(grid, y, t)                  the grid's band-limited signal read at arbitrary times t
resample(t_in, x, grid)                      lowpass_resample corrected for the quadrature's error under
                                              jitter (what the result misses at the samples' own times)
"""

from __future__ import annotations

import numpy as np
from scipy.special import i0  # numpy's i0 is a Python-level series, 20x slower


def _trapezoid_weights(t: np.ndarray) -> np.ndarray:
    w = np.empty_like(t)
    w[1:-1] = 0.5 * (t[2:] - t[:-2])
    w[0], w[-1] = 0.5 * (t[1] - t[0]), 0.5 * (t[-1] - t[-2])
    return w


def lowpass_resample(
    t_in: np.ndarray,
    x: np.ndarray,
    t_out: np.ndarray,
    cutoff_hz: float,
    half_width_s: float,
    beta: float = 8.0,
    chunk: int = 8192,
) -> np.ndarray:
    """x [n] sampled at the increasing times t_in [n] (irregular) -> [K] at t_out [K], through the low-pass
    g(τ) = 2 f_c sinc(2 f_c τ) · I0(β √(1 − (τ/W)²))/I0(β) on |τ| ≤ W (module docstring, step 2)."""
    t_in, x, t_out = (np.asarray(a, dtype=np.float64) for a in (t_in, x, t_out))
    w = _trapezoid_weights(t_in)
    lo = np.searchsorted(t_in, t_out - half_width_s, side="left")
    hi = np.searchsorted(t_in, t_out + half_width_s, side="right")
    width = int((hi - lo).max()) if t_out.size else 0
    out = np.empty(t_out.size)
    norm = i0(beta)
    for a in range(0, t_out.size, chunk):
        b = min(t_out.size, a + chunk)
        idx = lo[a:b, None] + np.arange(width)[None, :]
        valid = idx < hi[a:b, None]
        idx = np.minimum(idx, t_in.size - 1)
        tau = t_out[a:b, None] - t_in[idx]
        u = np.clip(tau / half_width_s, -1.0, 1.0)
        g = 2 * cutoff_hz * np.sinc(2 * cutoff_hz * tau) * i0(beta * np.sqrt(1 - u * u)) / norm
        g = np.where(valid, g, 0.0) * w[idx]
        out[a:b] = (g * x[idx]).sum(1) / g.sum(1)
    return out


def band_limited_at(grid: np.ndarray, y: np.ndarray, t: np.ndarray, half_width: int = 64, beta: float = 8.0):
    """y [K] on the uniform grid [K], band-limited to its Nyquist frequency, at the times t [n]: the
    Kaiser-windowed sinc interpolation Σ_k y_k sinc((t − T_k)/h) w((t − T_k)/(half_width h))."""
    h = float(grid[1] - grid[0])
    out = np.empty(t.size)
    k0 = np.floor((t - grid[0]) / h).astype(np.int64)
    offsets = np.arange(-half_width + 1, half_width + 1)
    norm = i0(beta)
    for a in range(0, t.size, 8192):
        b = min(t.size, a + 8192)
        idx = k0[a:b, None] + offsets[None, :]
        valid = (idx >= 0) & (idx < grid.size)
        idx = np.clip(idx, 0, grid.size - 1)
        tau = (t[a:b, None] - grid[idx]) / h
        u = np.clip(tau / half_width, -1.0, 1.0)
        g = np.where(valid, np.sinc(tau) * i0(beta * np.sqrt(1 - u * u)) / norm, 0.0)
        out[a:b] = (g * y[idx]).sum(1)
    return out


def resample(t_in: np.ndarray, x: np.ndarray, grid: np.ndarray, half_width: int = 64, iterations: int = 2):
    """x [n] at the irregular times t_in onto the uniform grid [K], band-limited to the grid's Nyquist
    frequency (module docstring, step 2): the filter's quadrature, then ``iterations`` corrections with the
    quadrature of what the result misses at the samples' own times (x − the result interpolated there):
    the quadrature alone is off by about the jitter (1 % jitter: 0.6 % RMS at 100 Hz), each correction
    takes a factor of ten off (measured: 4e-4 at 100 Hz, 5e-5 at 200 Hz with 1 % jitter, two corrections)."""
    h = float(grid[1] - grid[0])
    width = half_width * h
    y = lowpass_resample(t_in, x, grid, 0.5 / h, width)
    inside = (t_in > grid[0] + width) & (t_in < grid[-1] - width)  # where the result is whole
    for _ in range(iterations):
        missed = np.where(inside, x - band_limited_at(grid, y, t_in, half_width), 0.0)
        y = y + lowpass_resample(t_in, missed, grid, 0.5 / h, width)
    return y


__all__ = ["lowpass_resample", "band_limited_at", "resample"]
