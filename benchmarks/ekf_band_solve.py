"""Benchmark: the EKF smoother's banded solve, our kernels against LAPACK (CPU time).

The smoother's normal equations (:mod:`stemmap.slam._ekf_stream`) are block-tridiagonal (3x3
blocks, lower half-bandwidth 5). This times, on a random SPD chain of ``--frames`` frames
(diagonally dominant, as :func:`stemmap.slam._ekf_smooth.banded_lower` stores it) and
``--rhs`` right-hand sides (1: a Gauss-Newton step; more: a column block of the map term):

* ``lapack``: ``scipy.linalg.cholesky_banded`` + ``cho_solve_banded`` over the whole band
  (``dpbtrf`` + ``dpbtrs``; what the smoother called per block before);
* ``ours_whole``: :mod:`stemmap.slam._band_kernel` (numba) over the whole band, through
  :func:`stemmap.slam._ekf_stream.band_forward` / ``band_backward``;
* ``ours_blocks``: the same in blocks of 1,024 frames with the carry, as the smoother runs it
  (the same bytes as ``ours_whole``: checked here).

Each is the minimum CPU time (``time.process_time``, one BLAS thread) over ``--repeats`` runs;
``max_rel_diff`` is ``max |x_ours - x_lapack| / max |x_lapack|``. Prints one JSON object.

Usage::

    python benchmarks/ekf_band_solve.py [--frames 10000,100000] [--rhs 1,16] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np


def _chain(n: int, seed: int = 0) -> np.ndarray:
    """LAPACK lower band (6, 3n) of a random SPD block-tridiagonal matrix of ``n`` frames."""
    from stemmap.slam._ekf_smooth import banded_lower

    rng = np.random.default_rng(seed)
    m = rng.normal(size=(n, 3, 3))
    diag = m @ m.transpose(0, 2, 1) + 6.0 * np.eye(3)  # diagonally dominant: SPD
    return banded_lower(diag, rng.normal(size=(n - 1, 3, 3)))


def _in_blocks(lt: np.ndarray, rhs: np.ndarray, seg: int) -> tuple[np.ndarray, np.ndarray]:
    """Factor and solve frame block by frame block (``seg`` frames), carrying ``KD`` columns."""
    from stemmap.slam._ekf_stream import KD, band_backward, band_forward

    nf = lt.shape[0] // 3
    parts: list[tuple[np.ndarray, np.ndarray]] = []
    carry = None
    for lo in range(0, nf, seg):
        hi = min(nf, lo + seg)
        end = 3 * hi if hi == nf else 3 * hi + KD
        a, r = lt[3 * lo : end].copy(), rhs[3 * lo : end].copy()
        if carry is not None:
            a[:KD], r[:KD] = carry
        m = 3 * (hi - lo)
        t, y = band_forward(a, r, m, factor=True)
        parts.append((t[:m], y[:m]))
        carry = (t[m : m + KD], y[m : m + KD])
    xs, after = [], None
    for t, y in reversed(parts):
        after = band_backward(t, y, after)
        xs.append(after)
    return np.concatenate([t for t, _ in parts]), np.concatenate(xs[::-1])


def _cpu(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    best, out = float("inf"), None
    for _ in range(repeats):
        c0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - c0)
    return best, out


def run(frames: list[int], rhs_counts: list[int], repeats: int) -> dict[str, Any]:
    from scipy.linalg import cho_solve_banded, cholesky_banded

    from stemmap.slam._ekf_stream import band_backward, band_forward
    from stemmap.slam.base import single_threaded_blas

    rows: list[dict[str, Any]] = []
    with single_threaded_blas():
        _in_blocks(np.ascontiguousarray(_chain(8).T), np.ones((24, 1)), 3)  # numba: load/compile
        for n in frames:
            ab = _chain(n)
            lt = np.ascontiguousarray(ab.T)
            for r in rhs_counts:
                b = np.random.default_rng(1).normal(size=(3 * n, r))

                def lapack(ab: np.ndarray = ab, b: np.ndarray = b) -> np.ndarray:
                    return cho_solve_banded((cholesky_banded(ab, lower=True), True), b)

                def whole(lt: np.ndarray = lt, b: np.ndarray = b) -> np.ndarray:
                    t, y = band_forward(lt, b, lt.shape[0], factor=True)
                    return band_backward(t, y, None)

                t_lap, x_lap = _cpu(lapack, repeats)
                t_whole, x_whole = _cpu(whole, repeats)
                t_blk, (_, x_blk) = _cpu(lambda lt=lt, b=b: _in_blocks(lt, b, 1024), repeats)
                rows.append(
                    {
                        "frames": n,
                        "rhs": r,
                        "lapack_cpu_s": round(t_lap, 4),
                        "ours_whole_cpu_s": round(t_whole, 4),
                        "ours_blocks_cpu_s": round(t_blk, 4),
                        "blocks_equal_whole": bool(np.array_equal(x_blk, x_whole)),
                        "max_rel_diff": float(np.abs(x_whole - x_lap).max() / np.abs(x_lap).max()),
                    }
                )
    return {
        "benchmark": "ekf_band_solve",
        "repeats": repeats,
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "results": rows,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", default="10000,100000", help="comma list of chain lengths")
    ap.add_argument("--rhs", default="1,16", help="comma list of right-hand-side counts")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    frames = [int(v) for v in a.frames.split(",")]
    rhs = [int(v) for v in a.rhs.split(",")]
    print(json.dumps(run(frames, rhs, a.repeats), indent=1))


if __name__ == "__main__":
    main()
