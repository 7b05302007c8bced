"""Batched small matrix products on the CPU through numpy (OpenBLAS), for the many tiny
per-sample matrices of the estimation layers, where torch's batched products are 2-4x slower;
torch's thread count for those small per-step operations; and independent solves on threads."""

from __future__ import annotations

import itertools
import os
import platform
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
import torch
from torch import Tensor


def batched_matmul(a: Tensor, b: Tensor, out: Tensor | None = None) -> Tensor:
    """a @ b (batched, broadcast, float64 or complex128), into ``out`` if given (any strides with a
    unit column stride). On the CPU through numpy's matmul, one OpenBLAS call per matrix, 2-4x
    faster than torch's batched products at these sizes (512 samples, 1 thread: [100, 32] @ [32, 51]
    4.2 vs 8.9 ms; 512 x 10 complex [6, 6] @ [6, 6] 0.6 vs 1.9 ms; the Gram matrix of [300, 18]
    4.6 vs 7.5 ms). It reads and writes strided rows (leading dimension = row stride) with no copy.
    OpenBLAS runs a product on the calling thread below m n k = 262144 (all of these at T = 100);
    larger ones may use its threads (OPENBLAS_NUM_THREADS caps them). Other devices, and tensors that
    require grad: torch.matmul."""
    if a.device.type != "cpu" or a.requires_grad or b.requires_grad:
        return torch.matmul(a, b) if out is None else out.copy_(torch.matmul(a, b))
    # torch's conjugate and negative views are lazy: numpy must see the plain values
    a, b = a.resolve_conj().resolve_neg().numpy(), b.resolve_conj().resolve_neg().numpy()
    with np.errstate(all="ignore"):  # non-finite samples are flagged by the caller, as with torch
        if out is None:
            return torch.from_numpy(np.matmul(a, b))
        np.matmul(a, b, out=out.numpy())
    return out


def _intel_cpu() -> bool:
    """Whether this machine's CPU is Intel's (Linux: /proc/cpuinfo's vendor_id; elsewhere the platform's string)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            for line in info:
                if line.startswith("vendor_id"):
                    return "GenuineIntel" in line
    except OSError:
        pass
    return "intel" in platform.processor().lower()


# torch's CPU build multiplies with MKL, fast on Intel's processors and not on others; numpy's OpenBLAS the reverse
_GRAM_BY_TORCH = torch.backends.mkl.is_available() and _intel_cpu()


def gram_matrix(a: Tensor) -> Tensor:
    """aᵀa [b, w, w] of a [b, r, w] (per sample), by whichever library multiplies faster on this CPU (decided once per
    machine, so its numbers are the same from run to run). On an Intel Xeon, torch.matmul of the transposed view
    (one batched GEMM with a transposed operand, MKL) was 3x faster than numpy's per-sample calls at w = 11-18,
    r = 300, 512 samples, 1 thread (Euler 0.9-1.3 vs 2.9-3.5 ms, exact 2.9-3.5 vs 9.2-10.2 ms); on an AMD EPYC
    numpy's (OpenBLAS) were 1.2-1.7x faster than torch's (w = 11, 17, 23: 3.3, 4.8, 8.0 vs 4.1, 7.5, 13.6 ms;
    docs/measurements/roofline.md). Other devices, and tensors that require grad: torch."""
    if not _GRAM_BY_TORCH and a.device.type == "cpu" and not a.requires_grad:
        return batched_matmul(a.transpose(1, 2), a)
    return torch.matmul(a.transpose(1, 2), a)


@contextmanager
def torch_threads(count: int | None) -> Iterator[None]:
    """torch's intra-op threads set to ``count`` (None or 0: unchanged) inside the block. The solver's
    tensors are small ([chunk, time] per step): more threads cost more in wake-ups than they save,
    and on a loaded machine each parallel region waits for a busy core (docs/measurements/real_recordings.md)."""
    before = torch.get_num_threads()
    if count:
        torch.set_num_threads(int(count))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def chunk_workers(config) -> int:
    """Threads that run a pass's chunks at once: SolverConfig.num_threads when its thread_chunks, else 1."""
    threads = config.num_threads
    return int(threads) if config.thread_chunks and threads and int(threads) > 1 else 1


def op_threads(config) -> int | None:
    """torch's intra-op threads inside a solve: one per chunk worker, else SolverConfig.num_threads."""
    return 1 if chunk_workers(config) > 1 else config.num_threads


def available_cores() -> int:
    """The CPU cores this process may use: those it may run on, shared among the processes of a distributed run
    on this machine (LOCAL_WORLD_SIZE where the launcher sets it, else the initialised process group's size)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    local = int(os.environ.get("LOCAL_WORLD_SIZE") or 0)
    if not local and torch.distributed.is_available() and torch.distributed.is_initialized():
        local = torch.distributed.get_world_size()
    return max(1, cores // max(1, local))


def even_slices(n: int, parts: int) -> list[slice]:
    """Rows 0..n-1 as ``parts`` consecutive slices (at most n) whose lengths differ by one at the most, the longer
    first: how a batch of per-sample work is shared among threads."""
    parts = min(max(1, int(parts)), n)
    if parts == 0:
        return []
    base, extra = divmod(n, parts)
    lengths = [base + 1] * extra + [base] * (parts - extra)
    return [slice(end - length, end) for length, end in zip(lengths, itertools.accumulate(lengths))]


def parallel_map(function: Callable, items: Iterable, workers: int) -> list:
    """[function(item) for item in items], on up to ``workers`` threads (in order; at most one thread per item).

    For independent solves: torch's ops and numpy's products release the GIL, so the solves overlap, though
    only partly where their operations are small (the Python between kernels holds it: the occupant
    selection on two threads takes 0.85-0.92x one thread's wall time, docs/measurements/persons.md). torch runs
    one intra-op thread per op meanwhile (set here, restored after), so each result is the sequential one bit
    for bit: another thread count would change the order of torch's reductions (callers run sequentially where
    their solvers ask for more, ``op_threads``). An exception in any call is raised here once the calls already
    running have ended; a stop request (Ctrl-C) ends them at their solver's next iteration (interrupt.check_stop)."""
    items = list(items)
    if workers <= 1 or len(items) < 2:
        return [function(item) for item in items]
    with torch_threads(1), ThreadPoolExecutor(min(int(workers), len(items))) as pool:
        futures = [pool.submit(function, item) for item in items]
        try:
            return [future.result() for future in futures]
        except BaseException:
            for future in futures:
                future.cancel()
            raise
