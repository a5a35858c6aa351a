import json
import math

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval import diameter_errors


def test_overall_and_binned_statistics():
    truth = np.array([0.20, 0.30, 0.40, 0.50])
    est = np.array([0.21, 0.28, 0.46, 0.50])
    r = np.array([1.0, 4.0, 7.0, 12.0])
    e = diameter_errors(est, truth, ranges=r)
    err = est - truth
    assert e.overall.n == 4
    assert e.overall.rmse == pytest.approx(math.sqrt(np.mean(err**2)))
    assert e.overall.bias == pytest.approx(err.mean())
    assert e.overall.max_abs == pytest.approx(0.06)
    assert e.overall.relative_bias == pytest.approx(np.mean(err / truth))
    near, mid, far, beyond = e.by_range
    assert (near.n, mid.n, far.n, beyond.n) == (2, 1, 1, 0)
    assert mid.bias == pytest.approx(0.06) and far.rmse == 0.0
    assert math.isnan(beyond.rmse)
    d = json.loads(json.dumps(e.to_dict()))
    assert d["by_range"][3]["rmse"] is None


def test_no_ranges_gives_no_bins():
    e = diameter_errors([0.3, 0.2], [0.3, 0.25])
    assert e.by_range == ()
    assert e.overall.n == 2 and e.overall.bias == pytest.approx(-0.025)


def test_two_edges_make_one_bin():
    e = diameter_errors([0.3, 0.2], [0.3, 0.25], ranges=[1.0, 30.0], range_bins=(0.0, 10.0))
    assert len(e.by_range) == 1
    assert (e.by_range[0].n, e.by_range[0].bias) == (1, 0.0)  # 30 m is beyond the last edge


@pytest.mark.parametrize(
    ("est", "tru", "kw", "match"),
    [
        ([0.3, 0.2], [0.3], {}, "truth has"),
        ([np.nan], [0.3], {}, "NaN"),
        ([0.3], [0.0], {}, "positive"),
        ([0.3], [0.3], {"ranges": [1.0, 2.0]}, "ranges"),
        ([0.3], [0.3], {"ranges": [1.0], "range_bins": (1.0,)}, "range_bins"),
    ],
)
def test_bad_inputs(est, tru, kw, match):
    with pytest.raises(InputError, match=match):
        diameter_errors(est, tru, **kw)


def test_every_statistic_of_a_bin_and_the_half_open_edges():
    """Each field against its definition, with a pair exactly on an edge (5 m -> [5, 10))."""
    truth = np.array([0.20, 0.40, 0.25, 0.50])
    est = np.array([0.18, 0.46, 0.25, 0.47])
    r = np.array([0.0, 5.0, 9.999, 10.0])
    e = diameter_errors(est, truth, ranges=r, range_bins=(0.0, 5.0, 10.0, 20.0))
    err, rel = est - truth, (est - truth) / truth
    o = e.overall
    assert (o.range_lo, o.range_hi, o.n) == (0.0, math.inf, 4)
    assert o.mae == pytest.approx(np.mean(np.abs(err)))
    assert o.max_abs == pytest.approx(0.06)  # the largest |error|, of either sign
    assert o.relative_rmse == pytest.approx(math.sqrt(np.mean(rel**2)))
    assert o.relative_bias == pytest.approx(np.mean(rel))
    # +2.5 mm in metres but -0.25 % relative: the two biases are computed separately
    assert o.bias == pytest.approx(np.mean(err)) and o.bias > 0 > o.relative_bias
    first, second, third = e.by_range
    assert (first.range_lo, first.range_hi, first.n) == (0.0, 5.0, 1)  # r = 0 is in
    assert (second.range_lo, second.range_hi, second.n) == (5.0, 10.0, 2)  # 5 in, 9.999 in
    assert (third.range_lo, third.range_hi, third.n) == (10.0, 20.0, 1)  # 10 starts the next
    assert first.bias == pytest.approx(-0.02) and first.mae == pytest.approx(0.02)
    assert first.max_abs == pytest.approx(0.02) and first.rmse == pytest.approx(0.02)
    assert first.relative_bias == pytest.approx(-0.1)
    assert first.relative_rmse == pytest.approx(0.1)
    assert second.rmse == pytest.approx(math.sqrt((0.06**2 + 0.0) / 2))
    assert second.bias == pytest.approx(0.03) and second.max_abs == pytest.approx(0.06)
    assert third.relative_bias == pytest.approx(-0.06)
    # an empty bin: every statistic NaN, written as null; the counts and edges stay
    empty = diameter_errors([0.3], [0.3], ranges=[1.0], range_bins=(0.0, 2.0, 3.0)).by_range[1]
    assert empty.n == 0 and (empty.range_lo, empty.range_hi) == (2.0, 3.0)
    for k in ("rmse", "bias", "mae", "max_abs", "relative_rmse", "relative_bias"):
        assert math.isnan(getattr(empty, k))
    d = empty.to_dict()
    assert d["n"] == 0 and d["range_hi"] == 3.0 and d["bias"] is None and d["mae"] is None
    # the overall bin's infinite upper edge is written as null (JSON has no inf)
    assert e.to_dict()["overall"]["range_hi"] is None
    assert e.to_dict()["overall"]["n"] == 4
    assert len(e.to_dict()["by_range"]) == 3


def test_inputs_are_flattened_and_messages_name_the_counts():
    e = diameter_errors([[0.3, 0.2]], [[0.3], [0.25]], ranges=[[1.0, 2.0]])
    assert e.overall.n == 2 and e.by_range[0].n == 2
    with pytest.raises(InputError, match="estimate has 2 diameters but truth has 1"):
        diameter_errors([0.3, 0.2], [0.3])
    with pytest.raises(InputError, match="ranges has 1 values for 2 diameter pairs"):
        diameter_errors([0.3, 0.2], [0.3, 0.2], ranges=[1.0])
    with pytest.raises(
        InputError, match=r"^estimate contains NaN or inf diameters; drop .*first\.$"
    ):
        diameter_errors([math.inf], [0.3])
    with pytest.raises(InputError, match=r"^every truth diameter must be positive \(metres\)\.$"):
        diameter_errors([0.3], [-0.3])
    with pytest.raises(InputError, match="positive"):
        diameter_errors([0.3], [math.nan])
    # edges must increase strictly: equal or falling edges are refused, and so is one edge
    for bins in ((0.0, 5.0, 5.0), (5.0, 0.0), ()):
        with pytest.raises(InputError, match="strictly increasing"):
            diameter_errors([0.3], [0.3], ranges=[1.0], range_bins=bins)
