"""The compiled detector against the numpy pipeline on virtual 2D scans of the real slices
(../shared/datasets), with the validated concave-corner split of rejected candidates
(``refit_split="corners"``, issue 11) and the largest consistent arc (``arc_refit``) that the
simulator rarely triggers: the real merges (a trunk with a branch or a second stem in one
segment) are what they are for.

Without a footprint correction (the compiled path needs none), both scanner models, range
noise 0 and 1 cm; every detection must match (tests/scan/test_detect_fast.py's rule).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from tests.scan.test_detect_fast import _both, assert_same

from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch, virtual_scans
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

SPLIT = {"refit_pieces": True, "refit_split": "corners", "refit_validate": True}
SPLITS = {
    "validated": SPLIT,
    # every passing piece, convex candidates cut too (the RMS-failed path and the pre-fit
    # bound's exact re-fit; several pieces per candidate)
    "unvalidated_convex": {**SPLIT, "refit_validate": False, "corner_depth_convex": 0.10},
}


@pytest.fixture(scope="module")
def real_batches(datasets_dir):
    out = []
    rng = np.random.default_rng(4)
    for name in SLICES:
        sl = load_slice(datasets_dir, name)
        if not sl.refs:
            continue
        # 8 vantage points 1-12 m from random reference trunks, outside every object
        c = sl.centers[rng.integers(0, sl.centers.shape[0], 8)]
        b = rng.uniform(-np.pi, np.pi, 8)
        d = rng.uniform(1.0, 12.0, 8)
        vp = c + d[:, None] * np.c_[np.cos(b), np.sin(b)]
        for model in ("nearest", "averaging"):
            ranges0, _ = virtual_scans(
                sl.xy, sl.labels, vp, resolution_deg=0.5, model=model, centers=sl.centers
            )
            for noise in (0.0, 0.01):
                out.append((f"{name}/{model}/{noise}", noisy_batch(ranges0, 0.5, noise, rng)))
    return out


def _same_on_every_batch(det, batches):
    """Assert the compiled path equals the numpy path on every batch; yield (numpy result,
    batch)."""
    assert det._compiled(None, None)
    for label, batch in batches:
        fast, ref = _both(det, batch)
        try:
            assert_same(fast, ref)
        except AssertionError as err:
            raise AssertionError(label) from err
        yield ref, batch


@pytest.mark.slow
@pytest.mark.parametrize("split", sorted(SPLITS))
def test_compiled_corner_split_equals_numpy_on_real_slices(real_batches, split):
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **SPLITS[split]))
    base = ScanTrunkDetector(DetectorConfig.preset("stemmap", refit_pieces=False))
    gained = 0
    for ref, batch in _same_on_every_batch(det, real_batches):
        gained += len(ref) - len(_both(base, batch)[1])
    assert gained > 0  # the split found trunks the default rejects: the path was exercised


# the fourth round's arcs: no replacement, no tangent or chi-square test (the stemmap
# preset's since the fifteenth round: replace3_consistent)
ARCS = {
    "arc_refit": True,
    "arc_sigmas": 2.0,
    "arc_replace": math.inf,
    "arc_tangent_sigmas": math.inf,
    "arc_chi2": False,
}
ARC_SETTINGS = {
    # the leave-one-dataset-out choices (scan-detection-history.md, fifth and fourteenth rounds)
    "replace3": {**ARCS, "arc_replace": 3.0},
    "replace2_short_steps": {**ARCS, "arc_replace": 2.0, "arc_short_steps": True},
    # fifteenth round: ... in front of the tangent range, residuals of the noise
    "replace3_consistent": {
        **ARCS,
        "arc_replace": 3.0,
        "arc_tangent_sigmas": 3.0,
        "arc_chi2": True,
    },
    # sixteenth round: ... and short arcs set off by a range step (the TreeLS plot's merges)
    "replace3_consistent_short_steps": {
        **ARCS,
        "arc_replace": 3.0,
        "arc_tangent_sigmas": 3.0,
        "arc_chi2": True,
        "arc_short_steps": True,
    },
    # without the corner split: every non-convex merge goes to the arc
    "no_split": {**ARCS, "refit_pieces": False},
}


@pytest.mark.slow
@pytest.mark.parametrize("arcs", sorted(ARC_SETTINGS))
def test_compiled_arcs_equal_numpy_on_real_slices(real_batches, arcs):
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **ARC_SETTINGS[arcs]))
    base = ScanTrunkDetector(
        DetectorConfig.preset(
            "stemmap",
            refit_pieces=ARC_SETTINGS[arcs].get("refit_pieces", True),
            arc_refit=False,
        )
    )
    changed = 0
    for ref, batch in _same_on_every_batch(det, real_batches):
        plain = _both(base, batch)[1]
        changed += len(ref) != len(plain) or not np.array_equal(ref.radii, plain.radii)
    assert changed > 0  # the arcs changed detections: the path was exercised


@pytest.mark.slow
@pytest.mark.parametrize("pool", [False, True, "batch"])
def test_compiled_step_split_equals_numpy_on_real_slices(real_batches, pool):
    # Dec 5: the step split (grid 59 with pool "batch": the leave-one-dataset-out choice) on
    # every real slice's virtual scans (the TreeLS plot's stems with a branch behind or a twig
    # in front are what it is for)
    cfg = DetectorConfig.preset(
        "stemmap", step_split=True, step_noise_pool=pool, arc_short_steps=True
    )
    det = ScanTrunkDetector(cfg)
    # without the step split (the preset's since Dec 5)
    base = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", step_split=False, arc_short_steps=True)
    )
    changed = 0
    for ref, batch in _same_on_every_batch(det, real_batches):
        plain = _both(base, batch)[1]
        changed += len(ref) != len(plain) or not np.array_equal(ref.radii, plain.radii)
    assert changed > 0  # the step split changed detections: the path was exercised
