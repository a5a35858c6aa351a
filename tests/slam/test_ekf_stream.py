"""The EKF smoother's normal equations solved block by block (stemmap.slam._ekf_stream)."""

from __future__ import annotations

import itertools
import math
import tracemalloc

import numpy as np
import pytest
from scipy.linalg import cho_solve_banded, cholesky_banded, solveh_banded
from test_ekf_smooth import _drifted_chain, _observe, _random_chain

import stemmap.slam._ekf_smooth as sm
import stemmap.slam._ekf_stream as st
from stemmap.slam._ekf_smooth import banded_lower, smooth_path


def _blocked(lt: np.ndarray, rhs: np.ndarray, cuts: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Factor and solve the banded system (band ``lt`` (3n, KD+1), ``lt[j, i] = H[j + i, j]``)
    frame block by frame block (blocks end at ``cuts``, in frames; none: the whole band in
    one block), as :class:`~stemmap.slam._ekf_stream.StreamedStep` does."""
    nc = lt.shape[0]
    bands, ys = [], []
    carry = None
    edges = [0, *cuts, nc // 3]
    for lo, hi in itertools.pairwise(edges):
        last = hi == nc // 3
        end = 3 * hi if last else 3 * hi + st.KD
        a, r = lt[3 * lo : end].copy(), rhs[3 * lo : end].copy()
        if carry is not None:
            a[: st.KD], r[: st.KD] = carry
        m = 3 * (hi - lo)
        t, y = st.band_forward(a, r, m, factor=True)
        bands.append(t[:m])
        ys.append(y[:m])
        carry = None if last else (t[m : m + st.KD], y[m : m + st.KD])
    x, after = [], None
    for band, y in zip(reversed(bands), reversed(ys), strict=True):
        after = st.band_backward(band, y, after)
        x.append(after)
    return np.concatenate(bands), np.concatenate(x[::-1])


def _band_system(seed: int, n: int, spread: bool) -> tuple[np.ndarray, ...]:
    """A random SPD block-tridiagonal information of ``n`` frames as ``lt`` (3n, KD+1), its
    LAPACK banded storage (KD+1, 3n) and the dense matrix; ``spread``: the first variable of
    each frame scaled by 0.5-2,000 (a spread of magnitudes: rounding is exercised)."""
    rng = np.random.default_rng(seed)
    diag, off, H = _random_chain(rng, n)
    if spread:
        diag[:, 0, 0] *= rng.uniform(0.5, 2e3, n)
        H[np.arange(0, 3 * n, 3), np.arange(0, 3 * n, 3)] = diag[:, 0, 0]
    ab = banded_lower(diag, off)
    return np.ascontiguousarray(ab.T), ab, H


@pytest.mark.parametrize("cuts", [[2], [2, 4, 9], [5, 7, 9, 20, 22, 24], [45]])
def test_blocks_give_the_bytes_of_the_whole_band_solve(cuts):
    """Factor and solution of a block-tridiagonal SPD system cut into frame blocks of 2-45
    frames equal the same kernels run over the whole band in one block, bit for bit (one and
    three right-hand sides of mixed magnitudes): a block and its carry are the whole-band
    loop run in pieces (stemmap.slam._band_kernel), whatever BLAS the machine has."""
    lt, _, _ = _band_system(11, 47, spread=True)
    rng = np.random.default_rng(12)
    for r in (1, 3):
        rhs = rng.normal(size=(lt.shape[0], r)) * 10.0 ** rng.integers(-3, 4, (lt.shape[0], 1))
        whole_f, whole_x = _blocked(lt, rhs, [])
        factor, x = _blocked(lt, rhs, cuts)
        np.testing.assert_array_equal(factor, whole_f)
        np.testing.assert_array_equal(x, whole_x)


def _reference_python(lt: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The kernels' algorithm in plain Python floats (each ``*``, ``-``, ``/``, ``sqrt``
    rounded once: no fused multiply-add, no reassociation), on lists."""
    n = lt.shape[0]
    L = [list(map(float, row)) for row in lt]
    y = [float(v) for v in b]
    for j in range(n):
        L[j][0] = math.sqrt(L[j][0])
        nb = min(st.KD, n - 1 - j)
        for i in range(1, nb + 1):
            L[j][i] = L[j][i] / L[j][0]
        for q in range(1, nb + 1):
            for p in range(q, nb + 1):
                L[j + q][p - q] = L[j + q][p - q] - L[j][p] * L[j][q]
    for j in range(n):
        y[j] = y[j] / L[j][0]
        for i in range(1, min(st.KD, n - 1 - j) + 1):
            y[j + i] = y[j + i] - L[j][i] * y[j]
    for j in range(n - 1, -1, -1):
        for i in range(1, min(st.KD, n - 1 - j) + 1):
            y[j] = y[j] - L[j][i] * y[j + i]
        y[j] = y[j] / L[j][0]
    return np.array(L), np.array(y)


def test_band_kernels_round_each_operation_once():
    """The compiled kernels equal the same algorithm in plain Python floats bit for bit: no
    fused multiply-add or reordering crept in (numba without fastmath), so the bytes are the
    IEEE 754 ones, the same on every CPU."""
    lt, _, _ = _band_system(13, 20, spread=True)
    b = np.random.default_rng(14).normal(size=lt.shape[0]) * 10.0 ** np.arange(-3, 3).repeat(10)
    factor, x = _blocked(lt, b[:, None], [3, 4, 11])
    want_f, want_x = _reference_python(lt, b)
    np.testing.assert_array_equal(factor, want_f)
    np.testing.assert_array_equal(x[:, 0], want_x)


@pytest.mark.parametrize(("seed", "n", "spread"), [(21, 300, False), (11, 47, True)])
def test_band_solve_agrees_with_lapack_to_rounding(seed, n, spread):
    """Against LAPACK (``cholesky_banded``, ``solveh_banded``, ``cho_solve_banded``) on a
    random chain, blocks of 64 / 9 frames: both are backward-stable Cholesky solves, so they
    differ by rounding only. A factor entry is at most KD + 1 products, a square root or a
    division of numbers bounded by its column's pivot (SPD: no growth), so the two factors
    differ by a few ulps of ``|L_jj|`` (measured ≤ 0.94 ε here, 1.5 ε on 10,000 frames;
    bound 4 ε). The solutions differ by ~κ(H) ε in norm (perturbation bound of a
    backward-stable solve; measured 2.7e-16 / 2.5e-16 of ``max |x|`` for κ = 17 / 1.4e4;
    bound 16 κ ε) -- not elementwise: a small component of ``x`` from cancelling terms
    carries the rounding of the large ones. Any real error (a wrong update, a lost carry)
    is of order 1."""
    lt, ab, H = _band_system(seed, n, spread)
    eps, kappa = np.finfo(float).eps, np.linalg.cond(H)
    assert kappa < (1e5 if spread else 100)
    rhs = np.random.default_rng(22).normal(size=(lt.shape[0], 3))
    factor, x = _blocked(lt, rhs, list(range(64 if n > 64 else 9, n, 64 if n > 64 else 9)))
    ref = cholesky_banded(ab, lower=True)
    assert np.all(np.abs(factor - ref.T) <= 4 * eps * np.abs(factor[:, :1]))
    assert np.any(factor != ref.T)  # (not LAPACK's bytes: the comparison is a real one)
    bound = 16 * kappa * eps * np.abs(x).max(axis=0)
    for want in (solveh_banded(ab, rhs, lower=True), cho_solve_banded((ref, True), rhs)):
        np.testing.assert_allclose(x, want, rtol=0, atol=float(bound.max()))
    np.testing.assert_allclose(H @ x, rhs, rtol=0, atol=1e-12 * np.abs(rhs).max())


def _long_drive(n: int, seed: int = 2) -> tuple:
    """A slow arc of ``n`` frames past 6 landmarks, each frame seeing up to 2 (smooth_path's
    arguments, a drifted start)."""
    rng = np.random.default_rng(seed)
    th = np.linspace(0.0, 1.2, n)
    true = np.column_stack((60 * np.sin(th), 60 * (1 - np.cos(th)), th))
    lm = np.column_stack((60 * np.sin(np.linspace(0, 1.2, 6)) * 1.1, np.linspace(0, 25, 6)))
    obs = _observe(true, lm, (1.0, 0.2), 30.0, 2, rng, (0.2, math.radians(1.0)))
    deltas, covs, _, start = _drifted_chain(true)
    R1 = np.diag([0.2**2, math.radians(1.0) ** 2])
    marg = np.broadcast_to(0.01 * np.eye(2), (lm.shape[0], 2, 2)).copy()
    S = 0.1**2 * np.eye(2 * lm.shape[0]) + 0.02**2
    return (start, deltas, covs, obs, lm, marg, (1.0, 0.2), R1), S


def test_tiny_blocks_keep_the_working_set_bounded_and_the_result_unchanged(monkeypatch):
    """``smooth_path`` on 8,000 frames with the frames swept 64 at a time and the
    measurements assembled 500 at a time: the same path, covariances and statistics bit for
    bit as one block over the whole drive (``_SEG`` above the frame count: the whole-band
    solve), and beside its inputs and the (N, 3) + (N, 3, 3) result it allocates at most
    ~1.1 MB more (peak, tracemalloc), where the whole-band solve held the band, its factor,
    ``diag``/``off``, the iterates and the marginals: ~0.9 kB per frame, 7 MB here."""
    args, S = _long_drive(8_000)
    n = args[0].shape[0]
    monkeypatch.setattr(sm, "_CHUNK", 500)
    peaks, outs = {}, {}
    for seg in (64, n + 1):
        monkeypatch.setattr(st, "_SEG", seg)
        tracemalloc.start()
        outs[seg] = smooth_path(*args, map_cov=S)
        peaks[seg] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    small, whole = outs[64], outs[n + 1]
    np.testing.assert_array_equal(small[0], whole[0])
    np.testing.assert_array_equal(small[1], whole[1])
    assert small[2] == whole[2] and small[2]["smoother_iterations"] > 1
    # the path and covariances returned, the map term summed over its column blocks (N x 3 x
    # 3) and its forward solution (3 N x 2L doubles: bounded by block_mb, as the whole
    # solve's), then a few blocks' working arrays
    result = n * 8 * (3 + 9 + 9)
    ys = 3 * n * S.shape[0] * 8
    assert peaks[64] < result + ys + 1.1e6
    assert peaks[n + 1] > result + ys + 5e6  # (the bound is not trivially met)


@pytest.mark.parametrize("update", ["compressed", "full"])
@pytest.mark.parametrize("smooth", [True, False])
def test_filter_inputs_on_disk_leave_the_result_unchanged(monkeypatch, update, smooth):
    """EkfSlam with the pre-integrated odometry and the filtered poses kept 7 rows in memory
    (the rest in their temporary files) and the smoother sweeping 5 frames at a time: the
    same path, covariances, map and statistics bit for bit as with the defaults."""
    from _synthetic import loop_problem

    import stemmap.slam._ekf_compressed as ekf_c
    import stemmap.slam.ekf as ekf_mod
    from stemmap.slam.ekf import EkfSlam

    problem, *_ = loop_problem(1, laps=1.3)
    ref = EkfSlam(update=update, smooth=smooth).run(problem)
    made: list[st.FrameInputs] = []

    class Small(st.FrameInputs):
        def __init__(self, deltas: np.ndarray, covs: np.ndarray) -> None:
            super().__init__(deltas, covs, resident_rows=7)
            made.append(self)

    monkeypatch.setattr(ekf_c, "FrameInputs", Small)
    monkeypatch.setattr(ekf_mod, "FrameInputs", Small)
    monkeypatch.setattr(st, "_SEG", 5)
    got = EkfSlam(update=update, smooth=smooth).run(problem)
    assert len(made) == 1 and made[0]._odo.spilled > 20 * 7 and made[0]._path.spilled > 20 * 7
    np.testing.assert_array_equal(got.trajectory.poses, ref.trajectory.poses)
    if smooth:
        np.testing.assert_array_equal(got.pose_covs, ref.pose_covs)
    np.testing.assert_array_equal(got.stem_map.xy, ref.stem_map.xy)
    drop = ("runtime_s",)
    assert {k: v for k, v in got.stats.items() if k not in drop} == {
        k: v for k, v in ref.stats.items() if k not in drop
    }
