"""Windows that carry no information, found before any fit: a car standing still, a clipped logger.

A fit of such a window returns numbers, not a vehicle: an all-zero window (a parked car) made the
road-free occupant fit end in a traceback for the whole run (its noise model has no variance to
work with), a clipped one fits a different vehicle. So each window is classified on the recorded
signals of the channels it is fitted to, before noise or networks, and an unusable one is not fitted:
it gets its status in estimates.csv / status.csv, no estimate, and a count in the summary.

    status = window_status(signals [b, T, C], WindowCheck())     # int64 [b]: 0 usable, else a WindowStatus

* ``no_signal``: a channel is constant — all zeros, or a level that varies by no more than float32
  rounding (its range within 16 ulps of its magnitude) — or its standard deviation is at most
  ``min_std`` m/s². The default 0 skips constant channels only: the quietest windows of our
  simulated files (class A road, noise-free) have a std of 1.7e-4 m/s² and are estimated fine, so
  the threshold is the logger's to set (its noise floor skips the stops of a noisy sensor).
* ``clipped``: a channel's largest or smallest value is held by at least ``clip_samples`` samples:
  a logger at its full scale keeps writing that value while the acceleration is beyond it. A
  continuous signal meets its extreme once per window (our files: never twice); a quantised one can
  repeat it for a sample or two at a flat peak, hence 5 by default (None: no check).

Status values are apart from the solver's (estimation/solver.py SolverStatus 0-5), so the two
share one status column.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import torch
from torch import Tensor

_ULPS = 16 * torch.finfo(torch.float32).eps  # relative range of a constant stored as float32


class WindowStatus(IntEnum):
    """Why a window was not fitted (values stable: they go into CSV files)."""

    NO_SIGNAL = 16  # a channel constant (a car standing still) or below min_std
    CLIPPED = 17  # a channel held at its extreme value (the logger's full scale)

    @property
    def label(self) -> str:
        return self.name.lower()


WINDOW_STATUS_LABELS = {s.value: s.label for s in WindowStatus}


@dataclass(frozen=True)
class WindowCheck:
    """min_std: a channel's std [m/s²] at or below which the window has no signal (0: constant only);
    clip_samples: samples at a channel's extreme that make it clipped (None: not checked)."""

    min_std: float = 0.0
    clip_samples: int | None = 5

    def __post_init__(self):
        if not (isinstance(self.min_std, (int, float)) and math.isfinite(self.min_std) and self.min_std >= 0):
            raise ValueError(f"min_std must be a finite number >= 0, got {self.min_std!r}")
        clip = self.clip_samples
        if clip is not None and (isinstance(clip, bool) or not isinstance(clip, int) or clip < 2):
            raise ValueError(f"clip_samples must be an integer >= 2 or null, got {clip!r}")


def window_status(signals: Tensor, check: WindowCheck = WindowCheck()) -> Tensor:
    """int64 [b]: 0 for a usable window, WindowStatus.NO_SIGNAL / CLIPPED otherwise.

    signals: [b, T, C] the recorded channels a window is fitted to (finite; float32 or float64)."""
    x = signals.double()
    high, low = x.amax(1), x.amin(1)  # [b, C]
    level = torch.maximum(high.abs(), low.abs())
    flat = (high - low) <= _ULPS * level
    if check.min_std > 0:
        flat = flat | (x.std(1, correction=0) <= check.min_std)
    status = torch.zeros(x.shape[0], dtype=torch.int64)
    if check.clip_samples is not None:
        held = torch.maximum((x == high[:, None]).sum(1), (x == low[:, None]).sum(1))  # [b, C]
        clipped = ((held >= check.clip_samples) & ~flat).any(1)
        status[clipped] = int(WindowStatus.CLIPPED)
    status[flat.any(1)] = int(WindowStatus.NO_SIGNAL)
    return status


def is_skipped(status: Tensor) -> Tensor:
    """bool [b]: windows a WindowStatus kept from the fit."""
    return torch.isin(status, torch.tensor(list(WINDOW_STATUS_LABELS), dtype=status.dtype))


__all__ = ["WindowStatus", "WINDOW_STATUS_LABELS", "WindowCheck", "window_status", "is_skipped"]
