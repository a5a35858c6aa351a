"""Replay a recorded log through :class:`~stemmap.slam.online.OnlineMapper` (ours).

:func:`replay` feeds a :class:`~stemmap.slam.base.SlamProblem`'s odometry and scans to the
online mapper in time order, as a vehicle would deliver them, and collects the per-scan
latency and CPU time, the causal path, its pose covariances and the map (``stemmap map
--realtime``, ``benchmarks/slam_field.py --parts online``). With ``passes`` > 1 the log is
driven again after a transit without trees, a memory test for unbounded drives.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from stemmap.slam.base import SlamProblem, frame_trajectory, single_threaded_blas

if TYPE_CHECKING:
    from stemmap.slam.online import OnlineConfig

__all__ = ["replay"]


def replay(
    problem: SlamProblem,
    *,
    passes: int = 1,
    transit_s: float = 200.0,
    config: OnlineConfig | None = None,
    on_scan: Any = None,
) -> dict[str, Any]:
    """Feed ``problem``'s log to an :class:`~stemmap.slam.online.OnlineMapper` in time order
    (odometry samples up to each scan, then the scan) and return per-scan latency, the path
    and the map.

    ``passes`` > 1 drives the log again and again, each pass after ``transit_s`` of straight
    driving at 3 m/s without detections (the machine moving to the next stand, 600 m), so the
    replay is ``passes`` times longer and the map grows with new area (a memory test).
    ``on_scan(mapper, frame_index)`` is called after every scan (e.g. a live viewer).
    """
    import resource

    with single_threaded_blas():  # once: threadpoolctl costs ~10 ms per call
        return _replay(problem, passes, transit_s, config, on_scan, resource)


def _replay(
    problem: SlamProblem,
    passes: int,
    transit_s: float,
    config: OnlineConfig | None,
    on_scan: Any,
    resource: Any,
) -> dict[str, Any]:
    from stemmap.slam.online import OnlineMapper  # here: online.py re-exports replay

    ctl, fr = problem.controls, problem.frames
    m = OnlineMapper(problem.motion, problem.sensor_offset, problem.initial_pose, config)
    span = float(max(ctl.times[-1], fr.times[-1]) - min(ctl.times[0], fr.times[0]))
    poses, rss = [], []
    t_shift = 0.0
    for p_ in range(passes):
        if p_ > 0:  # transit: straight at 3 m/s, odometry at 10 Hz, empty scans at 5 Hz
            t_a = float(max(ctl.times[-1], fr.times[-1])) + t_shift
            empty = np.zeros(0)
            for q in range(int(transit_s * 10)):
                tq = t_a + 0.1 * (q + 1)
                m.add_odometry(tq, 3.0, 0.0)
                if q % 2 == 1:
                    m.add_scan(tq, empty, empty, empty)
            t_shift += span + transit_s + 1.0
        ci = 0
        for f in range(len(fr)):
            t = float(fr.times[f])
            while ci < len(ctl) and ctl.times[ci] <= t:
                m.add_odometry(
                    float(ctl.times[ci]) + t_shift, float(ctl.speed[ci]), float(ctl.steer[ci])
                )
                ci += 1
            rr, bb, dd = fr.frame(f)
            poses.append((t + t_shift, *m.add_scan(t + t_shift, rr, bb, dd)))
            if on_scan is not None:
                on_scan(m, f)
        rss.append(round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1))
    arr = np.asarray(poses)
    return {
        "latency_s": m.latency_s,
        "cpu_s": m.cpu_s,
        "trajectory": frame_trajectory(arr[:, 0], arr[:, 1:]),
        "pose_covs": m.pose_covs,
        "stem_map": m.stem_map(),
        "trees": len(m.stem_map()),
        "rss_mb_by_pass": rss,
        "stats": m.stats,
    }
