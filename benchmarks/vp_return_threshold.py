"""Benchmark: the return threshold of a real SICK LMS200, measured on the Victoria Park log.

Prints one JSON object. docs/algorithms/scan-detection.md, "The return threshold of a real
SICK LMS200, measured on Victoria Park (Dec 4)", explains the method and gives the numbers; in
short:

* Victoria Park holds no raw ranges, only the detections of its own beam-count detector
  (``measurements.dat``: range, bearing, diameter = beams spanned x 0.5 deg x edge range).
  The beams spanned ``N`` come back from range and diameter (exactly for one and two
  beams, unambiguously up to eight)
  (:func:`stemmap.eval.beam_width.beams_spanned`).
* A scanner that returns when a share ``q`` of its footprint ``w`` hits spans on average
  ``(Phi + e) / delta`` beams of a trunk of silhouette ``Phi``, ``e = (1 - 2 q) w``: a fixed
  angle, i.e. a reported diameter that grows by ``e`` metres per metre of range. Detections
  are linked into passes by dead reckoning, and ``e`` is fitted common to all passes with a
  diameter per pass (:func:`stemmap.eval.beam_width.width_excess`, bootstrap over passes).
* **Validation / calibration** (``sim``): the same detector (own implementation,
  :func:`~stemmap.eval.beam_width.beam_tree_detections`) and the same pipeline on simulated
  drives past a park-like stand, with the simulated SICK's ``min_hit_fraction`` set to each
  threshold; the measured ``e`` is compared with ``(1 - 2 q_eff) w`` (``q_eff`` the
  sub-beam threshold's own step: ``(k - 1/2) / K`` of ``K`` sub-beams, ``k`` needed).
* **Real geometry** (``real``): virtual SICK scans of real breast-height slices
  (:func:`stemmap.eval.real_slices.virtual_scans`, 20 sub-rays, threshold ``q``) through the
  same detector, detections matched to the reference trunks.
* The **Victoria Park** excess is turned into a threshold with the simulated calibration line
  (``q`` for the simulator's and the detector's footprint of 0.25 deg), and, as the planned
  DBH-drift test, the within-pass slope of the diameter on range after correcting for each assumed
  threshold (``D_q = (A - (1 - 2 q) w) r``): zero for the right assumption.

Usage::

    python benchmarks/vp_return_threshold.py [--parts sim real vp] [--seeds 1 2] [--clutter]
        [--q 0.05 0.25 0.5 0.75 1] [--scans N] [--real fortls_slice treels_pine lidr_dbh]
        [--real-q 0 0.25 0.5 0.75 1] [--vantage 600] [--data DIR] [--boot 1000]

The headline is the 2-15 m window (``near_2_15m``); ``calibration`` is the line fitted to the
simulated rows and the Victoria Park threshold read off it (for the 0.25-degree footprint).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any

import numpy as np

DELTA = math.radians(0.5)
FOOTPRINT = math.radians(0.25)  # the simulated SICK's and the detector's beam footprint
SUB_BEAMS = 20
ASSUMED_Q = (0.0, 0.25, 0.5, 0.75, 1.0)
#: The headline's range window (m): beyond it the Victoria Park widths shrink faster than any
#: threshold of a 0.25-degree footprint can explain (see the doc section).
NEAR_M = 15.0
BANDS = ((2.0, 10.0), (10.0, 15.0), (15.0, 20.0), (20.0, 25.0), (25.0, 40.0))
SIZES = ((0.0, 0.3), (0.3, 0.5), (0.5, 2.0))
#: Largest predicted span (beams) used: up to 8 the count comes back from a detection's range
#: and diameter without ambiguity (both edge-range models of ``beams_spanned`` agree).
MAX_BEAMS = 8.0


def _q_eff(q: float, k_sub: int = SUB_BEAMS) -> float:
    """The simulator's effective threshold: a beam returns when >= k = ceil(q K) of its K
    sub-beams (cell centres) hit; the k-th sub-beam from the far side sits (k - 1/2) / K of
    the footprint in, so the edge excess per side is (1/2 - (k - 1/2) / K) w."""
    k = max(1, math.ceil(q * k_sub - 1e-9))
    return (k - 0.5) / k_sub


def _park(seed: int, clutter: bool = False) -> tuple[Any, np.ndarray]:
    """A park-like stand (open grass, scattered trunks 10-90 cm, >= 6 m apart) and a drive
    of east-west passes through it (poses (S, 3) of the laser, 0.2135 s x 3 m/s steps).
    ``clutter``: 80 bushes (radius 0.5-2 m) among the trunks and a fence 30 m outside the
    drive's field, so that trunk edges also mix with surfaces behind them."""
    from stemmap.sim.forest import Stand

    gen = np.random.default_rng(seed)
    xy: list[np.ndarray] = []
    while len(xy) < 160:
        p = gen.uniform([0.0, 0.0], [220.0, 160.0])
        if all(np.hypot(*(p - q)) >= 6.0 for q in xy):
            xy.append(p)
    diam = np.clip(np.exp(gen.normal(math.log(0.35), 0.45, len(xy))), 0.10, 0.90)
    if clutter:
        bush = gen.uniform([0.0, 0.0], [220.0, 160.0], (80, 2))
        far = np.min(np.hypot(*(bush[:, None, :] - np.array(xy)[None]).transpose(2, 0, 1)), 1)
        bush = bush[far > 3.0]
        x0, y0, x1, y1 = -50.0, -30.0, 270.0, 190.0
        fence = np.array([[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]])
        stand = Stand(
            np.array(xy),
            diam,
            clutter_xy=bush,
            clutter_radius=gen.uniform(0.5, 2.0, bush.shape[0]),
            segments=fence,
            segment_owner=np.full(4, -1),
        )
    else:
        stand = Stand(np.array(xy), diam)
    poses = []
    step = 3.0 * 0.2135
    for k, y in enumerate(np.arange(8.0, 160.0, 16.0)):
        xs = np.arange(-20.0, 240.0, step)
        if k % 2:
            xs = xs[::-1]
        th = 0.0 if k % 2 == 0 else math.pi
        yy = y + 1.5 * np.sin(xs / 17.0)  # gentle weave: bearings and phases vary
        heading = th + np.arctan(1.5 / 17.0 * np.cos(xs / 17.0)) * (1 if k % 2 == 0 else -1)
        poses.append(np.column_stack((xs, yy, heading)))
    return stand, np.concatenate(poses)


