"""The host's share of a solve whose batch lives on another device (gn_device=accelerator).

Three kinds of per-sample work run faster on the CPU than on a GPU, and a GPU solve hands them over:

* LAPACK's eigen-decomposition of small non-symmetric matrices (torch's CUDA ``eig`` is MAGMA's geev, a
  host routine called once per matrix);
* the SVD of tall designs [b, r, n] (cuSOLVER's batched SVD took ~2 s for 17 000 of [300+, 6] on an H200,
  four calls of an exp 5 solve);
* the step recursion of the few samples the modal path leaves (T steps of a few ops each: launch-bound on
  a GPU, one compiled loop on the CPU).

``on_host(function, *tensors)`` runs ``function`` on CPU copies of the tensors and returns its result on
their device; with ``rows`` the samples (dim 0 of every tensor) are cut into slices solved at once on the
host's cores (the routines release the GIL). Every sample's result is the CPU path's at one torch thread:
the routines are per sample, so a slice gives each sample the same arithmetic as the whole batch
(tests/test_host.py). The call runs under ``torch.device("cpu")``: a solve on a GPU is made under
``torch.device(gpu)`` (estimation/shards.py), whose default would otherwise put the function's own new
tensors on the GPU.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from hybridqcm.estimation._blas import available_cores, even_slices, parallel_map

# below this many samples a slice's thread costs more than it saves (numpy's eig of [6, 6]: ~10 us each)
_MIN_SLICE = 1024


def on_host(function: Callable, *tensors: Tensor | None, rows: bool = False):
    """``function(*tensors)`` on the CPU, its tensors (one or a tuple) back on the first tensor's device.
    ``rows``: every tensor is [b, ...] and the function per sample; the batch runs in slices on threads."""
    device = next(t.device for t in tensors if t is not None)
    host = [None if t is None else t.detach().cpu() for t in tensors]
    with torch.device("cpu"):
        batch = host[0].shape[0] if rows else 0
        pieces = min(available_cores(), batch // _MIN_SLICE) if rows else 1
        if pieces <= 1:
            out = function(*host)
        else:
            parts = parallel_map(
                lambda rows: function(*[None if t is None else t[rows] for t in host]),
                even_slices(batch, pieces),
                pieces,
            )
            out = tuple(torch.cat(p) for p in zip(*parts)) if isinstance(parts[0], tuple) else torch.cat(parts)
    if isinstance(out, tuple):
        return tuple(t.to(device) for t in out)
    return out.to(device)


__all__ = ["on_host"]
