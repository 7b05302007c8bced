"""The learning-rate schedule: a cosine one-cycle curve over the run's progress in steps or time.

A run ends at max_steps/max_epochs or at trainer.max_time, whichever comes first; the schedule
follows the one that is further along, so a time-limited run still anneals to the low end.
"""

from __future__ import annotations

import math
import time

from lightning import Trainer
from lightning.pytorch.callbacks import Timer


def one_cycle_lr(
    progress: float, max_lr: float, pct_start: float = 0.25, div_factor: float = 25.0, final_div_factor: float = 1e4
) -> float:
    """Cosine one-cycle learning rate at training progress in [0, 1] (clamped).

    Rises from max_lr / div_factor to max_lr over the first pct_start of the run (half a
    cosine), then falls to max_lr / (div_factor * final_div_factor): torch's OneCycleLR curve
    with the anneal strategy "cos", as a function of progress instead of a step counter.
    """
    progress = min(max(progress, 0.0), 1.0)
    start, end = max_lr / div_factor, max_lr / (div_factor * final_div_factor)
    if progress < pct_start:
        f = progress / max(pct_start, 1e-12)
        return start + (max_lr - start) * 0.5 * (1 - math.cos(math.pi * f))
    f = (progress - pct_start) / max(1 - pct_start, 1e-12)
    return end + (max_lr - end) * 0.5 * (1 + math.cos(math.pi * f))


def timer_duration(trainer: Trainer) -> float | None:
    """The run's time limit in seconds (trainer.max_time), or None when it has none.

    Lightning turns max_time into a Timer callback and exposes the limit only as the private
    ``Timer._duration`` (lightning 2.x; ``time_remaining`` is measured from the Timer's own
    start, not from ours). This is the one place that reads it: if a Lightning release renames
    it, the schedule falls back to step progress alone.
    """
    timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
    return getattr(timer, "_duration", None) if timer is not None else None


def run_progress(trainer: Trainer, train_start: float | None) -> float:
    """Fraction of the run done: the larger of global_step / estimated steps and elapsed / max_time.

    train_start: time.monotonic() at on_train_start (None before training starts).
    """
    progress = 0.0
    total = trainer.estimated_stepping_batches
    if total and math.isfinite(total) and total > 0:
        progress = trainer.global_step / total
    duration = timer_duration(trainer)
    if duration and train_start is not None:
        progress = max(progress, (time.monotonic() - train_start) / duration)
    return progress


__all__ = ["one_cycle_lr", "timer_duration", "run_progress"]
