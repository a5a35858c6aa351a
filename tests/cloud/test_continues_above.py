"""A stem goes on above the slice band (``StemConfig.continues_above``,
:func:`stemmap.cloud.slicestem._ends_in_band`; docs/algorithms/cloud.md "Plots at lower
density: the lost stems, stage by stage").

The per-slice path asked for nothing above its agreeing slices, so an object 1.6 m tall with
three clean slices at 1.1-1.5 m was a stem. On treels pine_plot that is the source of the
extra stem under 1 cm noise and a 10 degree tilt (a blob at (6.2, 3.0) m with no return
within its radius + 5 cm at 1.6-2.0 m) and of the 6.3 cm "stem" at (1.09, 9.68) m (nothing
within 50 cm at 1.71-2.88 m: "pine_plot's 17th stem").
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from stemmap.cloud.result import CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems, detect_stems_file

#: the two objects of treels pine_plot that end inside the band (m, the cloud's frame)
OBJECTS = [(6.25, 2.95), (1.09, 9.68)]


def _scene(top: float, seed: int = 0, gap: tuple[float, float] | None = None) -> np.ndarray:
    """Flat ground, a reference trunk (r 15 cm, half seen, to 4 m) and a dense object
    (r 12 cm, 150 deg seen, 400 returns per metre: 80 per 20 cm slice) from the ground up to
    ``top``; ``gap`` (lo, hi): the object's returns between these heights removed (an
    occluded stretch)."""
    g = np.random.default_rng(seed)
    pts = [np.column_stack((g.uniform(0, 10, (20000, 2)), g.normal(0, 0.002, 20000)))]

    def trunk(c: tuple[float, float], r: float, n: int, half: float, h: float) -> np.ndarray:
        t = g.uniform(-half, half, n)
        rr = r + g.normal(0, 0.002, n)
        return np.column_stack((c[0] - rr * np.cos(t), c[1] - rr * np.sin(t), g.uniform(0, h, n)))

    pts.append(trunk((2.0, 2.0), 0.15, 4000, np.pi / 2, 4.0))
    obj = trunk((7.0, 7.0), 0.12, int(400 * top), np.radians(75), top)
    if gap is not None:
        obj = obj[(obj[:, 2] < gap[0]) | (obj[:, 2] > gap[1])]
    pts.append(obj)
    return np.vstack(pts)


def _has_object(det: CloudStems) -> bool:
    xy = det.xy
    return bool(len(xy)) and bool(np.hypot(*(xy - [7.0, 7.0]).T).min() < 0.05)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_object_ending_inside_the_band_is_no_stem(seed: int) -> None:
    """Ending at 1.6 m (slices at 0.9-1.5 m agree, nothing above): a stem before, not now;
    the reference trunk is found either way."""
    short = _scene(1.6, seed)
    on, off = detect_stems(short), detect_stems(short, StemConfig(continues_above=False))
    assert _has_object(off) and not _has_object(on)
    assert len(on) == 1 and np.hypot(*(on.xy[0] - [2.0, 2.0])) < 0.02


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_trunk_hidden_at_the_top_of_the_band_is_kept(seed: int) -> None:
    """The same object going on to 4 m is a stem; so it is when its returns at 1.6-1.95 m are
    missing (occluded) but a few come back above: one return above the agreeing slices is
    enough, only an absence counts."""
    for cloud in (_scene(4.0, seed), _scene(4.0, seed, gap=(1.6, 1.95))):
        det = detect_stems(cloud)
        assert _has_object(det)
        k = int(np.argmin(np.hypot(*(det.xy - [7.0, 7.0]).T)))
        assert abs(det.diameter[k] - 0.24) < 0.01


@pytest.mark.slow
def test_pine_plot_noise_and_tilt_have_no_extra_stem(datasets_dir: Path) -> None:
    """treels pine_plot as shipped: 16 stems, each pairing with a fixed ring reference (the
    6.3 cm object is gone; 17 with the test off). With 1 cm noise and tilted 10 degrees
    (benchmarks/cloud_robustness.py, seed 0): no stem away from the 16 references (with the
    test off the blob at (6.2, 3.0) m and the 6.3 cm object when tilted, one of them with
    noise since the locally optimised RANSAC, both before)."""
    import cloud_robustness as cr
    from _cloud_refs import CLOUDS, reference_of_each

    bl = cr.run_baseline("treels_pine_plot", datasets_dir / CLOUDS["treels_pine_plot"])
    assert len(bl.det) == 16 and len(bl.checked) == 16
    off = detect_stems_file(
        datasets_dir / CLOUDS["treels_pine_plot"], StemConfig(continues_above=False)
    )
    assert len(off) == 17
    with tempfile.TemporaryDirectory() as td:
        for name, prep, f in cr.transformed_files(bl, ["noise_1cm", "tilt_10"], Path(td)):
            for cfg, where in ((StemConfig(), []), (StemConfig(continues_above=False), OBJECTS)):
                det = detect_stems_file(f, cfg)
                back = prep.back(np.column_stack((det.xy, det.z)))[:, :2]
                unpaired = [j for j, h in enumerate(reference_of_each(bl.refs, back)) if h is None]
                if not where:
                    assert unpaired == [], name
                    continue
                # with the test off, extra stems and only at the known objects: both when
                # tilted; with 1 cm noise one of them since the locally optimised RANSAC
                # (docs/algorithms/cloud.md "RANSAC draws"; both with the plain count)
                assert 1 <= len(unpaired) <= len(where), (name, cfg.continues_above)
                for q in back[unpaired]:
                    assert min(np.hypot(*(q - p)) for p in where) < 0.3, (name, q)
