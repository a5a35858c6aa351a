"""Bounded working memory of the iSAM2 back-end on long drives (issue 13, "Soak")."""

from __future__ import annotations

import tracemalloc

import numpy as np
from _synthetic import loop_problem  # tests/slam is on sys.path (pytest rootdir-less mode)

import stemmap.slam._graph_run as graph_run
import stemmap.slam.graph as graph
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
    # (a block is longer only by the left-out run it ends in: ~200-300 frames here)
    assert peak_blocked < 1.25 * result_bytes + 8 * nf + 1_000_000


def test_isam2_trims_the_heap_when_used_as_a_library(monkeypatch):
    """``Isam2Slam.run`` trims the heap from its keyframe loop (not only under ``stemmap
    map``), at most once per interval of CPU time; the trims change no value."""
    problem, *_ = loop_problem(3, laps=0.5)
    counts = []

    class Counting(graph_run.HeapTrimmer):
        def __init__(self, *a, **k):
            super().__init__(*a, trim=lambda: counts.append(1) or True, **k)

    off = graph.Isam2Slam().run(problem)  # (interval 0.2 s of CPU: a few trims at most)
    monkeypatch.setattr(graph_run, "HeapTrimmer", Counting)
    monkeypatch.setattr(graph_run, "TRIM_INTERVAL_S", 0.0)  # every keyframe
    on = graph.Isam2Slam().run(problem)
    assert len(counts) == on.stats["keyframes"]
    assert np.array_equal(on.trajectory.poses, off.trajectory.poses)
    assert np.array_equal(on.pose_covs, off.pose_covs)
    assert np.array_equal(on.stem_map.xy, off.stem_map.xy)
