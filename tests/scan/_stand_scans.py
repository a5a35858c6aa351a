"""Simulated SICK-class scans of one 40-tree stand from random poses, and the DBH errors of
the detections on the trunks each scan sees: the scene of the realistic-stand tests
(test_detect_realistic.py) and of the outline-floor tests (test_outline_floor.py)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stemmap.sim import random_stand, scanner_preset, simulate_scans


def stand(seed: int) -> Any:
    """The 40-tree stand on 24 x 24 m (DBH 35 +- 15 cm within 10-100 cm, 2 m apart)."""
    return random_stand(
        40,
        (24.0, 24.0),
        dbh_mean=0.35,
        dbh_std=0.15,
        dbh_min=0.1,
        dbh_max=1.0,
        min_spacing=2.0,
        rng=seed,
    )


def scans(st: Any, seed: int, n: int, **model: Any) -> tuple[np.ndarray, Any, Any]:
    """``n`` random poses inside the stand (rng ``seed + 3``) and the ``sick_lms`` scans of
    ``st`` from them (30 m, ``model`` overrides): poses (n, 3), batch, hit ids."""
    gen = np.random.default_rng(seed + 3)
    poses = np.column_stack(
        (gen.uniform(2, 22, n), gen.uniform(2, 22, n), gen.uniform(-math.pi, math.pi, n))
    )
    batch, hit, _ = simulate_scans(
        st, poses, scanner_preset("sick_lms", range_max=30.0, **model), rng=4
    )
    return poses, batch, hit


def visible_dbh_errors(
    st: Any, poses: np.ndarray, hit: Any, obs: Any, min_returns: int, max_range: float
) -> tuple[int, np.ndarray]:
    """The trunks scan by scan with >= ``min_returns`` own returns within ``max_range`` m of
    the sensor, and the DBH errors (cm) of those a detection of ``obs`` matches (nearest
    centre within the trunk's radius + 5 cm): (count, errors)."""
    errs, total = [], 0
    for s in range(len(poses)):
        x, y, th = poses[s]
        c, si = math.cos(th), math.sin(th)
        rel = st.trees_xy - (x, y)
        local = np.column_stack((c * rel[:, 0] + si * rel[:, 1], -si * rel[:, 0] + c * rel[:, 1]))
        cnt = np.bincount(hit[s][hit[s] >= 0], minlength=st.n_trees)
        k = obs.index == s
        for t in np.flatnonzero((cnt >= min_returns) & (np.hypot(*local.T) <= max_range)):
            total += 1
            d = np.hypot(*(obs.centers[k] - local[t]).T)
            if d.size and d.min() < st.radii[t] + 0.05:
                errs.append(100.0 * (2.0 * obs.radii[k][int(np.argmin(d))] - st.diameters[t]))
    return total, np.asarray(errs)