def _excess(
    pid: np.ndarray, r: np.ndarray, width: np.ndarray, mask: np.ndarray, boot: int, **kw: Any
) -> dict[str, Any]:
    """:func:`~stemmap.eval.beam_width.width_excess` of the masked detections as JSON (degrees),
    or the reason it could not be computed."""
    from stemmap.errors import InputError
    from stemmap.eval.beam_width import width_excess

    try:
        res = width_excess(pid[mask], r[mask], width[mask], n_boot=boot, **kw)
    except InputError as exc:
        return {"error": str(exc)}
    return {
        "excess_deg": math.degrees(res.excess),
        "excess_ci_deg": [math.degrees(v) for v in res.ci],
        "excess_se_deg": math.degrees(res.se),
        "excess_median_pass_deg": math.degrees(res.median_pass),
        "passes": res.passes,
        "detections": res.detections,
    }


def _analyse(
    frame: np.ndarray,
    xy: np.ndarray,
    ranges: np.ndarray,
    beams: np.ndarray,
    boot: int,
    *,
    sensitivity: bool = False,
) -> dict[str, Any]:
    """Passes, usable detections, the pooled excess at 2-15 m (headline) and over all ranges,
    per range band and per trunk size, and the within-pass diameter-on-range slope for every
    assumed threshold."""
    from stemmap.eval.beam_width import link_passes, usable_detections

    pid = link_passes(frame, xy, gate=1.0, max_gap=3)
    width = beams * DELTA
    keep = usable_detections(
        pid, ranges, width, DELTA, min_beams=2.0, max_beams=MAX_BEAMS, min_range=2.0
    )
    near = keep & (ranges < NEAR_M)
    out: dict[str, Any] = {
        "detections": int(frame.size),
        "passes": int(np.unique(pid).size),
        "usable_detections": int(keep.sum()),
        f"near_2_{NEAR_M:g}m": _excess(pid, ranges, width, near, boot),
        "all_ranges": _excess(pid, ranges, width, keep, boot),
    }
    head = out[f"near_2_{NEAR_M:g}m"]
    if "excess_deg" in head:
        e = math.radians(head["excess_deg"])
        head["q_for_0.25deg"] = 0.5 * (1.0 - e / FOOTPRINT)
        head["q_ci_for_0.25deg"] = sorted(
            0.5 * (1.0 - math.radians(v) / FOOTPRINT) for v in head["excess_ci_deg"]
        )
        # the DBH-drift test: per assumed threshold, the slope (mm of diameter per m of range)
        # left after correcting the widths for it, pooled over passes: e - (1 - 2 q) w
        head["slope_mm_per_m_by_assumed_q"] = {
            f"{q:g}": 1e3 * (e - (1.0 - 2.0 * q) * FOOTPRINT) for q in ASSUMED_Q
        }
    out["by_range_band"] = {
        f"{lo:g}-{hi:g}": _excess(
            pid, ranges, width, keep & (ranges >= lo) & (ranges < hi), boot, min_spread=1.15
        )
        for lo, hi in BANDS
    }
    # trunk size per pass: median of width x range (the reported diameter)
    _, inv = np.unique(pid, return_inverse=True)
    dmed = np.array([np.median((width * ranges)[inv == k]) for k in range(inv.max() + 1)])
    size = dmed[inv]
    out["near_by_pass_diameter_m"] = {
        f"{lo:g}-{hi:g}": _excess(pid, ranges, width, near & (size >= lo) & (size < hi), boot)
        for lo, hi in SIZES
    }
    if sensitivity:
        sens: dict[str, Any] = {}
        for mx in (6.0, math.inf):
            k2 = usable_detections(
                pid, ranges, width, DELTA, min_beams=2.0, max_beams=mx, min_range=2.0
            )
            sens[f"max_beams_{mx:g}"] = _excess(pid, ranges, width, k2 & (ranges < NEAR_M), boot)
        for mb in (1.5, 3.0):
            k2 = usable_detections(
                pid, ranges, width, DELTA, min_beams=mb, max_beams=MAX_BEAMS, min_range=2.0
            )
            sens[f"min_beams_{mb:g}"] = _excess(pid, ranges, width, k2 & (ranges < NEAR_M), boot)
        for gate in (0.5, 2.0):
            p2 = link_passes(frame, xy, gate=gate, max_gap=3)
            k2 = usable_detections(
                p2, ranges, width, DELTA, min_beams=2.0, max_beams=MAX_BEAMS, min_range=2.0
            )
            sens[f"gate_{gate:g}m"] = _excess(p2, ranges, width, k2 & (ranges < NEAR_M), boot)
        out["near_sensitivity"] = sens
    return out


