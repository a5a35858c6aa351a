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
    assert diameter_errors([0.3], [0.3]).by_range == ()


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
