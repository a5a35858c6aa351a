"""The ``stemmap`` preset is LOO grid 80 (issue 11, Dec 5; docs/algorithms/scan-detection.md,
"Grid 80 is the `stemmap` preset").

Grid 80 = grid 67 (the preset before) + the stub test by runs of end returns read as data
snooping on the side of an inner worst return (``stub_sigmas`` 2, ``stub_runs``,
``stub_runs_snoop``, ``stub_runs_worst``), the cut-end trim (``cut_ends``) and the batch's
range noise by the biweight (``batch_noise_scale``). The trims act on first-echo fits only
(``beam_footprint_deg`` > 0 or thin beams: the numpy path); an averaging scanner (a SICK, the
simulator) keeps the compiled path, and its detections are grid 67's bit for bit."""

import math

import numpy as np
from tests.scan.test_edge_protrusion import STEP
from tests.scan.test_fit_noise_default import sick_drive
from tests.scan.test_stub_runs import GRID_67, R, _errors, _scan

from _loo_grid import LOO_GRID  # benchmarks/ is on sys.path (tests/conftest.py)
from stemmap.scan.detect import PRESETS, DetectorConfig, ScanTrunkDetector

#: The options grid 80 adds to grid 67 (the fields of GRID_67), at their grid-80 values.
GRID_80_ADDS = {field: LOO_GRID[80][field] for field in GRID_67}


def test_the_stemmap_preset_is_loo_grid_80():
    preset = DetectorConfig.preset("stemmap")
    for field, value in LOO_GRID[80].items():
        assert getattr(preset, field) == value, field
    # the one grid point that equals the preset (what kasa_count.py and the LOO call the
    # default), and grid 67 is the preset before with exactly the six options changed
    same = [g for g, s in enumerate(LOO_GRID) if DetectorConfig.preset("stemmap", **s) == preset]
    assert same == [80]
    assert DetectorConfig.preset("stemmap", **LOO_GRID[67]) == DetectorConfig.preset(
        "stemmap", **GRID_67
    )
    assert DetectorConfig.preset("stemmap", **{**LOO_GRID[67], **GRID_80_ADDS}) == preset
    # the six fields the flip changed: on in grid 80, off in grid 67
    assert all(GRID_80_ADDS[f] != GRID_67[f] for f in GRID_67)


def test_the_paper_presets_keep_their_published_fits():
    plain = DetectorConfig()
    for name in PRESETS:
        if name == "stemmap":
            continue
        cfg = DetectorConfig.preset(name)
        for field in GRID_80_ADDS:
            assert getattr(cfg, field) == getattr(plain, field), (name, field)
        assert math.isinf(cfg.stub_sigmas) and cfg.batch_noise_scale == "mad"


def test_a_first_echo_default_drops_the_branch_run():
    # test_stub_runs's scene: a bar leaving a 30 cm stem's flank over several beams, 0.5 deg
    # first-echo, no noise, 12 bearings within 5 beams, seen from 1.5 m
    before, _ = _errors(1.5, 0.06, False)  # the fits at the tests' sigma, no run test
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", beam_footprint_deg=STEP))
    assert not det._compiled(None, None)
    plain67 = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", beam_footprint_deg=STEP, **GRID_67)
    )
    err, err67, foreign = [], [], []
    for k in range(12):
        batch, centre, hit = _scan(1.5, 0.3 + k * math.radians(STEP) * 5.3 / 12, 0.06)
        for d, out in ((det, err), (plain67, err67)):
            obs = d.detect_batch(batch)
            near = np.hypot(*(obs.centers - centre).T) < 0.1
            assert np.count_nonzero(near) == 1
            out.append(200.0 * (obs.radii[near][0] - R))
            if d is det:
                foreign.append(int(obs.n_points[near][0]) - int(np.count_nonzero(hit[0] == 0)))
    # grid 67 fits the bar with the stem (measured +4.5 ... +6.6 cm, as the tests' sigma);
    # the default deletes the bar's run: at most the two returns at its root stay
    assert np.mean(err67) > 3.0 and before.mean() > 3.0
    assert max(foreign) <= 2
    assert abs(np.mean(err)) < 1.0
    assert np.abs(err).max() < 2.0


def test_an_averaging_default_is_grid_67_bit_for_bit():
    # a simulated SICK LMS drive with clutter (the simulator's averaging beam): the compiled
    # path, where the trims never act and the biweight batch noise leaves every step
    # threshold where it was (max(sigma, estimate): the scans hold their own estimates)
    batch = sick_drive()
    new = ScanTrunkDetector("stemmap")
    old = ScanTrunkDetector(DetectorConfig.preset("stemmap", **GRID_67))
    assert new._compiled(None, None) and old._compiled(None, None)
    a, b = new.detect_batch(batch), old.detect_batch(batch)
    assert len(a) > 0
    for x, y in (
        (a.index, b.index),
        (a.centers, b.centers),
        (a.radii, b.radii),
        (a.covs, b.covs),
        (a.n_points, b.n_points),
    ):
        np.testing.assert_array_equal(x, y)
