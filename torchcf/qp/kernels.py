"""Batch-last linear algebra: the kernels every layer of the solver is built on.

Every tensor here is *batch-last*: a vector of one instance per column, ``(n, B)``,
a matrix ``(r, c, B)``, with ``B`` the number of QP instances. A matrix-vector
product is then ``c`` fused multiply-adds over contiguous ``B``-vectors, cheaper on
the CPU than ``bmm`` over many tiny matrices, and a Cholesky factorisation is a loop
over ``n`` of elementwise operations over the batch instead of one LAPACK call per
matrix. Small batches go to LAPACK or ``einsum`` instead, where those win
(``_SMALL_BATCH``, ``_LAPACK_BATCH``). Measured costs are in
``reports/bench_qp.md``.

This module imports nothing from the rest of the package.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

#: Batches up to this size multiply by one batched product (see :func:`mv`).
_SMALL_BATCH = 64
#: Batches up to this size are factorised and solved by LAPACK, one call per matrix:
#: the elementwise loops cost a fixed ``n^2 / 2`` tensor operations whatever the
#: batch, LAPACK a small cost per matrix.
_LAPACK_BATCH = 1024
#: Triangular sweeps (:func:`back_substitute`, the leading-block solve) run over
#: batch slices whose accumulator (``(n, b)`` values, read and written once per
#: column) fits in this many bytes, so that it stays in the last-level cache
#: between columns.
_SWEEP_BYTES = 8 << 20


# --------------------------------------------------------------------------------------
# Products and norms.


def mv(M: Tensor, v: Tensor) -> Tensor:
    """``M v`` per instance: (r, c, B) x (c, B) -> (r, B)."""
    if v.shape[-1] <= _SMALL_BATCH:  # a few instances: one batched product
        return torch.einsum("rcb,cb->rb", M, v)
    out = M[:, 0] * v[0]
    for j in range(1, v.shape[0]):
        out.addcmul_(M[:, j], v[j])
    return out


def rmv(M: Tensor, v: Tensor) -> Tensor:
    """``M' v`` per instance: (r, c, B) x (r, B) -> (c, B)."""
    out = M[0] * v[0]
    for i in range(1, v.shape[0]):
        out.addcmul_(M[i], v[i])
    return out


def inf_norm(v: Tensor) -> Tensor:
    """``||v||_inf`` per instance: (m, B) -> (B,); NaN propagates.

    Two reductions and no ``|v|`` temporary, which on the CPU costs more than both
    (``torch.aminmax`` over dim 0 is slower still).
    """
    return torch.maximum(v.amax(0), v.amin(0).neg_())


# --------------------------------------------------------------------------------------
# Selecting instances, and the batch-first / batch-last change of layout.


def take_instances(t: Tensor, idx: Tensor) -> Tensor:
    """Instances ``idx`` of a batch-last tensor: ``(..., B) -> (..., len(idx))``.

    Gathering along the last dim of a flat ``(rows, B)`` view is faster than
    ``index_select(-1)`` on the ``(n, n, B)`` tensor itself.
    """
    flat = t.reshape(-1, t.shape[-1]).index_select(1, idx)
    return flat.reshape(*t.shape[:-1], idx.numel())


def is_small_subset(idx: Tensor, batch: int) -> bool:
    """Is ``idx`` (at most an eighth of ``batch`` instances) few enough to gather
    from batch-first storage instead?

    Gathering a few columns of a batch-last ``(n, n, B)`` tensor touches a memory
    page per element; batch-first, each instance is one contiguous block.
    """
    return idx.numel() * 8 <= batch


def put_instances_(t: Tensor, idx: Tensor, src: Tensor) -> Tensor:
    """Overwrite instances ``idx`` of contiguous batch-last ``t: (..., B)`` with
    ``src: (..., len(idx))``, in place; returns ``t``."""
    if idx.numel():
        t.view(-1, t.shape[-1]).index_copy_(1, idx, src.reshape(-1, idx.numel()))
    return t