def run_sim(
    q: float, seed: int, n_scans: int | None, boot: int, *, clutter: bool = False
) -> dict[str, Any]:
    """Simulated SICK (0.5 deg, footprint 0.25 deg, 20 sub-beams, 1 cm noise) with return
    threshold ``q``; the drive's detections through the benchmark's pipeline."""
    from stemmap.eval.beam_width import beam_tree_detections
    from stemmap.sim.scanner import scanner_preset, simulate_scans

    stand, poses = _park(seed, clutter)
    if n_scans is not None:
        poses = poses[:n_scans]
    model = scanner_preset(
        "sick_lms", sub_beams=SUB_BEAMS, min_hit_fraction=q, range_max=80.0, range_noise=0.01
    )
    scans, _, _ = simulate_scans(stand, poses, model, rng=seed)
    det = beam_tree_detections(scans.ranges, model.angle_min, model.angle_increment)
    pose = poses[det.scan]
    ang = pose[:, 2] + det.bearing
    xy = pose[:, :2] + det.range[:, None] * np.column_stack((np.cos(ang), np.sin(ang)))
    out = _analyse(det.scan, xy, det.range, det.beams, boot)
    out["clutter"] = clutter
    qe = _q_eff(q)
    out.update(
        {
            "scanner_q": q,
            "scanner_q_eff": qe,
            "expected_excess_deg": math.degrees((1.0 - 2.0 * qe) * FOOTPRINT),
            "seed": seed,
            "scans": int(poses.shape[0]),
        }
    )
    return out


#: Apparent width excess of a disc under the real-geometry virtual scanner (20 uniform
#: sub-rays, a sub-ray counts when anything is in its sub-cell), in footprints, measured on
#: perfect 30 cm discs (docs/algorithms/scan-detection.md, "Averaging scanners: the return
#: threshold (Dec 4)": 0.965 / 0.565 / 0.135 / -0.375 / -0.94 for q = 0 / 0.25 / 0.5 / 0.75 / 1;
#: the step rule's (1 - 2 q_eff), q_eff = (ceil(20 q) - 1) / 20, gives 1 / 0.6 / 0.1 / -0.4 /
#: -0.9).
VIRTUAL_EXCESS_FOOTPRINTS = {0.0: 0.965, 0.25: 0.565, 0.5: 0.135, 0.75: -0.375, 1.0: -0.94}


