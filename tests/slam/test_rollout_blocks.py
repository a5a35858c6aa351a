"""preintegrate's pose-only path (rollout, the map command's metrics) in blocks: bit-identical to
the whole-array integration, in memory bounded by the block size (issue 13, Soak)."""

from __future__ import annotations

import hashlib
import tracemalloc

import numpy as np
import pytest

from stemmap.slam.base import Controls
from stemmap.slam.motion import (
    AckermannModel,
    UnicycleModel,
    _poses_blocked,
    _poses_whole,
    preintegrate,
    preintegrate_spans,
    rollout,
)


def _whole_array(model, controls, tq, p0):
    """The whole-array integration (preintegrate's covariance path, unchanged from before the
    blocks: the same VP covariance hashes before and after)."""
    return _poses_whole(model, controls, tq, p0)[:2]


def _sha(*arrays):
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()


def _stream(rng, n, kind):
    """n controls at jittered 40 Hz, query times that repeat, coincide with control times and
    start before the first control."""
    t = np.cumsum(rng.uniform(0.005, 0.05, n))
    if kind == "ackermann":
        c = Controls(t, 3 + rng.normal(size=n), 0.3 * rng.normal(size=n), kind)
    else:
        c = Controls(t, 2 + rng.normal(size=n), 0.5 * rng.normal(size=n), kind)
    nq = max(n // 10, 3)
    tq = np.sort(np.concatenate((rng.uniform(-1.0, t[-1] + 1.0, nq), rng.choice(t, nq // 4))))
    tq = np.concatenate((tq[:5], tq[4:5], tq[5:]))  # a repeated query time
    return c, tq


@pytest.mark.parametrize("kind", ["ackermann", "unicycle"])
@pytest.mark.parametrize(("n", "block"), [(2_000, 1), (20_000, 7), (20_000, 64), (60_000, 4096)])
def test_blocks_are_bit_identical_to_the_whole_array(kind, n, block):
    rng = np.random.default_rng(n + block)
    model = AckermannModel() if kind == "ackermann" else UnicycleModel()
    c, tq = _stream(rng, n, kind)
    p0 = np.array([12.3, -4.5, 3.1])  # the heading wraps soon
    ref = _whole_array(model, c, tq, p0)
    got = _poses_blocked(model, c, tq, p0, block=block)
    assert _sha(*got) == _sha(*ref)
    # the public path and the (unchanged) covariance path agree with it too
    pre = preintegrate(model, c, tq, p0, with_covariance=False)
    assert _sha(pre.poses, pre.distance) == _sha(*ref)
    if n <= 20_000:
        full = preintegrate(model, c, tq, p0)
        assert _sha(full.poses, full.distance, full.deltas) == _sha(*ref, pre.deltas)
        assert np.all(np.isnan(pre.covs)) and pre.covs.shape == full.covs.shape
    # no covariance stack is allocated: a read-only view of one NaN (also across spans)
    assert pre.covs.strides == (0, 0, 0) and not pre.covs.flags.writeable
    spans = preintegrate_spans(model, c, tq, p0, span_s=(tq[-1] - tq[0]) / 3.0,
                               with_covariance=False)  # fmt: skip
    assert spans.covs.strides == (0, 0, 0) and spans.covs.shape == pre.covs.shape
    assert np.all(np.isnan(spans.covs))


def test_blocks_edge_streams():
    model = AckermannModel()
    t = np.arange(10.0)
    c = Controls(t, np.ones(10), np.full(10, 0.1), "ackermann")
    p0 = np.array([1.0, 2.0, -0.5])
    for tq in (np.array([3.0, 3.0, 3.0]), np.array([-5.0, -2.0]), np.array([20.0, 30.0])):
        for block in (1, 2, 1 << 14):
            assert _sha(*_poses_blocked(model, c, tq, p0, block=block)) == _sha(
                *_whole_array(model, c, tq, p0)
            )


def test_rollout_memory_is_bounded_by_the_block():
    """A 400,000-control stream: the whole-array integration holds a dozen arrays of every
    segment (> 20 MB); the blocked one a dozen arrays of one block plus the F poses."""
    rng = np.random.default_rng(5)
    n = 400_000
    t = np.cumsum(rng.uniform(0.02, 0.03, n))
    c = Controls(t, 3 + rng.normal(size=n), 0.3 * rng.normal(size=n), "ackermann")
    tq = np.linspace(t[0], t[-1], 2_000)
    model = AckermannModel()
    bound = 8e6  # bytes

    def peak(fn):
        tracemalloc.start()
        try:
            fn()
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    whole = peak(lambda: _whole_array(model, c, tq, np.zeros(3)))
    blocked = peak(lambda: rollout(model, c, tq))
    assert whole > bound > blocked, (whole, blocked)
