import math

import numpy as np
import pytest

from stemmap import InputError, LaserScan, Pose2, ScanBatch, StemObservations, Trajectory
from stemmap.types import wrap_angle


def test_laserscan_invalid_returns_are_no_return_not_errors():
    scan = LaserScan(
        [1.0, np.nan, np.inf, 0.01, 50.0, 2.0], -0.1, 0.04, range_min=0.05, range_max=30
    )
    assert scan.valid.tolist() == [True, False, False, False, False, True]
    pts = scan.points()
    assert pts.shape == (2, 2)
    np.testing.assert_allclose(pts[0], [math.cos(-0.1), math.sin(-0.1)])


def test_laserscan_is_immutable_and_copies_input():
    r = np.array([1.0, 2.0, 3.0])
    scan = LaserScan(r, 0.0, 0.1)
    r[0] = 99.0
    assert scan.ranges[0] == 1.0
    with pytest.raises(ValueError, match="read-only"):
        scan.ranges[0] = 5.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"ranges": np.zeros((2, 2))}, "1-dimensional"),
        ({"ranges": ["a", "b"]}, "numeric"),
        ({"angle_increment": 0.0}, "non-zero"),
        ({"angle_increment": np.nan}, "finite"),
        ({"range_min": 5.0, "range_max": 1.0}, "range_min < range_max"),
        ({"intensities": [1.0]}, "intensities has 1"),
    ],
)
def test_laserscan_bad_input_names_the_problem(kwargs, message):
    base = {"ranges": [1.0, 2.0], "angle_min": 0.0, "angle_increment": 0.1}
    base.update(kwargs)
    with pytest.raises(InputError, match=message):
        LaserScan(**base)


def test_scanbatch_roundtrip_and_geometry_check():
    scans = [LaserScan(np.full(5, k + 1.0), -0.2, 0.1, time=k) for k in range(3)]
    batch = ScanBatch.from_scans(scans)
    assert batch.ranges.shape == (3, 5)
    assert batch[2].time == 2.0
    np.testing.assert_array_equal(batch[1].ranges, scans[1].ranges)
    with pytest.raises(InputError, match="different beam geometry"):
        ScanBatch.from_scans([scans[0], LaserScan(np.ones(4), -0.2, 0.1)])


def test_wrap_angle_range():
    a = np.array([-math.pi, math.pi, 3 * math.pi, -3 * math.pi + 1e-9, 0.5])
    w = wrap_angle(a)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    assert w[0] == pytest.approx(math.pi)


def test_pose_compose_inverse_identity(rng):
    for _ in range(20):
        p = Pose2(*rng.normal(size=3))
        ident = p.compose(p.inverse())
        assert abs(ident.x) < 1e-12 and abs(ident.y) < 1e-12 and abs(ident.theta) < 1e-12
        pts = rng.normal(size=(4, 2))
        back = p.inverse().transform_points(p.transform_points(pts))
        np.testing.assert_allclose(back, pts, atol=1e-12)


def test_trajectory_rejects_time_going_backwards():
    with pytest.raises(InputError, match="strictly increasing"):
        Trajectory([0.0, 1.0, 0.5], np.zeros((3, 3)))


def test_observations_select_and_concat():
    obs = StemObservations(
        centers=[[1, 2], [3, 4]],
        radii=[0.1, 0.2],
        covs=np.zeros((2, 3, 3)),
        n_points=[5, 6],
        arc_deg=[90, 80],
        widths=[0.2, 0.4],
        quality=[1, 1],
        index=[0, 1],
        times=[0.0, 0.1],
    )
    both = StemObservations.concatenate([obs, obs.select([1])])
    assert len(both) == 3
    assert both[2].radius == 0.2
    assert both.diameters.tolist() == [0.2, 0.4, 0.4]
    assert len(StemObservations.empty()) == 0
