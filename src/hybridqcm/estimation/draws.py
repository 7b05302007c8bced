"""Any slice of one seeded ``torch.randn`` draw, computed without drawing the whole of it.

qcm-estimate draws the random initial guesses δ [M, 10] (and the source's multiplicative noise
η [M, T, 3]) as ONE ``torch.randn`` call over the whole file prefix, so every experiment sees the
same δ. Streaming the file in blocks needs rows [a, b) of that draw with memory independent of M,
and bit-for-bit the values the one call gives (estimates must not depend on the block size or
the number of processes).

How torch fills a contiguous float64 tensor of S >= 16 values on the CPU (ATen
``normal_fill``): S uniforms u_k in [0, 1) are drawn in order from the generator (one per value;
a chunked ``torch.rand`` consumes the stream identically), then every full block of 16 is
transformed by Box-Muller, pairing k and k + 8:

    r = sqrt(-2 log(1 - u_k)),  θ = 2π u_{k+8},  z_k = r cos θ,  z_{k+8} = r sin θ;

when S is not a multiple of 16, 16 more uniforms u_S .. u_{S+15} are drawn and the LAST 16
values z_{S-16} .. z_{S-1} are recomputed from them. Python's ``math`` functions are the C
library's, as ATen's scalar loop; numpy's vectorised log differs in the last bit, so the
transcendental calls go through ``math`` (tested bit-for-bit against ``torch.randn``).
Below 16 values torch uses another algorithm: those draws are simply made whole.
"""

from __future__ import annotations

import math

import numpy as np
import torch

_CHUNK = 1 << 20  # uniforms drawn per step while skipping ahead (8 MiB)


def _box_muller_16(u: np.ndarray) -> np.ndarray:
    """uniforms [16 n] -> normals [16 n], ATen's normal_fill_16 on each block of 16."""
    blocks = u.reshape(-1, 16)
    u1 = (1.0 - blocks[:, :8]).ravel()
    theta = (2.0 * math.pi * blocks[:, 8:]).ravel()
    radius = np.sqrt(-2.0 * np.fromiter(map(math.log, u1), np.float64, u1.size))
    cos = np.fromiter(map(math.cos, theta), np.float64, theta.size)
    sin = np.fromiter(map(math.sin, theta), np.float64, theta.size)
    out = np.empty_like(blocks)
    out[:, :8] = (radius * cos).reshape(-1, 8)
    out[:, 8:] = (radius * sin).reshape(-1, 8)
    return out.ravel()


class NormalStream:
    """Slices of ``torch.randn(total, generator=torch.Generator().manual_seed(seed), dtype=float64)``.

    ``take(start, stop)`` returns values [start, stop) as float64 numpy [stop - start]; memory is
    O(stop - start). Calls with increasing ``start`` continue from the generator's position (a
    step back restarts from the seed), so reading the draw in order costs one pass over it.
    """

    def __init__(self, seed: int, total: int):
        self.seed, self.total = int(seed), int(total)
        self._small = None
        if self.total < 16:
            g = torch.Generator().manual_seed(self.seed)
            self._small = torch.randn(self.total, generator=g, dtype=torch.float64).numpy()
        self._full = (self.total // 16) * 16  # values from the in-order blocks
        self._rewind()

    def _rewind(self) -> None:
        self._generator = torch.Generator().manual_seed(self.seed)
        self._position = 0  # uniforms consumed so far

    def _uniforms(self, start: int, stop: int) -> np.ndarray:
        """Uniforms [start, stop) of the stream (skipping ahead in bounded chunks)."""
        if start < self._position:
            self._rewind()
        while self._position < start:
            n = min(_CHUNK, start - self._position)
            torch.rand(n, generator=self._generator, dtype=torch.float64)
            self._position += n
        out = torch.rand(stop - start, generator=self._generator, dtype=torch.float64).numpy()
        self._position = stop
        return out

    def take(self, start: int, stop: int) -> np.ndarray:
        start, stop = int(start), int(stop)
        if not 0 <= start <= stop <= self.total:
            raise ValueError(f"NormalStream.take({start}, {stop}) outside [0, {self.total}]")
        if self._small is not None:
            return self._small[start:stop].copy()
        out = np.empty(stop - start, dtype=np.float64)
        # in-order blocks covering [start, min(stop, full)), aligned to 16
        lo, hi = (start // 16) * 16, min(-(-stop // 16) * 16, self._full)
        if hi > lo:
            z = _box_muller_16(self._uniforms(lo, hi))
            a, b = start, min(stop, hi)
            out[: b - a] = z[a - lo : b - lo]
        tail = self.total - 16
        if self.total % 16 and stop > tail:  # the last 16 values, recomputed from 16 extra uniforms
            z = _box_muller_16(self._uniforms(self.total, self.total + 16))
            a = max(start, tail)
            out[a - start :] = z[a - tail : stop - tail]
        return out


__all__ = ["NormalStream"]
