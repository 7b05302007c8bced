"""Pseudo-inverses and solves of batches of small symmetric positive semi-definite matrices [b, n, n]
(normal equations, covariances), with a relative eigenvalue cutoff instead of NaN on rank deficiency."""

from __future__ import annotations

import torch
from torch import Tensor

# cuSOLVER's batched symmetric eigensolver failed (CUSOLVER_STATUS_INTERNAL_ERROR) on 170 000 matrices
# [18, 18] at once on an H200 and ran on 17 000: larger batches go through it in slices.
_DEVICE_EIGH_BATCH = 16384


def _eigh(matrix: Tensor, slice_rows: int | None = None) -> tuple[Tensor, Tensor]:
    """torch.linalg.eigh of [b, n, n] in slices of ``slice_rows`` matrices (off the CPU by default
    _DEVICE_EIGH_BATCH, on the CPU whole)."""
    rows = slice_rows or (_DEVICE_EIGH_BATCH if matrix.device.type != "cpu" else None)
    if rows is None or matrix.shape[0] <= rows:
        return torch.linalg.eigh(matrix)
    parts = [torch.linalg.eigh(part) for part in matrix.split(rows)]
    return torch.cat([v for v, _ in parts]), torch.cat([w for _, w in parts])


def pseudo_inverse(matrix: Tensor, rcond: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pseudo-inverse of symmetric PSD matrices [b, n, n] with column scaling and an eigenvalue cutoff
    rcond² (relative to the largest). Returns (M⁺ [b, n, n], unidentified [b, n] — an entry with
    weight on a dropped direction, or a zero column —, singular values of the column-scaled factor
    [b, n] descending, rank_deficient [b])."""
    scale = matrix.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt()
    safe = torch.where(scale > 0, scale, torch.ones_like(scale))
    scaled = matrix / (safe.unsqueeze(2) * safe.unsqueeze(1))
    eigval, eigvec = _eigh(scaled)  # ascending
    eigval = eigval.clamp_min(0.0)
    keep = (eigval > (rcond**2) * eigval[:, -1:].clamp_min(1e-300)) & (eigval > 0)
    inv = torch.where(keep, 1.0 / eigval.clamp_min(1e-300), torch.zeros_like(eigval))
    pinv = (eigvec * inv.unsqueeze(1)) @ eigvec.transpose(1, 2) / (safe.unsqueeze(2) * safe.unsqueeze(1))
    unidentified = ((eigvec.square() * (~keep).unsqueeze(1).to(eigvec.dtype)).sum(2) > 1e-6) | (scale == 0)
    rank_deficient = (~keep).any(1) | (scale == 0).any(1)
    return pinv, unidentified, eigval.sqrt().flip(1), rank_deficient


def _cholesky_where_well(matrix: Tensor, rcond: float) -> tuple[Tensor, Tensor]:
    """(Cholesky factor [b, n, n], well [b]): the samples whose factor is safe to use. The smallest Cholesky
    pivot² bounds the smallest eigenvalue from above: a cheap test for which samples need the (slower)
    eigen-decomposition with its cutoff."""
    factor, info = torch.linalg.cholesky_ex(matrix)
    pivots = factor.diagonal(dim1=1, dim2=2)
    max_diag = matrix.diagonal(dim1=1, dim2=2).amax(1).clamp_min(1e-300)
    well = (info == 0) & torch.isfinite(pivots).all(1) & (pivots.square().amin(1) > 1e3 * rcond**2 * max_diag)
    return factor, well


def psd_inverse(matrix: Tensor, rcond: float) -> Tensor:
    """(Pseudo-)inverse [b, n, n] of symmetric PSD ``matrix``: by Cholesky where it is well conditioned (the
    test of :func:`pseudo_inverse_solve`), :func:`pseudo_inverse`'s eigenvalue cutoff elsewhere."""
    factor, well = _cholesky_where_well(matrix, rcond)
    inverse = torch.empty_like(matrix)
    if bool(well.any()):
        inverse[well] = torch.cholesky_inverse(factor[well])
    if bool((~well).any()):
        inverse[~well] = pseudo_inverse(matrix[~well], rcond)[0]
    return inverse


def pseudo_inverse_solve(matrix: Tensor, rhs: Tensor, rcond: float) -> tuple[Tensor, Tensor]:
    """Solve matrix [b, n, n] x = rhs [b, n] (symmetric PSD); Cholesky where well conditioned,
    eigen-decomposition with cutoff rcond² on the eigenvalues elsewhere. Returns (x, rank_deficient)."""
    x = torch.zeros_like(rhs)
    rank_deficient = torch.zeros(rhs.shape[0], dtype=torch.bool)
    if rhs.shape[0] == 0:
        return x, rank_deficient
    factor, well = _cholesky_where_well(matrix, rcond)
    if bool(well.any()):
        x[well] = torch.cholesky_solve(rhs[well].unsqueeze(2), factor[well]).squeeze(2)
    if bool((~well).any()):
        ill = (~well).nonzero().squeeze(1)
        eigval, eigvec = _eigh(matrix[ill])
        keep = eigval > (rcond**2) * eigval[:, -1:].clamp_min(1e-300)
        inv = torch.where(keep, 1.0 / eigval.clamp_min(1e-300), torch.zeros_like(eigval))
        proj = (eigvec.transpose(1, 2) @ rhs[ill].unsqueeze(2)).squeeze(2)
        x[ill] = (eigvec @ (inv * proj).unsqueeze(2)).squeeze(2)
        rank_deficient[ill] = (~keep).any(1)
    return x, rank_deficient