def run_real(
    name: str, q: float, n_vantage: int, seed: int, boot: int, sl: Any = None
) -> dict[str, Any]:
    """Virtual SICK scans (0.5 deg, 0.25 deg footprint, 20 sub-rays, threshold ``q``) of a
    real breast-height slice from ``n_vantage`` vantage points 2-25 m from its trunks, the
    same detector, detections matched to the reference trunks (nearest centre within the
    radius + 0.5 m); a "pass" is one trunk seen from one tenth of the vantage points (the
    vantage points are independent draws)."""
    from _datasets import require_datasets_dir
    from _real_scanning import vantage_points
    from stemmap.eval.beam_width import beam_tree_detections
    from stemmap.eval.real_slices import load_slice, virtual_scans

    if sl is None:
        sl = load_slice(require_datasets_dir(), name)
    gen = np.random.default_rng(seed)
    vp = vantage_points(sl, n_vantage, gen, 2.0, 25.0)
    ranges, _ = virtual_scans(
        sl.xy,
        sl.labels,
        vp,
        resolution_deg=0.5,
        model="averaging",
        footprint_deg=math.degrees(FOOTPRINT),
        sub_rays=SUB_BEAMS,
        min_hit_fraction=q,
        centers=sl.centers,
        max_range=40.0,
    )
    det = beam_tree_detections(ranges, -math.pi, DELTA)
    pos = vp[det.scan] + det.range[:, None] * np.column_stack(
        (np.cos(det.bearing), np.sin(det.bearing))
    )
    c = sl.centers
    dist = np.hypot(*(pos[:, None, :] - c[None, :, :]).transpose(2, 0, 1))
    t = np.argmin(dist, axis=1)
    ok = dist[np.arange(t.size), t] < 0.5 * sl.diameters[t] + 0.5
    pid = t[ok] * 10 + det.scan[ok] % 10
    from stemmap.eval.beam_width import usable_detections, width_excess

    width = det.beams[ok] * DELTA
    rr = det.range[ok]
    keep = usable_detections(
        pid, rr, width, DELTA, min_beams=2.0, max_beams=MAX_BEAMS, min_range=2.0
    )
    res = width_excess(pid[keep], rr[keep], width[keep], n_boot=boot)
    expect = VIRTUAL_EXCESS_FOOTPRINTS.get(q)
    return {
        "dataset": name,
        "scanner_q": q,
        "trunks": int(c.shape[0]),
        "vantages": int(vp.shape[0]),
        "detections_matched": int(ok.sum()),
        "detections_used": res.detections,
        "excess_deg": math.degrees(res.excess),
        "excess_ci_deg": [math.degrees(v) for v in res.ci],
        "expected_excess_deg": None if expect is None else expect * math.degrees(FOOTPRINT),
    }


def run_vp(data: str | None, boot: int) -> dict[str, Any]:
    """The Victoria Park detections: beams spanned from range and diameter, passes linked in
    the dead-reckoned frame (the repo's calibrated vehicle model)."""
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.beam_width import beams_spanned
    from stemmap.slam.base import observation_to_world
    from stemmap.slam.motion import preintegrate

    vp = load_victoria_park(data)
    fr = vp.frames
    m = vp.model
    pre = preintegrate(m, vp.controls, fr.times, with_covariance=False)
    frame = np.repeat(np.arange(len(fr)), np.diff(fr.ptr))
    xy = observation_to_world(pre.poses[frame], fr.ranges, fr.bearings, m.sensor_offset)
    r = np.asarray(fr.ranges)
    d = np.asarray(fr.diameters)
    n = beams_spanned(r, d, DELTA)
    nf = n.astype(float)
    off = (nf - 1.0) / nf
    edge = r - 0.5 * d + np.where(n > 2, 0.5 * d * (1.0 - np.sqrt(1.0 - off * off)), 0.0)
    frac = d / (DELTA * edge) - n  # how far from a whole number of beams
    out = _analyse(frame, xy, r, n, boot, sensitivity=True)
    out["beam_count_residual_p99_by_beams_1_to_8"] = [
        float(np.percentile(np.abs(frac[n == k]), 99)) for k in range(1, 9)
    ]
    out["beams_histogram_1_to_8"] = np.bincount(np.minimum(n, 8), minlength=9)[1:].tolist()
    return out


