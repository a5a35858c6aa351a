"""Banded Cholesky factor and substitutions of the EKF smoother (numba; ours).

The smoother's normal equations (:mod:`stemmap.slam._ekf_stream`) are symmetric positive
definite with lower half-bandwidth ``KD = 5`` (3x3 blocks per frame, block-tridiagonal). They
are factored ``H = L Lᵀ`` and solved here, by one implementation whether the band is taken
whole or frame block by frame block, so that a block and what it carries into the next are
the same loop run in pieces: the same operations on the same operands in the same order, and
so the same bytes whatever the cuts, on any CPU.

Why not LAPACK (``dpbtrf`` / ``dtbtrs``, as before): the bytes of LAPACK's banded Cholesky
depend on the BLAS kernel it calls, which OpenBLAS's ``DYNAMIC_ARCH`` picks per CPU (an AVX-512
Xeon's kernel rounded ``a - x_p x_q`` differently, presumably fused, from the one the carry
had been written against: 1 ulp in the factor, ~1e-14 relative in the path). Re-doing LAPACK's
arithmetic at the block seams in numpy can therefore only match one CPU's kernel; a whole-band
call and a blocked solve then differ on the others, so a result would depend on the drive's
length and on whether the inputs spilled to disk. numba compiles without ``fastmath``: no
contraction into fused multiply-adds and no reassociation, each ``*``, ``-``, ``/`` and
``sqrt`` rounds once as IEEE 754 prescribes, so every CPU computes the same bytes (vectorised
lanes do the same operations as scalar code).

Storage: ``lt`` (c, KD + 1) C-ordered, ``lt[j, i] = L[j + i, j]`` (column ``j`` of the band
as a row: LAPACK's lower band storage ``ab[i, j]`` transposed, i.e. ``ab.T``). The algorithm
is the unblocked right-looking Cholesky (LAPACK's ``dpbtf2``; Golub & Van Loan, "Matrix
Computations", 4th ed., Alg. 4.3.5, band Cholesky): column ``j`` is divided by ``√a_jj`` and
its outer product subtracted from the next ``KD`` columns; forward substitution ``L y = b``
column by column (each solved ``y_j`` subtracted from the ``KD`` rows below: what a block
leaves in its last ``KD`` rows is the carry); back substitution ``Lᵀ x = y`` row by row from
the end, ``x_j = (y_j - Σ_(i=1..KD) L[j+i, j] x_(j+i)) / L[j, j]`` with the sum in ``i``
order (a block needs the next block's first ``KD`` rows of ``x``). Against LAPACK the results
agree to rounding (``tests/slam/test_ekf_stream.py``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["KD", "band_back", "band_factor", "band_forward"]

KD = 5  # lower half-bandwidth of a 3x3 block-tridiagonal matrix


@numba.njit(cache=True)
def band_factor(lt: np.ndarray, m: int) -> int:
    """Factor columns ``[0, m)`` of the band ``lt`` (c, KD + 1) in place (right-looking).

    The matrix is taken to end at column ``c``: a column's updates reach the next
    ``min(KD, c - 1 - j)`` columns, so with ``c >= m + KD`` the last ``KD`` rows of ``lt`` come
    out carrying every update from columns ``< m`` (and nothing else); with ``c = m`` it is the
    matrix's end. Returns 0, or ``j + 1`` if the pivot of column ``j`` is not positive (the
    columns from ``j`` on are then left as they were).
    """
    c = lt.shape[0]
    for j in range(m):
        a = lt[j, 0]
        if not a > 0.0:  # (NaN too)
            return j + 1
        d = math.sqrt(a)
        lt[j, 0] = d
        nb = min(KD, c - 1 - j)
        for i in range(1, nb + 1):
            lt[j, i] = lt[j, i] / d
        for q in range(1, nb + 1):  # column j + q, rows j + q .. j + nb
            xq = lt[j, q]
            for p in range(q, nb + 1):
                lt[j + q, p - q] = lt[j + q, p - q] - lt[j, p] * xq
    return 0


@numba.njit(cache=True)
def band_forward(lt: np.ndarray, y: np.ndarray, m: int) -> int:
    """Forward substitution ``L y = b`` over columns ``[0, m)`` of the factor ``lt``, in place
    on ``y`` (rows, r) C-ordered, which holds ``b`` (and the previous block's carry in its
    first rows). A column's updates reach the next ``min(KD, rows - 1 - j)`` rows: with
    ``rows >= m + KD`` the last ``KD`` rows come out carrying every update from columns ``< m``.
    Returns 0, or ``j + 1`` for a zero diagonal."""
    rows, r = y.shape
    for j in range(m):
        d = lt[j, 0]
        if d == 0.0:
            return j + 1
        for k in range(r):
            y[j, k] = y[j, k] / d
        nb = min(KD, rows - 1 - j)
        for i in range(1, nb + 1):
            lij = lt[j, i]
            for k in range(r):
                y[j + i, k] = y[j + i, k] - lij * y[j, k]
    return 0


@numba.njit(cache=True)
def band_back(lt: np.ndarray, z: np.ndarray, m: int) -> int:
    """Back substitution ``Lᵀ x = y`` over columns ``[0, m)`` of the factor ``lt``, in place on
    ``z`` (rows, r) C-ordered: rows ``[0, m)`` hold ``y`` on entry and ``x`` on return, rows
    ``[m, rows)`` the next block's first rows of ``x`` (none at the matrix's end). Row ``j``
    reads ``x`` up to row ``min(j + KD, rows - 1)``. Returns 0, or ``j + 1`` for a zero
    diagonal."""
    rows, r = z.shape
    for j in range(m - 1, -1, -1):
        d = lt[j, 0]
        if d == 0.0:
            return j + 1
        nb = min(KD, rows - 1 - j)
        for i in range(1, nb + 1):
            lij = lt[j, i]
            for k in range(r):
                z[j, k] = z[j, k] - lij * z[j + i, k]
        for k in range(r):
            z[j, k] = z[j, k] / d
    return 0
