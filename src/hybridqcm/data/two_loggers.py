"""Two loggers, two clocks: a seat and a floor recording of one drive onto one time grid (issue 32).

Phone apps and stand-alone loggers record three axes with gravity (logger_csv.read_logger), each on its
own clock: its own start, its own irregular sample times, its own rate error and its own orientation.
The road-free estimator needs the seat's vertical acceleration a3 and the floor's a2 on one grid:

1. **Vertical from gravity.** On average (braking and cornering average out over a drive) a logger reads
   the specific force +g along the vertical: ĝ = mean(a)/|mean(a)|, and a_up = a·ĝ − |mean(a)| is the
   vertical acceleration with gravity removed (and with it any constant sensor offset along ĝ), whatever
   the tilt; tilt = the angle between ĝ and the logger's z axis.
2. **Resampling from each sample's own time stamp** with an anti-aliasing filter:
   y(t) = Σ_i x_i g(t − t_i) w_i / Σ_i g(t − t_i) w_i, w_i = (t_{i+1} − t_{i−1})/2 (trapezoid weights of the
   irregular samples), g a Kaiser-windowed sinc (β = 8) cut off at the grid's Nyquist frequency, 64 grid
   steps to each side: a quadrature of one continuous low-pass filter, so both loggers, whatever their rate
   and jitter, pass through the same filter and the ratio A3/A2 is untouched; the normalisation keeps its
   gain at DC exactly one under jitter. The quadrature of so sharp a filter on jittered samples is off by
   about the jitter, so it is corrected twice by the quadrature of what the result misses at the samples'
   own times (data/resample.py): 4e-4 of the signal at 100 Hz and 5e-5 at 200 Hz with 1 % jitter. The cutoff sits at the Nyquist frequency, not below it, because the
   estimator tests its residual for whiteness: resampled white noise with a cutoff at 0.4 of the rate
   failed the Ljung-Box test in every 4.88 s window, at 0.5 with 64 steps in 3 % (1 % nominal), for 100
   and 200 Hz loggers alike (what the sharp edge lets alias from a faster logger is its noise above 50 Hz). No rate is taken from a median step (with 1 % jitter that is 1e-4 off): a logger's
   rate is (n − 1)/(t_last − t_first), reported, and the grid's rate is a round number near the slower one.
3. **Clocks.** t_floor = offset + (1 + drift) t_seat, found where the seat moves with the floor: below
   2 Hz its transfer delays by a millisecond or less (0.8 ms at 2 Hz on the reference seat). Coarse: the
   peak of the phase correlation (cross-correlation with the phase transform) of the two vertical signals,
   each resampled on its own clock to ``rate_xcorr``, in 0.3-2 Hz, over every offset that leaves
   min_overlap_s in common, to a sample; a peak under min_peak times the correlation's typical value means
   no common motion: the files do not overlap in time. Fine: with the signals paired at that shift, the
   delay left is the slope of the phase of their Welch cross-spectrum in 0.3-2 Hz, weighted by
   2n γ²/(1 − γ²) (γ² the coherence; Hannan & Thomson's maximum-likelihood delay): measured within 0.9 ms
   on 40 drives where the correlation peak alone was up to 19 ms off. Drift: that delay in segments of
   segment_s along the overlap (from the middle outwards, each paired at the lag the line so far predicts)
   and a weighted line through them: the slope, with its standard error (widened by the segments'
   scatter). Applied when it exceeds three of its standard errors (an hour pins it to a fraction of a
   ppm; a minute only to some tens of ppm, where 100 ppm is 6 ms over the minute and each window's
   estimated delay takes it). What the seat's dynamics add to the delay is the estimator's (qcm-estimate
   delay=estimate fits a channel delay per window).
4. **One grid**: both on t_k = T0 + k h in the floor logger's clock, over the overlap (less the filter's
   half-width at each end), a3 = seat, a2 = floor.

Memory: per logger its time stamps and axes (32 bytes a row: an hour at 1 kHz is 115 MB), then the two
vertical signals on the grid; windows are written as they are cut (import_writer.write_windows).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.import_writer import write_windows
from hybridqcm.data.logger_csv import read_logger
from hybridqcm.data.resample import lowpass_resample, resample

XCORR_HALF_WIDTH = 16  # samples: the filter's half-width for the alignment's own resampling
MIN_DRIFT_SEGMENTS = 6  # segments a drift must rest on to be applied
BAND_HZ = (0.3, 2.0)  # where the seat moves with the floor: its transfer's phase is a millisecond's delay or less
GRAVITY_RANGE = (7.0, 12.5)  # |mean acceleration| a logger with gravity reads [m/s²]; else: not in m/s²?


@dataclass
class Vertical:
    """A logger's vertical acceleration (gravity removed) [n] and what was found: its gravity vector [3]
    (m/s², logger axes), tilt [deg] from its z axis."""

    values: np.ndarray
    gravity: np.ndarray
    tilt_deg: float


def vertical(xyz: np.ndarray) -> Vertical:
    """a_up = a·ĝ − |ḡ| with ḡ the mean of xyz [n, 3] (module docstring)."""
    mean = xyz.mean(0)
    g = float(np.linalg.norm(mean))
    up = mean / g
    tilt = math.degrees(math.acos(min(1.0, abs(float(up[2])))))
    return Vertical(values=xyz @ up - g, gravity=mean, tilt_deg=tilt)


def _uniform(t: np.ndarray, x: np.ndarray, rate: float, half_width_s: float) -> tuple[float, np.ndarray]:
    """x on its own clock's uniform grid t0 + k / rate (inside the record by the filter's half-width)."""
    t0 = t[0] + half_width_s
    n = int(math.floor((t[-1] - half_width_s - t0) * rate)) + 1
    grid = t0 + np.arange(max(n, 0)) / rate
    return t0, lowpass_resample(t, x, grid, 0.4 * rate, half_width_s)


def _band(x: np.ndarray, rate: float, band: tuple[float, float], n: int | None = None) -> np.ndarray:
    """The spectrum of x (mean removed, zero-padded to n) with only the band [low, high) Hz kept."""
    n = n or x.size
    spectrum = np.fft.rfft(x - x.mean(), n)
    freq = np.fft.rfftfreq(n, 1.0 / rate)
    return spectrum * ((freq >= band[0]) & (freq < band[1]))


def _phase_correlation(s: np.ndarray, f: np.ndarray, rate: float, band: tuple[float, float]):
    """(lags [samples], c): the generalised cross-correlation with the phase transform of f against s in
    ``band``: Σ over the band's frequencies of e^{i(φ_f − φ_s)}, whose peak is at the lag L with
    f[k + L] ≈ s[k], sharp whatever the spectra (the car's slow bounce would make a plain correlation's
    peak seconds wide)."""
    n = 1 << int(math.ceil(math.log2(s.size + f.size)))
    cross = _band(f, rate, band, n) * np.conj(_band(s, rate, band, n))
    cross = cross / np.maximum(np.abs(cross), 1e-300) * (np.abs(cross) > 0)
    c = np.fft.fftshift(np.fft.irfft(cross, n))
    return np.arange(n) - n // 2, c


def _phase_slope(a: np.ndarray, b: np.ndarray, rate: float, band: tuple[float, float], nperseg: int):
    """(τ, its standard error) [s]: the delay of b behind a from the phase of their Welch cross-spectrum,
    φ(f) = −2π f τ, fitted through the origin over ``band`` with the weights 1/var φ = 2 n γ²/(1 − γ²)
    (γ² the coherence, n Welch's segments at half overlap): the maximum-likelihood delay for jointly
    stationary signals (Hannan & Thomson), good to a fraction of a millisecond where the plain
    correlation's peak is seconds wide. |τ| must stay well below 1/(2 band[1]) (no phase wrap)."""
    from scipy.signal import csd, welch

    n = min(a.size, b.size)
    nperseg = min(int(nperseg), n)
    a, b = a[:n] - a[:n].mean(), b[:n] - b[:n].mean()
    f, pab = csd(a, b, fs=rate, nperseg=nperseg)
    _, paa = welch(a, fs=rate, nperseg=nperseg)
    _, pbb = welch(b, fs=rate, nperseg=nperseg)
    sel = (f >= band[0]) & (f <= band[1]) & (paa > 0) & (pbb > 0)
    coherence = np.clip(np.abs(pab[sel]) ** 2 / (paa[sel] * pbb[sel]), 1e-12, 0.999)
    segments = max(1.0, 2.0 * n / nperseg - 1.0)
    w = 2 * segments * coherence / (1 - coherence)
    fs, phase = f[sel], np.angle(pab[sel])
    info = np.sum(w * fs**2) * (2 * np.pi) ** 2
    return float(-np.sum(w * fs * phase) * 2 * np.pi / info), float(1 / math.sqrt(info))


def _line(t: np.ndarray, y: np.ndarray, sd: np.ndarray) -> tuple[float, float, float]:
    """(value at t = 0, slope, the slope's standard error) of the weighted least-squares line through
    (t, y ± sd); with four points or more the error grows with their scatter beyond their own errors."""
    w = 1.0 / sd**2
    design = np.stack([np.ones_like(t), t], 1)
    information = design.T @ (w[:, None] * design)
    covariance = np.linalg.inv(information)
    coef = covariance @ (design.T @ (w * y))
    if t.size >= 4:
        chi2 = float(np.sum(w * (y - design @ coef) ** 2)) / (t.size - 2)
        covariance = covariance * max(1.0, chi2)
    return float(coef[0]), float(coef[1]), float(math.sqrt(covariance[1, 1]))


def _peak(values: np.ndarray, k: int) -> float:
    """Sub-sample position of the maximum at k by a parabola through k - 1, k, k + 1."""
    if k <= 0 or k >= values.size - 1:
        return float(k)
    a, b, c = values[k - 1], values[k], values[k + 1]
    denom = a - 2 * b + c
    return float(k + (0.5 * (a - c) / denom if denom < 0 else 0.0))


@dataclass
class Alignment:
    """Both loggers on one grid: a3 (seat), a2 (floor) [K] m/s², t0 (floor clock) and h; what was found."""

    a3: np.ndarray
    a2: np.ndarray
    t0: float
    h: float
    report: dict = field(default_factory=dict)


def _verticals(seat, floor) -> dict:
    """Each logger's vertical acceleration (gravity's direction), checked to be gravity in m/s²."""
    verticals = {}
    for role, logger in (("seat", seat), ("floor", floor)):
        v = vertical(logger.xyz)
        g = float(np.linalg.norm(v.gravity))
        if not GRAVITY_RANGE[0] <= g <= GRAVITY_RANGE[1]:
            raise RecordingError(
                f"{logger.path}: the mean acceleration is {g:.4g} m/s², not gravity: give three axes with gravity "
                f"in m/s² (or units=g)"
            )
        verticals[role] = v
    return verticals


def _coarse_shift(s_u, f_u, rc: float, min_overlap_s: float, min_peak: float, names: str) -> tuple[int, float]:
    """The phase correlation's peak in the band where the seat moves with the floor: the shift in samples
    (f_u[i + shift] pairs with s_u[i]) and the peak over the correlation's typical value."""
    lags, c = _phase_correlation(s_u, f_u, rc, BAND_HZ)
    overlap_n = np.minimum(s_u.size, f_u.size - lags) - np.maximum(0, -lags)
    c = np.where(overlap_n >= min_overlap_s * rc, c, -np.inf)
    k = int(np.argmax(c))
    finite = c[np.isfinite(c)]
    spread = 1.4826 * float(np.median(np.abs(finite - np.median(finite))))
    if not c[k] >= min_peak * spread:
        raise RecordingError(
            f"{names}: no common motion at any time offset (the best phase correlation of the vertical "
            f"accelerations is {c[k] / spread:.1f} x its typical value, {min_peak:g} needed): the two files do not "
            f"overlap in time, or are not the same drive"
        )
    return int(lags[k]), float(c[k] / spread)


def _segment_lags(s_u, f_u, ts0, tf0, rc, starts, seg, t_mid, lag_mid, nperseg):
    """The delay in segments along the overlap, taken from the middle outwards, each paired at the lag the
    line so far predicts (an hour at 300 ppm drifts by a second: beyond what the phase slope alone takes),
    the phase slope measuring the rest. Returns the segments' times and lags and the weighted line
    (lag at t_mid, drift, its standard error) through them."""
    times, lag_s, lag_sd = [], [], []
    fit = (lag_mid, 0.0, math.nan)
    for a in starts:
        lo = int(math.ceil((a - ts0) * rc))
        hi = lo + int(seg * rc)
        predicted = fit[0] + fit[1] * (ts0 + 0.5 * (lo + hi) / rc - t_mid)
        m = int(round((predicted - tf0 + ts0) * rc))  # f_u[i + m] pairs with s_u[i]
        lo, hi = max(lo, -m, 0), min(hi, f_u.size - m, s_u.size)
        per = min(nperseg, max(64, int(seg * rc) // 4))  # a few Welch segments in each
        if hi - lo < per:
            continue
        d, sd = _phase_slope(s_u[lo:hi], f_u[lo + m : hi + m], rc, BAND_HZ, per)
        times.append(ts0 + 0.5 * (lo + hi - 1) / rc)
        lag_s.append(tf0 - ts0 + m / rc + d)
        lag_sd.append(sd)
        if len(times) >= 2:
            fit = _line(np.asarray(times) - t_mid, np.asarray(lag_s), np.asarray(lag_sd))
    return times, lag_s, fit


def _logger_report(logger, v, rate_hz: float) -> dict:
    return {
        "file": str(logger.path),
        "rate_hz": rate_hz,
        "rows": int(logger.t.size),
        "tilt_deg": v.tilt_deg,
        "gravity_m_s2": float(np.linalg.norm(v.gravity)),
        "start_s": float(logger.t[0]),
        "end_s": float(logger.t[-1]),
    }


def align(
    seat,
    floor,
    *,
    rate: float | None = None,
    rate_xcorr: float = 100.0,
    min_overlap_s: float = 10.0,
    segment_s: float | None = None,
    max_drift_ppm: float = 300.0,
    half_width: int = 64,
    min_peak: float = 8.0,
    nperseg: int = 1024,
) -> Alignment:
    """The seat's and the floor's recordings (logger_csv.LoggerRecording) on one grid (module docstring).
    Raises RecordingError (one line) when they share no motion (not the same drive, or no time in common)
    or have too little in common."""
    names = f"{seat.path} and {floor.path}"
    verticals = _verticals(seat, floor)
    rates = {"seat": seat.rate_hz, "floor": floor.rate_hz}
    rate_out = float(rate) if rate is not None else float(round(min(rates.values())))
    if not rate_out > 0:
        raise RecordingError(f"{names}: rate = {rate} is not a positive rate [Hz]")
    rc = min(float(rate_xcorr), rate_out)
    hw_c = XCORR_HALF_WIDTH / rc
    ts0, s_u = _uniform(seat.t, verticals["seat"].values, rc, hw_c)
    tf0, f_u = _uniform(floor.t, verticals["floor"].values, rc, hw_c)
    for logger, u in ((seat, s_u), (floor, f_u)):
        if u.size < min_overlap_s * rc:
            raise RecordingError(
                f"{logger.path}: {logger.t[-1] - logger.t[0]:.4g} s of recording, shorter than min_overlap_s = "
                f"{min_overlap_s:g} (the drive is shorter than the time the two loggers must share)"
            )
    shift, peak = _coarse_shift(s_u, f_u, rc, min_overlap_s, min_peak, names)  # f_u[i + shift] pairs with s_u[i]
    i0, i1 = max(0, -shift), min(s_u.size, f_u.size - shift)
    tau, tau_sd = _phase_slope(s_u[i0:i1], f_u[i0 + shift : i1 + shift], rc, BAND_HZ, nperseg)
    lag_mid = tf0 - ts0 + shift / rc + tau  # t_floor - t_seat over the overlap, ~ at its middle
    seat_lo, seat_hi = max(seat.t[0], floor.t[0] - lag_mid), min(seat.t[-1], floor.t[-1] - lag_mid)
    overlap = seat_hi - seat_lo
    if overlap < min_overlap_s:
        raise RecordingError(f"{names}: {overlap:.3g} s in common, less than min_overlap_s = {min_overlap_s:g}")
    t_mid = ts0 + 0.5 * (i0 + i1 - 1) / rc
    # drift: the same delay in segments along the overlap, a weighted line through them
    seg = float(segment_s) if segment_s else max(min_overlap_s, min(60.0, overlap / 6))
    starts = [seat_lo + j * seg for j in range(int(overlap // seg))]
    starts.sort(key=lambda a: abs(a + 0.5 * seg - t_mid))
    times, lag_s, fit = _segment_lags(s_u, f_u, ts0, tf0, rc, starts, seg, t_mid, lag_mid, nperseg)
    drift, drift_sd = fit[1], fit[2]
    if len(times) < 2:
        drift = math.nan
    residual_ms = math.nan
    if len(times) >= 2:
        t_arr, l_arr = np.asarray(times) - t_mid, np.asarray(lag_s)
        residual_ms = float(1000 * np.sqrt(np.mean((l_arr - fit[0] - drift * t_arr) ** 2)))
    used = len(times)
    # applied where it rests on enough segments for their scatter to check its error (a segment's delay
    # scatters about three times its phase-based error: its own road spectrum meets the seat's dynamics)
    applied = bool(
        used >= MIN_DRIFT_SEGMENTS
        and np.isfinite(drift)
        and abs(drift) > 3 * drift_sd
        and abs(drift) <= max_drift_ppm * 1e-6
    )
    rate_ratio = drift if applied else 0.0
    offset = (fit[0] if applied else lag_mid) - rate_ratio * t_mid
    # the grid in the floor's clock over the overlap, inside both records by the filter's half-width
    hw = half_width / rate_out
    seat_in_floor = offset + (1 + rate_ratio) * seat.t
    lo = max(floor.t[0], seat_in_floor[0]) + hw
    hi = min(floor.t[-1], seat_in_floor[-1]) - hw
    t0 = math.ceil(lo * rate_out) / rate_out
    n_out = int(math.floor((hi - t0) * rate_out + 1e-9)) + 1
    if n_out < 2:
        raise RecordingError(f"{names}: no time in common once aligned (offset {offset:.6g} s)")
    grid = t0 + np.arange(n_out) / rate_out
    # cut off at the grid's Nyquist frequency: white sensor noise stays white (the estimator tests it)
    a3 = resample(seat_in_floor, verticals["seat"].values, grid, half_width)
    a2 = resample(floor.t, verticals["floor"].values, grid, half_width)
    report = {
        "offset_s": offset,
        "drift_ppm": drift * 1e6,
        "drift_sd_ppm": drift_sd * 1e6,
        "drift_applied": applied,
        "segments": used,
        "segment_s": seg,
        "lag_fit_rms_ms": residual_ms,
        "offset_sd_ms": 1000 * tau_sd,
        "phase_correlation_peak": peak,
        "rate_hz": rate_out,
        "overlap_s": float((n_out - 1) / rate_out),
        "t0_s": t0,
    }
    for role, logger in (("seat", seat), ("floor", floor)):
        report[role] = _logger_report(logger, verticals[role], rates[role])
    return Alignment(a3=a3, a2=a2, t0=t0, h=1.0 / rate_out, report=report)


@dataclass
class AlignedLayout:
    """What import_writer.write_windows needs of two aligned loggers cut into windows."""

    h: float
    n_steps: int
    cuts: list[int]  # first grid index of every window
    t0: float
    recordings: list[str]
    source_columns: dict
    window: int | None
    stride: int | None
    channels: tuple[str, ...] = ("a3", "a2")
    source_units: dict = field(default_factory=lambda: {"a3": "m/s2", "a2": "m/s2"})
    has_road: bool = False

    @property
    def n_samples(self) -> int:
        return len(self.cuts)

    @property
    def profile_id(self) -> np.ndarray:
        return np.zeros(len(self.cuts), dtype=np.int32)

    @property
    def t_start(self) -> np.ndarray:
        return self.t0 + np.asarray(self.cuts, dtype=np.float64) * self.h


def import_two_loggers(
    seat_path: str | os.PathLike,
    floor_path: str | os.PathLike,
    output: str | os.PathLike,
    *,
    window: int | None = None,
    stride: int | None = None,
    split: str = "test",
    overwrite: bool = False,
    progress: bool = False,
    read: dict | None = None,
    base_read: dict | None = None,
    **align_options,
) -> tuple[AlignedLayout, dict]:
    """Read the seat and the floor logger (read_logger's keys in ``read``, ``base_read``), align them
    (``align_options``: align's keys) and write the windows (a3 = seat, a2 = floor; one drive: profile_id
    0, t_start in the floor's clock) with the alignment report as the file attribute ``two_loggers``."""
    import json

    seat = read_logger(seat_path, progress=progress, **dict(read or {}))
    floor = read_logger(floor_path, progress=progress, axes_key="base_axes", **dict(base_read or {}))
    aligned = align(seat, floor, **align_options)
    n = aligned.a3.size
    if window is None:
        cuts, steps = [0], n
    else:
        window, stride = int(window), int(stride or window)
        if n < window:
            raise RecordingError(
                f"{seat.path} and {floor.path}: {n} samples in common at {1 / aligned.h:g} Hz "
                f"({(n - 1) * aligned.h:.4g} s), fewer than window = {window} (the drive is shorter than one window)"
            )
        cuts, steps = list(range(0, n - window + 1, stride)), window
    name = Path(seat_path).stem
    layout = AlignedLayout(
        h=aligned.h,
        n_steps=steps,
        cuts=cuts,
        t0=aligned.t0,
        recordings=[name],
        source_columns={
            "a3": f"{seat.path}: vertical of {list(seat.columns.values())[1:]}",
            "a2": f"{floor.path}: vertical of {list(floor.columns.values())[1:]}",
        },  # fmt: skip
        window=window,
        stride=stride if window is not None else None,
    )

    def windows():
        for m, start in enumerate(cuts):
            accel = np.full((steps, 3), np.nan, dtype=np.float32)
            accel[:, 0] = aligned.a3[start : start + steps]
            accel[:, 1] = aligned.a2[start : start + steps]
            yield m, accel, None

    write_windows(
        output,
        layout,
        windows(),
        split=split,
        source=f"{seat_path} + {floor_path}",
        overwrite=overwrite,
        attrs={"two_loggers": json.dumps(aligned.report)},
    )
    return layout, aligned.report


__all__ = [
    "Vertical",
    "vertical",
    "Alignment",
    "align",
    "AlignedLayout",
    "import_two_loggers",
]
