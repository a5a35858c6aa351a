"""What ``stemmap map`` reports of a run: metrics.json (:func:`slam_metrics`), the terminal
summary rows, the one-line headline and the frame facts."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stemmap.cli._summary import fmt

__all__ = ["RPE_DELTA_M", "frames_metadata", "headline", "slam_metrics", "summary_rows"]


RPE_DELTA_M = 10.0
"""Path length (m) of the relative pose error's stretches on simulated runs (evo's --delta)."""


def slam_metrics(
    problem: Any, result: Any, ctx: dict[str, Any], dr: Any = None
) -> tuple[dict[str, Any], Any, Any]:
    """Metrics for the run and (gps_xy_in_map, truth_xy) for the figure.

    ``dr`` is the run's dead reckoning (:func:`~stemmap.slam.base.dead_reckoning`), computed
    here when not given.
    """
    from stemmap.eval.trajectory import ate, loop_closure_error, rpe, screen_gps
    from stemmap.slam.base import dead_reckoning, duplicate_pairs, sensor_poses
    from stemmap.slam.motion import preintegrate

    m: dict[str, Any] = {
        "problem": problem.name,
        "backend_stats": result.stats,
        "n_trees": len(result.stem_map),
        "duplicates_1m": duplicate_pairs(result.stem_map, 1.0),
        "n_frames": len(problem.frames),  # "frames" holds the frame facts (frames_metadata)
        "detections": problem.frames.n_detections,
    }
    if "front_end" in ctx:  # a frames bundle's trunk detector (and EB-LiDAR's frame window)
        m["front_end"] = ctx["front_end"]
    if dr is None:
        dr = dead_reckoning(problem)
    gps_map = None
    truth_xy = None
    if ctx["kind"] == "victoria-park":
        vp = ctx["vp"]
        # poses and distances only: the covariance of every control segment would be the
        # command's largest allocation on a long drive (9 doubles x 4 arrays per segment)
        pre = preintegrate(vp.model, vp.controls, vp.gps_times, with_covariance=False)
        sp = sensor_poses(pre.poses, vp.model.sensor_offset)
        scr = screen_gps(
            vp.gps_times, vp.gps_xy, sp[:, :2], np.concatenate(([0.0], np.cumsum(pre.distance)))
        )
        off = vp.model.sensor_offset
        r = ate(result.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep)
        rd = ate(dr, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep)
        if problem.gnss is not None:  # map in the GPS frame: also scored as it is
            m.update(ate(result.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep,
                         align=False).as_dict("ate_unaligned_"))  # fmt: skip
        m["gps_fixes_kept"] = scr.n_kept
        m["gps_fixes_total"] = scr.n_total
        m["gps_screening"] = scr.rule
        if r:
            m.update(r.as_dict("ate_"))
            al = r.alignment
            assert al is not None
            ctx["alignment"] = al
            # GPS into the map frame (inverse of the map->GPS alignment) for the figure
            g = vp.gps_xy[scr.keep] - np.asarray(al.t)
            gps_map = g @ al.rotation
        else:
            m["ate_error"] = r.reason
        if rd:
            m.update(rd.as_dict("dead_reckoning_ate_"))
    elif ctx["kind"] == "sim":
        from stemmap.eval.maps import map_metrics

        run = ctx["run"]
        truth = run.vehicle_poses
        err = np.hypot(*(result.trajectory.interpolate(truth.times)[:, :2] - truth.xy).T)
        m["trajectory_rmse_m"] = float(np.sqrt(np.mean(err**2)))
        m["trajectory_max_m"] = float(err.max())
        r_rel = rpe(result.trajectory, truth, delta=RPE_DELTA_M)  # full poses: evo's RPE
        m.update(r_rel.as_dict("rpe_") if r_rel else {"rpe_error": r_rel.reason})
        true_disp = truth.xy[-1] - truth.xy[0]
        th0 = float(truth.poses[0, 2])
        c, s = math.cos(th0), math.sin(th0)
        body = (c * true_disp[0] + s * true_disp[1], -s * true_disp[0] + c * true_disp[1])
        m["loop_closure_error_m"] = loop_closure_error(result.trajectory, body)
        m["dead_reckoning_loop_closure_error_m"] = loop_closure_error(dr, body)
        truth_xy = run.stand.trees_xy
        mm = map_metrics(result.stem_map, None, truth_xy, run.stand.diameters, gate=1.0)
        m["map"] = mm.to_dict()
        m["scenario"] = ctx["params"]
    return m, gps_map, truth_xy


def summary_rows(m: dict[str, Any], stem_map: Any) -> list[tuple[str, str, str]]:
    """The terminal summary of a map run: (quantity, value, metrics.json key)."""
    rows = [
        ("trees mapped", fmt(m.get("n_trees")), "n_trees"),
        ("tree pairs closer than 1 m", fmt(m.get("duplicates_1m")), "duplicates_1m"),
    ]
    if "ate_rmse_m" in m:
        rows.append(("path error vs GPS (ATE RMSE)", fmt(m["ate_rmse_m"], " m"), "ate_rmse_m"))
        dr = m.get("dead_reckoning_ate_rmse_m")
        rows.append(("dead reckoning ATE RMSE", fmt(dr, " m"), "dead_reckoning_ate_rmse_m"))
    if "trajectory_rmse_m" in m:
        rows.append(("path RMSE vs truth", fmt(m["trajectory_rmse_m"], " m"), "trajectory_rmse_m"))
        lc = m.get("loop_closure_error_m")
        rows.append(("loop-closure error", fmt(lc, " m"), "loop_closure_error_m"))
    if "rpe_trans_rmse_m" in m:
        per = f"per {m['rpe_delta']:g} {m['rpe_delta_unit']}"
        rows.append((f"RPE translation RMSE ({per})", fmt(m["rpe_trans_rmse_m"], " m"),
                     "rpe_trans_rmse_m"))  # fmt: skip
        rows.append((f"RPE rotation RMSE ({per})", fmt(m["rpe_rot_rmse_deg"], " deg"),
                     "rpe_rot_rmse_deg"))  # fmt: skip
    ft = m.get("false_trees")
    if isinstance(ft, dict) and "method" in ft:  # forestrix: Öhman's ray-cast removal
        if ft.get("ran"):
            rows.append(("false trees removed (ray casting)", fmt(ft.get("removed")),
                         "false_trees.removed"))  # fmt: skip
        else:
            rows.append(("false-tree removal", f"skipped: {ft.get('reason')}", "false_trees"))
    rl = m.get("relocalisation")
    if isinstance(rl, dict) and "prior" in rl:
        rows.append(("prior map trees held by", f"{rl['prior']} prior", "relocalisation.prior"))
    sg = m.get("session_graph")
    if isinstance(sg, dict):
        said = "written" if sg.get("written") else str(sg.get("summary", "not written"))
        rows.append(("session graph (graph.npz)", said, "session_graph"))
    mm = m.get("map")
    if isinstance(mm, dict):
        rows.append(("map recall (matched / all true trees)", fmt(mm.get("recall")), "map.recall"))
        rows.append(("map precision", fmt(mm.get("precision")), "map.precision"))
        pr = mm.get("position_rmse")
        rows.append(("tree position RMSE", fmt(pr, " cm", 100, 1), "map.position_rmse"))
        dr_ = mm.get("diameter_rmse")
        rows.append(("DBH RMSE", fmt(dr_, " cm", 100, 2), "map.diameter_rmse"))
    if len(stem_map):
        import numpy as np

        ds = np.array([t.diameter_std for t in stem_map])
        conf = np.array([t.confidence for t in stem_map])
        med = float(np.nanmedian(ds)) if np.isfinite(ds).any() else math.nan
        rows.append(("median DBH standard error", fmt(med, " cm", 100, 2), "trees.csv"))
        rows.append(("trees with confidence >= 0.5", fmt(int(np.sum(conf >= 0.5))), "trees.csv"))
    return rows


def headline(m: dict[str, Any]) -> str:
    """One line of the run's key numbers (figure titles, the terminal summary)."""
    parts = [f"{m.get('n_trees', 0)} trees"]
    mm = m.get("map")
    if isinstance(mm, dict):
        parts.append(f"recall {mm.get('recall', math.nan):.2f}")
        parts.append(f"precision {mm.get('precision', math.nan):.2f}")
    if "ate_rmse_m" in m:
        parts.append(f"ATE RMSE {m['ate_rmse_m']:.2f} m vs GPS")
    if "trajectory_rmse_m" in m:
        parts.append(f"path RMSE {m['trajectory_rmse_m']:.2f} m")
    return ", ".join(parts)


def frames_metadata(problem: Any, crs: str | None, *, gnss_frame: bool = False) -> dict[str, Any]:
    """What the map and trajectory coordinates mean (recorded in metrics.json); ``gnss_frame``:
    the map is in the GNSS fixes' frame (``--gnss``, or a prior map in it), read back by
    ``--prior-map`` (:func:`stemmap.cli._map_prior.prior_map_frame`)."""
    a, b = problem.sensor_offset
    return {
        "map_frame": "the GNSS fixes' frame (x, y metres)"
        if gnss_frame
        else "the frame of the initial pose (x, y metres; odometry frame, the simulator's "
        "world frame for --sim and demo; with --prior-map the prior map's frame)",
        "gnss_frame": gnss_frame,
        "crs": crs,
        "georeferenced": crs is not None,
        "trajectory_point": "the vehicle reference point of the motion model (Victoria Park: "
        "the rear-axle centre), sensor_offset_m behind the laser",
        "sensor_offset_m": [a, b],
        "sensor_offset_meaning": f"the laser is {a} m ahead and {b} m left of the trajectory "
        "point, in the vehicle frame",
    }
