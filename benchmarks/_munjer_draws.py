"""Shared by the Munjer et al. (2025) benchmarks (``munjer2025.py``,
``munjer2025_motion_noise.py``): FastSLAM's detection range, the per-seed FastSLAM draw loop
and the mean / spread of a metric over the draws. A helper module, not a script; each
benchmark imports it explicitly (the script's own folder is on ``sys.path`` when it runs, from
any working directory)."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from stemmap.sim.munjer import MunjerDrive
from stemmap.slam.base import SlamResult
from stemmap.slam.munjer import MunjerMapConfig, map_munjer, munjer_problem
from stemmap.types import StemObservations

__all__ = ["MAX_RANGE", "map_draws", "spread"]

#: The sensor range the problem declares (m, ``SlamProblem.max_range``): a declaration, not a
#: filter -- FastSLAM maps every detection whatever its range (docs/algorithms/slam.md).
MAX_RANGE = 12.0


def map_draws(
    drive: MunjerDrive,
    obs: StemObservations,
    draws: int,
    motion: tuple[Any, Any] | None = None,
    config: MunjerMapConfig | None = None,
) -> Iterator[tuple[int, SlamResult, float]]:
    """FastSLAM (100 particles) + the Kalman refinement on one drive's detections, once per
    particle-filter seed ``MunjerMapConfig(seed=d)``, ``d`` in ``range(draws)``: yields ``(d,
    result, seconds)``. ``motion`` is ``(controls, model)``, default the drive's simulated
    odometry and :meth:`MunjerDrive.motion_model`. The drive starts at the true pose and the
    problem declares the sensor range :data:`MAX_RANGE` (Munjer et al. 2025, §3.6; no
    detection is dropped by it, ``SlamProblem.max_range``). ``config``: the
    back end's settings (default :class:`MunjerMapConfig`), its seed replaced by ``d``."""
    controls, model = motion or (drive.controls(), drive.motion_model())
    p0 = (float(drive.poses[0, 0]), float(drive.poses[0, 1]), float(drive.poses[0, 2]))
    for d in range(draws):
        t0 = time.perf_counter()
        problem = munjer_problem(
            obs, drive.times, controls, model, initial_pose=p0, max_range=MAX_RANGE
        )
        result = map_munjer(problem, replace(config or MunjerMapConfig(), seed=d))
        yield d, result, time.perf_counter() - t0


def spread(values: Sequence[float], key: str) -> dict[str, float]:
    """``key``: the mean of the finite ``values``; ``key_sd`` (population sd), ``key_min``,
    ``key_max``: their spread (NaN when none is finite)."""
    x = np.asarray([v for v in values if math.isfinite(v)], dtype=float)
    if not x.size:
        return {
            key: math.nan,
            f"{key}_sd": math.nan,
            f"{key}_min": math.nan,
            f"{key}_max": math.nan,
        }
    return {
        key: float(x.mean()),
        f"{key}_sd": float(x.std()),
        f"{key}_min": float(x.min()),
        f"{key}_max": float(x.max()),
    }