def swap_layout(t: Tensor) -> Tensor:
    """Contiguous ``t.T`` of a 2-D tensor: between the batch-first API, ``(B, n)``,
    and the batch-last working layout, ``(n, B)``.

    On the CPU numpy's blocked transpose beats torch's strided copy.
    """
    if t.device.type == "cpu" and not t.requires_grad and t.dtype != torch.bfloat16:
        array = t.resolve_conj().resolve_neg().numpy()
        return torch.from_numpy(np.ascontiguousarray(array.T))
    return t.T.contiguous()


# --------------------------------------------------------------------------------------
# Cholesky factorisation, solves and inverse.


def cholesky(M: Tensor, strict: bool = True) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor ``L L' = M`` of symmetric ``M: (n, n, B)``, one column
    per step.

    Every inner product is a chain of in-place ``addcmul_`` over ``B``-vectors: no
    ``(n, n, B)`` temporaries, which is what makes ``n = 20`` affordable.

    Args:
        M: (n, n, B).
        strict: treat pivots below ``n eps max(diag)`` as zero (a singular ``M``);
            otherwise only non-positive pivots fail.

    Returns:
        L: (n, n, B) whose lower triangle holds the factor, ``L L' = M`` where
            ``ok`` (garbage elsewhere); the strict upper triangle is uninitialised.
        ok: (B,) bool, False where a pivot is not clearly positive (``M`` singular or
            indefinite to working precision).
    """
    n = M.shape[0]
    floor = torch.diagonal(M).amax(-1).clamp_min(0) * (n * torch.finfo(M.dtype).eps)
    if not strict:
        floor = torch.zeros_like(floor)
    if M.shape[-1] <= _LAPACK_BATCH:
        # A few matrices: LAPACK per matrix beats n^2 / 2 tiny elementwise calls.
        L, info = torch.linalg.cholesky_ex(M.permute(2, 0, 1))  # (B, n, n)
        pivots = torch.diagonal(L, 0, 1, 2).square()  # (B, n)
        ok = (info == 0) & (pivots > floor[:, None]).all(1)
        return L.permute(1, 2, 0).contiguous(), ok
    L = torch.empty_like(M)  # only the lower triangle is written and read
    ok = torch.ones(M.shape[-1], dtype=torch.bool, device=M.device)
    for j in range(n):
        col = M[j:, j].clone()  # (n - j, B)
        for k in range(j):
            col.addcmul_(L[j:, k], L[j, k], value=-1)
        good = col[0] > floor
        ok &= good
        pivot = torch.where(good, col[0], torch.ones_like(col[0])).sqrt_()  # (B,)
        L[j, j] = pivot
        L[j + 1 :, j] = col[1:] / pivot
    return L, ok


def cholesky_solve(L: Tensor, b: Tensor) -> Tensor:
    """Solve ``L L' x = b`` for ``L: (n, n, B)`` lower triangular, ``b: (n, B)``;
    returns ``x: (n, B)``."""
    n = b.shape[0]
    if b.shape[-1] <= _LAPACK_BATCH:
        x = torch.cholesky_solve(b.T[:, :, None], L.permute(2, 0, 1).tril())
        return x[:, :, 0].T
    w = b.clone()
    for i in range(n):  # forward: L w = b
        for k in range(i):
            w[i].addcmul_(L[i, k], w[k], value=-1)
        w[i] /= L[i, i]
    for i in reversed(range(n)):  # backward: L' x = w
        for k in range(i + 1, n):
            w[i].addcmul_(L[k, i], w[k], value=-1)
        w[i] /= L[i, i]
    return w


def spd_inverse(M: Tensor) -> tuple[Tensor, Tensor]:
    """Explicit inverse of symmetric positive definite ``M: (n, n, B)``.

    LAPACK's potri done by hand: ``W = L^{-1}`` row by row, then ``M^{-1} = W' W``,
    both as ``addcmul_`` chains over the batch (``n^3 / 3`` of them in all); the cost
    is a few elementwise passes per matrix entry instead of one LAPACK call per
    matrix.

    Returns:
        inverse: (n, n, B); ok: (B,) bool as in :func:`cholesky`.
    """
    n = M.shape[0]
    L, ok = cholesky(M)
    if M.shape[-1] <= _LAPACK_BATCH:  # a few matrices: LAPACK's potri per matrix
        inverse = torch.cholesky_inverse(L.permute(2, 0, 1).tril())  # (B, n, n)
        inverse = torch.where(ok[:, None, None], inverse, 0)  # no NaN where not ok
        return inverse.permute(1, 2, 0).contiguous(), ok
    W = torch.empty_like(M)  # lower triangular; the upper triangle is never read
    for i in range(n):
        W[i, i] = L[i, i].reciprocal()
        if i:
            row = M.new_zeros(i, M.shape[-1])  # (i, B)
            for k in range(i):
                row[: k + 1].addcmul_(W[k, : k + 1], L[i, k])  # W[k, c>k] = 0
            W[i, :i] = row.mul_(-W[i, i])
    inverse = torch.empty_like(M)
    for a in range(n):
        # Column a below the diagonal: inverse[c, a] = sum_{k >= c} W[k, c] W[k, a],
        # and W[k, c] = 0 for c > k, so term k only touches rows c <= k.
        col = W[n - 1, a:] * W[n - 1, a]  # (n - a, B)
        for k in range(a, n - 1):
            col[: k - a + 1].addcmul_(W[k, a : k + 1], W[k, a])
        inverse[a:, a] = col
        inverse[a, a + 1 :] = col[1:]
    return inverse, ok


# --------------------------------------------------------------------------------------
# The "UL" factor and triangular sweeps over it.


def ul_cholesky(M: Tensor) -> tuple[Tensor, Tensor]:
    """Upper triangular ``U`` with ``M = U U'`` for symmetric ``M: (n, n, B)``.

    It is the Cholesky factor of ``M`` with its rows and columns reversed, and it
    factorises every trailing block at once: row ``i`` of ``U`` is zero left of
    ``i``, so ``M[k:, k:] = U[k:, k:] U[k:, k:]'``. Fixing the first ``k`` variables
    of a box QP therefore needs no new factorisation (see
    :func:`torchcf.qp.leading.leading_solve`).

    Returns:
        U: (n, n, B), strict lower triangle uninitialised; ok: (B,) bool as in
        :func:`cholesky`.
    """
    L, ok = cholesky(M.flip(0, 1))
    return L.flip(0, 1), ok


def sweep_slices(t: Tensor) -> list[slice]:
    """Even batch slices of a sweep's accumulator ``t: (n, B)`` (see
    ``_SWEEP_BYTES``); one slice, the whole batch, where it fits."""
    batch = t.shape[-1]
    per = max(1, _SWEEP_BYTES // max(1, t.shape[0] * t.element_size()))
    size = -(-batch // -(-batch // per)) if batch else 1  # ceil(batch / slices)
    return [slice(start, start + size) for start in range(0, batch, size)]


def back_substitute(U: Tensor, inv_diag: Tensor, q: Tensor) -> Tensor:
    """``g = U^{-1} q``: (n, B), for upper triangular ``U: (n, n, B)``, ``q: (n, B)``.

    Column by column, one fused ``(rows, b)`` operation per column and batch slice
    (:func:`sweep_slices`): ``n^2 / 2`` multiply-adds. ``inv_diag``: (n, B)
    ``1 / diag(U)``.
    """
    n = q.shape[0]
    g = q.clone()
    for part in sweep_slices(g):
        g_, U_, inv_ = g[:, part], U[..., part], inv_diag[:, part]
        for j in reversed(range(n)):
            g_[j].mul_(inv_[j])
            if j:
                g_[:j].addcmul_(U_[:j, j], g_[j], value=-1)
    return g


def tail_residuals(U: Tensor, g: Tensor, q: Tensor) -> Tensor:
    """(n + 1, B): ``max_{i >= k} |U g - q|_i`` in row ``k``, 0 in row ``n``.

    The residual is recomputed from ``U: (n, n, B)`` and ``g: (n, B)``, not carried
    over from the substitution, so that round-off growth in it (an ill-conditioned
    ``U``) shows.
    """
    n = q.shape[0]
    table = q.new_empty(n + 1, q.shape[-1])
    residual = torch.neg(q, out=table[:n])
    for j in range(n):
        residual[: j + 1].addcmul_(U[: j + 1, j], g[j])
    residual.abs_()
    table[n] = 0
    for i in reversed(range(n)):  # a running max from the bottom (cummax is slow)
        torch.maximum(table[i], table[i + 1], out=table[i])
    return table