def _near(row: dict[str, Any]) -> dict[str, Any]:
    return dict(row[f"near_2_{NEAR_M:g}m"])


def _calibrate(sim_rows: list[dict[str, Any]], vp: dict[str, Any] | None) -> dict[str, Any]:
    """Least-squares line excess = a + b q_eff over the simulated rows (2-15 m window); the
    VP threshold (and its interval from the VP bootstrap interval) read off the line."""
    qe = np.array([r["scanner_q_eff"] for r in sim_rows])
    ex = np.array([_near(r)["excess_deg"] for r in sim_rows])
    expect = np.array([r["expected_excess_deg"] for r in sim_rows])
    b, a = np.polyfit(qe, ex, 1)
    cal: dict[str, Any] = {
        "line_excess_deg": {"intercept": float(a), "slope_per_q": float(b)},
        "expected_line": {
            "intercept": math.degrees(FOOTPRINT),
            "slope_per_q": -2 * math.degrees(FOOTPRINT),
        },
        "max_abs_error_deg": float(np.max(np.abs(ex - expect))),
        "mean_error_deg": float(np.mean(ex - expect)),
    }
    if vp is not None and "excess_deg" in _near(vp):
        v = _near(vp)
        cal["vp_q_calibrated_for_0.25deg"] = float((v["excess_deg"] - a) / b)
        cal["vp_q_calibrated_ci"] = sorted(float((e - a) / b) for e in v["excess_ci_deg"])
    return cal


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", nargs="+", default=["sim", "real", "vp"])
    ap.add_argument("--q", nargs="+", type=float, default=[0.05, 0.25, 0.5, 0.75, 1.0])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1])
    ap.add_argument("--scans", type=int, default=None, help="first N poses of each drive")
    ap.add_argument("--clutter", action="store_true", help="bushes and a fence in the park")
    ap.add_argument(
        "--real",
        nargs="+",
        default=["fortls_slice", "treels_pine", "lidr_dbh"],
        help="real slices for the virtual-scan validation",
    )
    ap.add_argument("--real-q", nargs="+", type=float, default=[0.0, 0.25, 0.5, 0.75, 1.0])
    ap.add_argument("--vantage", type=int, default=600)
    ap.add_argument("--boot", type=int, default=1000)
    ap.add_argument("--data", default=None, help="Victoria Park folder")
    args = ap.parse_args(argv)
    bad = set(args.parts) - {"sim", "real", "vp"}
    if bad:
        ap.error(f"unknown parts {sorted(bad)}: choose from sim, real, vp")
    t0 = time.process_time()
    out: dict[str, Any] = {
        "footprint_deg": math.degrees(FOOTPRINT),
        "step_deg": 0.5,
        "argv": sys.argv[1:] if argv is None else argv,
    }
    sim_rows: list[dict[str, Any]] = []
    if "sim" in args.parts:
        for seed in args.seeds:
            for q in args.q:
                sim_rows.append(run_sim(q, seed, args.scans, args.boot, clutter=args.clutter))
                print(f"sim q={q} seed={seed} done", file=sys.stderr)
        out["sim"] = sim_rows
    if "real" in args.parts:
        from _datasets import require_datasets_dir
        from stemmap.errors import InputError
        from stemmap.eval.real_slices import load_slice

        rows: list[dict[str, Any]] = []
        ddir = require_datasets_dir()
        for name in args.real:
            sl = load_slice(ddir, name)
            for q in args.real_q:
                try:
                    rows.append(run_real(name, q, args.vantage, 1, args.boot, sl))
                except InputError as exc:
                    rows.append({"dataset": name, "scanner_q": q, "error": str(exc)})
                print(f"real {name} q={q} done", file=sys.stderr)
        out["real_geometry"] = rows
    vp = None
    if "vp" in args.parts:
        vp = run_vp(args.data, args.boot)
        out["victoria_park"] = vp
    if len(sim_rows) >= 2:
        out["calibration"] = _calibrate(sim_rows, vp)
    out["cpu_s"] = time.process_time() - t0
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
