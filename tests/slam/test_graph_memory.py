"""Bounded working memory of the iSAM2 back-end on long drives (issue 13, "Soak")."""

from __future__ import annotations

import tracemalloc

import numpy as np

from stemmap.slam._graph_odometry import frame_covariances


def _drive(rng: np.random.Generator, nk: int, every: int, left_out: float):
    """Random keyframe marginals (a share ``left_out`` of them NaN: left out of the graph)
    and frame increments, as :func:`frame_covariances` takes them."""
    nf = nk * every - 1
    kf_of = np.arange(nf) // every
    kf_frames = np.arange(0, nf, every)
    a = rng.normal(size=(nk, 3, 3))
    kf_cov = a @ np.swapaxes(a, 1, 2) * 0.01
    out = rng.random(nk) < left_out
    out[0] = False
    # long left-out runs too (a revisit localised on the map), as on the soak
    out[nk // 3 : nk // 3 + 40] = True
    kf_cov[out] = np.nan
    d_f = rng.normal(size=(nf, 3)) * 0.1
    b = rng.normal(size=(nf, 3, 3))
    cov_f = b @ np.swapaxes(b, 1, 2) * 1e-4
    theta = rng.uniform(-np.pi, np.pi, nf)
    return kf_cov, kf_of, kf_frames, d_f, cov_f, theta


def _traced_peak(fn):
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        out = fn()
        return out, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_frame_covariances_in_blocks_are_the_same_bytes_in_bounded_memory(rng):
    """The covariance bridge of every frame (docs/outputs.md) computed in blocks cut at graph
    keyframes gives the same bytes as one block (the gaps' odometry variance is summed over
    the whole drive), and its working memory besides the (N, 3, 3) result is that of one
    block: with blocks of 256 frames on a 20,000-frame drive the peak is the result plus a
    little, where one block holds ~6 frame-length (N, 3, 3) temporaries."""
    args = _drive(rng, nk=4000, every=5, left_out=0.6)
    nf = args[1].size
    whole, peak_whole = _traced_peak(lambda: frame_covariances(*args[:5], (3.78, 0.5), args[5],
                                                               block=10**9))  # fmt: skip
    for block in (1, 7, 256):
        got = frame_covariances(*args[:5], (3.78, 0.5), args[5], block=block)
        assert np.array_equal(got, whole, equal_nan=True), block
    blocked, peak_blocked = _traced_peak(
        lambda: frame_covariances(*args[:5], (3.78, 0.5), args[5], block=256)
    )
    result_bytes = nf * 9 * 8
    assert np.array_equal(blocked, whole, equal_nan=True)
    assert peak_whole > 4 * result_bytes  # (one block: the temporaries are frame-length)
    # the result, the drive-long variance sum (8 B per frame) and blocks of <= 256 frames
    # (the longest left-out run here is 205 frames)
    assert peak_blocked < 1.25 * result_bytes + 8 * nf + 1_000_000
