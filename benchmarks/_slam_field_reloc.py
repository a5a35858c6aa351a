"""The ``reloc`` part of benchmarks/slam_field.py (maps reused across sessions, Victoria Park).

Split out of slam_field.py (past the ~800-line limit); see that module's docs for what each
key means. Run through ``python benchmarks/slam_field.py --parts reloc ...``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np


def _reloc_diagnosis(vp: Any, r1: Any, cal: Any, first: Any, r2: Any, full: Any) -> dict[str, Any]:
    """Why session 2 on the prior map differs from the single run (docs/algorithms/slam.md
    "Maps reused across sessions"): the keyframe-phase spread of both (session 2 started at
    800.0-801.1 s, the full run at 0-2.6 s; fixes after 801 s, own alignment), session 2 started
    from the full run's own pose (relocalisation error carried?), the prior's information
    scaled by 0.25 / 4 (too tight or loose?), the joint prior's chi2 at session 2's optimum
    (prior trees within 0.5 m of a merged-map tree vs all), and the phases again with every
    prior tree held by its own Huber prior (``prior_map_robust="huber"``)."""
    from scipy.spatial import cKDTree

    from stemmap.eval.trajectory import ate
    from stemmap.slam.graph import Isam2Slam
    from stemmap.slam.motion import compose, preintegrate
    from stemmap.slam.relocalise import relocalise, with_calibration

    keep, off = vp.screened_gps(), vp.model.sensor_offset

    def score(res: Any, t0: float) -> float:
        m = keep & (vp.gps_times >= t0)
        return round(ate(res.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=m).rmse, 3)

    out: dict[str, Any] = {}
    s2_ph, full_ph, hub_ph = [], [], []
    for t0 in (800.0, 800.4, 800.6, 800.7, 800.9, 801.1):
        p2 = vp.slice(t0, 1549.0).problem()
        t1l, t2f = float(r1.trajectory.times[-1]), float(p2.frames.times[0])
        d = preintegrate(vp.model, vp.controls, [t1l, t2f], with_covariance=False).deltas[0]
        rel = relocalise(p2, r1.stem_map, guess=tuple(compose(r1.trajectory.poses[-1], d)))
        p2r = dataclasses.replace(p2, initial_pose=rel.pose, prior_map=r1.stem_map)
        s2_ph.append(
            [
                round(t2f, 3),
                score(Isam2Slam(prior_map_robust="none").run(with_calibration(p2r, *cal)), 801.0),
            ]
        )
        # each prior tree held by its own Huber prior instead of the joint one
        r2h = Isam2Slam(prior_map_robust="huber").run(with_calibration(p2r, *cal))
        hub_ph.append([round(t2f, 3), score(r2h, 801.0)])
        if t0 == 800.0:
            out["session2_prior_map_huber_ate_after_800s_m"] = score(r2h, t2f)
    for t0 in (0.0, 1.0, 1.2, 1.6, 2.0, 2.3, 2.6):
        pf = vp.slice(t0, 1549.0).problem()
        full_ph.append([round(float(pf.frames.times[0]), 3), score(Isam2Slam().run(pf), 801.0)])
    out["phase_session2_first_scan_ate"] = s2_ph
    out["phase_full_first_scan_ate"] = full_ph
    out["phase_session2_mean_m"] = round(float(np.mean([a for _, a in s2_ph])), 3)
    out["phase_full_mean_m"] = round(float(np.mean([a for _, a in full_ph])), 3)
    out["phase_session2_huber_first_scan_ate"] = hub_ph
    out["phase_session2_huber_mean_m"] = round(float(np.mean([a for _, a in hub_ph])), 3)
    p2 = vp.slice(800.0, 1549.0).problem()
    t2f = float(p2.frames.times[0])
    base = dataclasses.replace(p2, initial_pose=first.pose, prior_map=r1.stem_map)
    start = tuple(full.trajectory.interpolate([t2f])[0])
    res = Isam2Slam(prior_map_robust="none").run(
        with_calibration(dataclasses.replace(base, initial_pose=start), *cal)
    )
    out["start_from_full_run_pose_ate_m"] = score(res, t2f)
    info = r1.stem_map.information
    for f in (0.25, 4.0):
        pm = dataclasses.replace(r1.stem_map, information=info * f)
        res = Isam2Slam(prior_map_robust="none").run(
            with_calibration(dataclasses.replace(base, prior_map=pm), *cal)
        )
        out[f"prior_information_x{f:g}_ate_m"] = score(res, t2f)
    m1, xy2 = r1.stem_map, r2.stem_map.xy
    dist, j = cKDTree(xy2).query(m1.xy)
    dv = (xy2[j] - m1.xy).reshape(-1)
    ok = np.flatnonzero(dist < 0.5)
    sel = np.column_stack((2 * ok, 2 * ok + 1)).reshape(-1)
    cov = np.linalg.inv(info)[np.ix_(sel, sel)]
    out["prior_chi2_all"] = [round(float(dv @ info @ dv), 1), int(dv.size)]
    out["prior_chi2_matched"] = [
        round(float(dv[sel] @ np.linalg.solve(cov, dv[sel])), 1),
        int(sel.size),
    ]
    far = np.flatnonzero(dist >= 0.5)  # prior trees that session 2 moved or merged
    d_full = cKDTree(full.stem_map.xy).query(m1.xy)[0]
    out["prior_trees_moved_0p5m"] = {
        "count": int(far.size),
        "max_m": round(float(dist.max()), 2),
        "full_run_keeps_within_0p1m": int((d_full[far] < 0.1).sum()),
        "full_run_moves_too_0p5m": int((d_full[far] >= 0.5).sum()),
    }
    return out


def _reloc_per_trial(
    vp: Any, p2: Any, r1: Any, cal: Any, rels: list[Any], t2f: float
) -> dict[str, Any]:
    """Session 2 mapped from every accepted trial's relocalised pose, once per way of holding
    the prior trees (``prior_map_robust``: "none" = the joint prior, "huber" = per-tree Huber
    priors), scored on the screened fixes after 800 s with its own alignment; process CPU per
    run. The prior map's robust loss does not enter :func:`relocalise`, so the success rate and
    the relocalisation time are the same for both by construction."""
    from stemmap.eval.trajectory import ate
    from stemmap.slam.graph import Isam2Slam
    from stemmap.slam.relocalise import with_calibration

    keep = vp.screened_gps() & (vp.gps_times >= t2f)
    out: dict[str, Any] = {}
    for kind in ("none", "huber"):
        ates, cpus = [], []
        for rel in rels:
            p2r = dataclasses.replace(p2, initial_pose=rel.pose, prior_map=r1.stem_map)
            c0 = time.process_time()
            res = Isam2Slam(prior_map_robust=kind).run(with_calibration(p2r, *cal))
            cpus.append(time.process_time() - c0)
            a = ate(
                res.trajectory, vp.gps_times, vp.gps_xy, offset=vp.model.sensor_offset, keep=keep
            )
            ates.append(round(a.rmse, 3))
        out[kind] = {
            "ate_after_800s_m": ates,
            "mean_m": round(float(np.mean(ates)), 3),
            "max_m": round(float(np.max(ates)), 3),
            "cpu_s_mean": round(float(np.mean(cpus)), 2),
        }
    return out


#: session 2 on the prior map in ``--reloc-splits``: the default (per-tree Huber priors on the
#: inflated marginals, ``Isam2Config.prior_map_inflation``), the same without inflation, the
#: joint prior (inflated), and the prior held weakly (x100: session 2's own estimates of the
#: prior trees, for ``prior_consistency``); ``graph``: session 1's whole graph continued
#: (``SlamProblem.prior_graph``, stemmap.slam._graph_continue) instead of a marginal prior,
#: its factors' covariances x ``prior_graph_inflation`` (default 4; ``graph_f1``: x1)
SPLIT_PRIORS: list[tuple[str, dict[str, Any]]] = [
    ("huber", {"prior_map_robust": "huber"}),
    ("graph", {}),
    ("graph_f1", {"prior_graph_inflation": 1.0}),
    ("huber_f1", {"prior_map_inflation": 1.0}),
    ("joint", {"prior_map_robust": "none"}),
    ("weak", {"prior_map_inflation": 100.0}),
]


def _step_latency(c0: float, steps: list[float], res: Any) -> dict[str, Any]:
    """Process CPU of each keyframe step of an :class:`Isam2Slam` run (the progress callback
    fires once per keyframe: its ``keyframe_every`` = 5 scans tracked, plus the iSAM2 update
    every ``update_every`` keyframes; the first step includes the setup, e.g. inserting a
    continued graph), p50 / p99 / max in ms, and the end-of-run batch step (merging, LM,
    marginals) in s of wall time (the back-end's own ``runtime_s - incremental_s``)."""
    t = np.diff(np.concatenate(([c0], steps))) * 1e3
    return {
        "keyframe_cpu_ms_p50": round(float(np.percentile(t, 50)), 2),
        "keyframe_cpu_ms_p99": round(float(np.percentile(t, 99)), 2),
        "keyframe_cpu_ms_max": round(float(t.max()), 1),
        "first_keyframe_cpu_ms": round(float(t[0]), 1),
        "keyframes": int(t.size),
        "end_batch_wall_s": round(float(res.stats["runtime_s"] - res.stats["incremental_s"]), 2),
    }


def _reloc_splits(vp: Any, splits: list[float], full: Any, trials: int) -> dict[str, Any]:
    """Other session pairs: map 0-``s`` s, relocalise the ``s``-1549 s session from session
    1's end pose (odometry over the gap) off by (+15 m, -10 m, +20 deg) and by ``trials - 1``
    more offsets U(+-20 m, +-20 m, +-30 deg) (seed 1; success = accepted within 30 s, within
    1 m and 2 deg; false = accepted farther off), and from ``trials`` guesses 45-90 m away
    (the true start outside the 30-m search: any acceptance is false, ``outside_accepted``);
    map it on the prior map from the (+15, -10, +20) relocalisation, the prior held each way of
    ``SPLIT_PRIORS`` (keys ``huber_m`` = the default, ``huber_f1_m``, ``joint_m``, ``weak_m``),
    session 1's calibration carried over; ATE on the screened fixes after the session's first
    scan (own alignment), next to the full single run on the same fixes; process CPU of each
    session-2 run; ``prior_consistency`` (:func:`stemmap.slam.relocalise.prior_consistency` of
    the weak run) and ``cover_dist_m`` (the relocalisation's default, the map's spacing)."""
    from stemmap.eval.trajectory import ate
    from stemmap.slam.graph import Isam2Slam
    from stemmap.slam.motion import compose, preintegrate
    from stemmap.slam.relocalise import (
        RelocConfig,
        map_spacing,
        prior_consistency,
        relocalise,
        with_calibration,
    )

    keep, off = vp.screened_gps(), vp.model.sensor_offset
    rng = np.random.default_rng(1)
    out: dict[str, Any] = {}
    for split in splits:
        r1 = Isam2Slam(joint_information=True, export_graph=True).run(
            vp.slice(0.0, split).problem()
        )
        p2 = vp.slice(split, 1549.0).problem()
        t1l, t2f = float(r1.trajectory.times[-1]), float(p2.frames.times[0])
        d = preintegrate(vp.model, vp.controls, [t1l, t2f], with_covariance=False).deltas[0]
        want = compose(r1.trajectory.poses[-1], d)
        offs = [(15.0, -10.0, 20.0)] + [
            (*rng.uniform(-20.0, 20.0, 2), rng.uniform(-30.0, 30.0)) for _ in range(trials - 1)
        ]
        good, false, times, rel = 0, 0, [], None
        for dx, dy, dth in offs:
            guess = (want[0] + dx, want[1] + dy, want[2] + math.radians(dth))
            r = relocalise(p2, r1.stem_map, guess=guess)
            rel = rel or r
            e = math.hypot(r.pose[0] - want[0], r.pose[1] - want[1])
            eth = abs(math.degrees(math.remainder(r.pose[2] - want[2], 2 * math.pi)))
            good += int(r.ok and r.time_s <= 30.0 and e < 1.0 and eth < 2.0)
            false += int(r.ok and not (e < 1.0 and eth < 2.0))
            if r.ok:
                times.append(r.time_s)
        outside = 0
        for _ in range(trials):
            a, dist = rng.uniform(0.0, 2 * math.pi), rng.uniform(45.0, 90.0)
            guess = (
                want[0] + dist * math.cos(a),
                want[1] + dist * math.sin(a),
                want[2] + math.radians(rng.uniform(-30.0, 30.0)),
            )
            outside += int(relocalise(p2, r1.stem_map, guess=guess).ok)
        assert rel is not None
        m2 = keep & (vp.gps_times >= t2f)
        row: dict[str, Any] = {
            "reloc_ok": bool(rel.ok),
            "reloc_time_s": round(rel.time_s, 2),
            "reloc_error_m": round(math.hypot(rel.pose[0] - want[0], rel.pose[1] - want[1]), 3),
            "reloc_heading_error_deg": round(
                math.degrees(math.remainder(rel.pose[2] - want[2], 2 * math.pi)), 2
            ),
            "reloc_success_rate": round(good / len(offs), 3),
            "reloc_false": false,
            "reloc_time_s_max": round(max(times), 2) if times else None,
            "outside_accepted": outside,
            "trials": len(offs),
            "full_m": round(
                ate(full.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=m2).rmse, 3
            ),
        }
        row["cover_dist_m"] = round(map_spacing(r1.stem_map.xy, RelocConfig().inlier_dist), 2)
        if rel.ok:
            cal = (float(r1.stats["calib_offset_mean"]), float(r1.stats["calib_scale_mean"]))
            p2r = with_calibration(
                dataclasses.replace(p2, initial_pose=rel.pose, prior_map=r1.stem_map), *cal
            )
            for name, kw in SPLIT_PRIORS:
                pr = (
                    dataclasses.replace(p2r, prior_graph=r1.graph)
                    if name.startswith("graph")
                    else p2r
                )
                steps: list[float] = []
                c0 = time.process_time()
                res = Isam2Slam(**kw).run(
                    pr, progress=lambda *_, st=steps: st.append(time.process_time())
                )
                cpu = time.process_time() - c0
                if name in ("huber", "graph"):
                    row[f"{name}_step"] = _step_latency(c0, steps, res)
                a = ate(res.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=m2)
                row[f"{name}_m"] = round(a.rmse, 3)
                row[f"{name}_cpu_s"] = round(cpu, 2)
                if name == "weak":  # the prior's consistency with session 2's own estimates
                    pc = prior_consistency(r1.stem_map, res.stem_map)
                    row["prior_consistency"] = {
                        "trees": pc.n_trees,
                        "ratio_median": round(pc.ratio_median, 2),
                        "ratio_mean": round(pc.ratio_mean, 2),
                        "inflation_fit": round(pc.inflation, 2),
                    }
        out[f"{split:g}"] = row
    return out


def _reloc(
    data: str | None,
    trials: int,
    diagnose: bool = False,
    per_trial: bool = False,
    splits: list[float] | None = None,
    *,
    splits_only: bool = False,
) -> dict[str, Any]:
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import ate
    from stemmap.slam.base import duplicate_pairs
    from stemmap.slam.graph import Isam2Slam
    from stemmap.slam.motion import compose, preintegrate
    from stemmap.slam.relocalise import relocalise, with_calibration

    vp = load_victoria_park(data)
    if splits_only:
        return {
            "reloc_other_splits": _reloc_splits(
                vp, splits or [], Isam2Slam().run(vp.problem()), trials
            )
        }
    keep = vp.screened_gps()
    off = vp.model.sensor_offset
    s1, s2 = vp.slice(0.0, 800.0), vp.slice(800.0, 1549.0)
    r1 = Isam2Slam(joint_information=True).run(s1.problem())
    p2 = s2.problem()
    t1l, t2f = float(r1.trajectory.times[-1]), float(p2.frames.times[0])
    d = preintegrate(vp.model, vp.controls, [t1l, t2f], with_covariance=False).deltas[0]
    truth = compose(r1.trajectory.poses[-1], d)
    rng = np.random.default_rng(0)
    good, times, errs, cpus, false = [], [], [], [], 0
    first = None
    accepted = []
    for _ in range(trials):
        dx, dy = rng.uniform(-20.0, 20.0, 2)
        dth = math.radians(rng.uniform(-30.0, 30.0))
        guess = (truth[0] + dx, truth[1] + dy, truth[2] + dth)
        c0 = time.process_time()
        rel = relocalise(p2, r1.stem_map, guess=guess)
        cpus.append(time.process_time() - c0)
        e = math.hypot(rel.pose[0] - truth[0], rel.pose[1] - truth[1])
        eth = abs(math.degrees(math.remainder(rel.pose[2] - truth[2], 2 * math.pi)))
        ok = rel.ok and rel.time_s <= 30.0 and e < 1.0 and eth < 2.0
        good.append(ok)
        false += int(rel.ok and not (e < 1.0 and eth < 2.0))
        if rel.ok:
            times.append(rel.time_s)
            errs.append(e)
        if ok and first is None:
            first = rel
        if ok:
            accepted.append(rel)
    out: dict[str, Any] = {
        "reloc_success_rate": round(float(np.mean(good)), 3),
        "reloc_trials": trials,
        "reloc_false": false,
        "reloc_time_s_mean": round(float(np.mean(times)), 2) if times else None,
        "reloc_time_s_max": round(float(np.max(times)), 2) if times else None,
        "reloc_pose_error_m_max": round(float(np.max(errs)), 3) if errs else None,
        "reloc_cpu_s_mean": round(float(np.mean(cpus)), 3),
        "reloc_data": "Victoria Park: prior map = isam2 on 0-800 s; session 2 = 800-1549 s; "
        "start guess = session 1's end pose (carried over the gap by odometry) + U(+-20 m, "
        "+-20 m, +-30 deg), seed 0",
    }
    if first is not None:
        # session 2 on the prior map (default: each prior tree held by its own Huber prior),
        # the odometry calibration of session 1 carried over (same vehicle); and the same with
        # all its trees held by their joint information
        cal = (float(r1.stats["calib_offset_mean"]), float(r1.stats["calib_scale_mean"]))
        p2r = dataclasses.replace(p2, initial_pose=first.pose, prior_map=r1.stem_map)
        r2 = Isam2Slam().run(with_calibration(p2r, *cal))
        r2j = Isam2Slam(prior_map_robust="none").run(with_calibration(p2r, *cal))
        # as before: independent per-tree priors (the map without its joint information), no
        # calibration carried over
        diag_map = dataclasses.replace(r1.stem_map, information=None)
        r2d = Isam2Slam(prior_map_robust="none").run(dataclasses.replace(p2r, prior_map=diag_map))
        m2 = keep & (vp.gps_times >= t2f)
        alone = Isam2Slam().run(p2)
        full = Isam2Slam().run(vp.problem())
        for name, res in (
            ("session2_prior_map", r2),
            ("session2_prior_map_joint", r2j),
            ("session2_prior_map_per_tree", r2d),
            ("session2_alone", alone),
            ("full", full),
        ):
            a = ate(res.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=m2)
            out[f"{name}_ate_after_800s_m"] = round(a.rmse, 3)
        out["merged_map_trees"] = len(r2.stem_map)
        out["merged_map_pairs_below_1m"] = duplicate_pairs(r2.stem_map, 1.0)
        out["session1_trees"] = len(r1.stem_map)
        out["session1_calibration"] = {"steer_offset_rad": cal[0], "speed_scale": cal[1]}
        if diagnose:
            out["reloc_diagnosis"] = _reloc_diagnosis(vp, r1, cal, first, r2, full)
        if per_trial:
            out["reloc_per_trial_session2"] = _reloc_per_trial(vp, p2, r1, cal, accepted, t2f)
        if splits:
            out["reloc_other_splits"] = _reloc_splits(vp, splits, full, trials)
    return out
