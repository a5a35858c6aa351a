"""Soak benchmark (issue 13): a Victoria Park drive N times as long, through ``stemmap map``.

The real log (ACFR Victoria Park, text redistribution, read with
:func:`stemmap.datasets.victoria_park.load_victoria_park`) is replayed ``--repeats`` times as
revisits of the same park, built in memory (the dataset files are only read). The log ends
21 m (GPS) from where it starts, with another heading, so replaying it forward again would
teleport the vehicle, which no odometry explains. Every second pass is therefore the log
driven *backwards* (time reversed, wheel speed negated, the same scans in reverse order): the
vehicle retraces its path to the start, where the next forward pass begins, so every pass
revisits the same trees and the motion is physically continuous. Passes are 1 s apart
(standing still).

Each back-end runs in its own subprocess (honest peak RSS) through the ``stemmap map``
command itself (typer app, ``--dataset victoria-park``) with the dataset loader swapped for
the replayed drive, so product writing, uncertainty annotation and metrics are the CLI's own.
Reported per back-end and repeat count:

* ``peak_rss_mb`` (``ru_maxrss``) and ``rss_after_load_mb`` (before SLAM);
* time per 100 scans from the back-end's progress calls (every keyframe for iSAM2, every 50
  scans for the EKF): first tenth vs last tenth of the run (``growth_last_vs_first``), and
  per pass; per pass also the process CPU time per scan of those progress intervals (median
  and 99th percentile, ms: CPU time, so usable on a loaded machine) and the RSS (``VmRSS``)
  at the pass's end, with ``rss_mb_per_pass_from_3`` the least-squares slope of the latter
  over passes 3 to N (the memory growth per pass once the map is built);
* map quality: ATE against the screened GPS for every pass (each pass aligned on its own)
  and for the whole run under ONE alignment (drift between passes shows there), tree count,
  mapped trees first seen in each pass, and pairs of trees closer than 1 m (revisits must
  not create duplicates), compared with a 1x run of the same back-end;
* the back-end's graph counters (iSAM2: keyframes in the graph, localisation-mode counters),
  and for iSAM2 per pass the graph keyframes and measurement factors added and the RSS at the
  pass's end (``VmRSS``: the current size, where ``peak_rss_mb`` is the peak);
* ``heap_trims`` and ``heap_trim_cpu_s``: the ``malloc_trim`` calls during SLAM (the map
  command's :class:`stemmap._memory.HeapTrimmer` and the iSAM2 back-end's own, which share
  one interval) and the CPU time spent in them.

The progress log is flat doubles (48 bytes per progress call; a list of tuples grew this
process by ~0.6 MB per pass, which the RSS slope counted as the back-end's). Where the memory
goes part by part: ``benchmarks/soak_memory.py``.

A warm-up run on the first 60 s compiles the numba kernels before timing. Absolute times are
from a loaded shared machine (2 cores, ~8 users): compare the ratios.

Usage: ``python benchmarks/soak.py --json [--repeats 10] [--backends isam2,ekf] [--set
KEY=VALUE ...]`` (``--set`` overrides one setting of the back-end's config, as in
``benchmarks/slam_victoria_park.py``, for A/B runs; echoed in the output)
"""

from __future__ import annotations

import argparse
import array
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from _soak_common import GAP_S, revisit_drive  # shared with soak_memory.py
from _soak_common import parse_settings as _parse_settings
from _soak_common import rss_now_mb as _rss_now_mb


def _rss_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)


def _count_graph_growth() -> list[int]:
    """[graph keyframes, measurement factors] added so far by :class:`Isam2Slam`, live.

    Counted through the calls the back-end makes for exactly these events on its
    :class:`~stemmap.slam._graph_revisits.RevisitGate` (``entered``: one per graph keyframe
    after the first; ``factored``: the trees of one keyframe's measurement factors), wrapped
    for this process only.
    """
    import stemmap.slam._graph_run as graph_run  # where Isam2Slam's run builds its gate

    n = [0, 0]

    class Gate(graph_run.RevisitGate):
        def entered(self, xy: Any, s: float, anchored: bool = False) -> None:
            n[0] += 1
            super().entered(xy, s, anchored)

        def factored(self, trees: Any, s: float = 0.0) -> None:
            n[1] += int(trees.size)
            super().factored(trees, s)

    graph_run.RevisitGate = Gate  # type: ignore[misc]
    return n


def _time_heap_trims(*modules: Any) -> list[float]:
    """[trims, CPU s in them] of the :class:`~stemmap._memory.HeapTrimmer` of each module
    (the map command's, the iSAM2 back-end's own), live (wrapped for this process only; stays
    [0, 0] with code that has no trimmer)."""
    out = [0.0, 0.0]
    for mod in modules:
        base = getattr(mod, "HeapTrimmer", None)
        if base is None:
            continue

        class Timed(base):  # type: ignore[misc, valid-type]
            def __init__(self, *a: Any, **k: Any) -> None:
                super().__init__(*a, **k)
                inner = self._trim

                def timed() -> bool:
                    c = time.process_time()
                    r = bool(inner())
                    out[0] += 1
                    out[1] += time.process_time() - c
                    return r

                self._trim = timed

        mod.HeapTrimmer = Timed
    return out


def _per_100(marks: np.ndarray, n: int) -> dict[str, Any]:
    """Seconds per 100 scans in the first and last tenth, from (frames done, time) marks."""
    f = np.concatenate(([0.0], marks[:, 0]))
    t = np.concatenate(([0.0], marks[:, 1]))
    a, b = np.interp([0.1 * n, 0.9 * n], f, t)
    first = 100.0 * a / (0.1 * n)
    last = 100.0 * (t[-1] - b) / (f[-1] - 0.9 * n)
    return {
        "s_per_100_scans_first_tenth": round(first, 4),
        "s_per_100_scans_last_tenth": round(last, 4),
        "growth_last_vs_first": round(last / first, 3),
    }


def _cpu_pass(marks: np.ndarray, cpu: np.ndarray, fa: int, fb: int) -> dict[str, Any]:
    """CPU time per scan (ms) of the progress intervals ending in frames ``(fa, fb]``: median,
    99th percentile and total; and the RSS (MB, ``VmRSS``) at the pass's last progress call."""
    f = np.concatenate(([0.0], marks[:, 0]))
    c = np.concatenate(([0.0], cpu[:, 0]))
    rss = np.concatenate(([0.0], cpu[:, 1]))
    i = np.flatnonzero((f[1:] > fa) & (f[1:] <= fb)) + 1
    if i.size == 0:
        return {}
    per_scan = 1000.0 * (c[i] - c[i - 1]) / np.maximum(f[i] - f[i - 1], 1.0)
    return {
        "cpu_ms_per_scan_p50": round(float(np.percentile(per_scan, 50)), 3),
        "cpu_ms_per_scan_p99": round(float(np.percentile(per_scan, 99)), 3),
        "cpu_s": round(float(c[i[-1]] - c[i[0] - 1]), 2),
        "rss_end_mb": round(float(rss[i[-1]]), 1),
    }


def _slope(y: list[float]) -> float | None:
    """Least-squares slope of ``y`` per step (None with fewer than 2 values)."""
    if len(y) < 2:
        return None
    return round(float(np.polyfit(np.arange(len(y)), np.asarray(y, dtype=float), 1)[0]), 2)


def _worker(
    backend: str, repeats: int, data: str | None, settings: dict[str, Any]
) -> dict[str, Any]:
    import stemmap.cli._map as cli_map
    import stemmap.slam._graph_run as slam_graph  # the iSAM2 run's HeapTrimmer
    import stemmap.slam.base as slam_base
    from stemmap.cli import app
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import ate

    vp = load_victoria_park(data)
    make = slam_base.make_backend
    make(backend).run(vp.slice(0.0, 60.0).problem())  # compile numba kernels before timing
    rep, spans = revisit_drive(vp, repeats)
    rss_load = _rss_mb()
    # per progress call: frames done, wall time, process CPU time, RSS now, graph keyframes and
    # measurement factors added so far (iSAM2); flat doubles (8 bytes each: a list of tuples
    # grew this process by ~0.6 MB per pass of 1,450 progress calls, which the RSS slope saw)
    log = array.array("d")
    seen: dict[str, Any] = {}
    grown = _count_graph_growth() if backend == "isam2" else None

    class Timed:
        def __init__(self, inner: Any) -> None:
            self.inner = inner

        def run(self, problem: Any, progress: Any = None) -> Any:
            t_start = time.perf_counter()
            c_start = time.process_time()

            def tick(done: int, total: int) -> None:
                log.extend((done, time.perf_counter() - t_start, time.process_time() - c_start))
                log.extend((_rss_now_mb(), *(grown if grown is not None else (0, 0))))
                if progress is not None:
                    progress(done, total)

            res = self.inner.run(problem, progress=tick)
            seen["slam_s"] = time.perf_counter() - t_start
            seen["peak_rss_after_slam_mb"] = _rss_mb()
            seen["result"] = res
            return res

    def timed_make(name: str, **cfg: Any) -> Any:
        return Timed(make(name, **(cfg | settings)))

    def replayed(data_: Any, t_end: Any, t_start: float = 0.0) -> Any:
        return rep.problem(name=f"victoria_park x{repeats}"), {"kind": "victoria-park", "vp": rep}

    trims = _time_heap_trims(cli_map, slam_graph)
    slam_base.make_backend = timed_make
    cli_map._victoria_park = replayed  # type: ignore[assignment]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "map"
        argv = ["map", "--dataset", "victoria-park", "--backend", backend, "--out", str(out)]
        argv += ["--no-progress", "--json"] + (["--data", data] if data else [])
        t_cli = time.perf_counter()
        app(argv, standalone_mode=False)
        cli_s = time.perf_counter() - t_cli
        rss_map = _rss_mb()
        metrics = json.loads((out / "metrics.json").read_text())
    res = seen["result"]
    lg = np.frombuffer(log, dtype=np.float64).reshape(-1, 6)
    marks, cpu_marks = lg[:, :2], lg[:, 2:4]
    keep = rep.screened_gps()
    off = rep.model.sensor_offset
    per_pass: list[dict[str, Any]] = []
    ends = [0] + [int(np.searchsorted(rep.frames.times, b, side="right")) for _, b in spans]
    first_seen = np.array([t.first_time for t in res.stem_map.trees])
    for k, (a, b) in enumerate(spans):
        in_pass = keep & (rep.gps_times >= a) & (rep.gps_times <= b)
        r = ate(res.trajectory, rep.gps_times, rep.gps_xy, offset=off, keep=in_pass)
        fa, fb = ends[k], ends[k + 1]
        ta, tb = np.interp([fa, fb], np.r_[0.0, marks[:, 0]], np.r_[0.0, marks[:, 1]])
        graph_pass: dict[str, Any] = _cpu_pass(marks, cpu_marks, fa, fb)
        if grown is not None:
            # the back-end's graph growth in this pass (iSAM2) and the RSS at its end
            gm = lg[:, [0, 4, 5, 3]]  # frames, keyframes, factors, RSS
            ia = int(np.searchsorted(gm[:, 0], fa)) - 1
            ib = min(int(np.searchsorted(gm[:, 0], fb)), len(gm) - 1)
            prev = gm[ia] if ia >= 0 else np.zeros(4)
            graph_pass |= {
                "graph_keyframes_added": int(gm[ib, 1] - prev[1]),
                "measurement_factors_added": int(gm[ib, 2] - prev[2]),
                "rss_at_end_mb": round(float(gm[ib, 3]), 1),
            }
        per_pass.append(
            {
                **graph_pass,
                "direction": "forward" if k % 2 == 0 else "backward",
                "ate_rmse_m": round(float(r.rmse), 3) if r else None,
                "s_per_100_scans": round(100.0 * (tb - ta) / max(fb - fa, 1), 4),
                # mapped trees first seen in this pass (a revisit should add ~none)
                "new_trees": int(np.count_nonzero((first_seen >= a) & (first_seen <= b + GAP_S))),
            }
        )
    return {
        "backend": backend,
        "repeats": repeats,
        "settings": settings,
        "scans": len(rep.frames),
        "drive_s": round(spans[-1][1] - spans[0][0], 1),
        "peak_rss_mb": _rss_mb(),
        "rss_after_load_mb": rss_load,
        # peak so far at the end of the back-end's run and of the whole map command (products,
        # metrics); peak_rss_mb also covers this benchmark's own per-pass scoring
        "peak_rss_after_slam_mb": seen["peak_rss_after_slam_mb"],
        "peak_rss_after_map_command_mb": rss_map,
        "slam_s": round(seen["slam_s"], 1),
        # the map command's heap trims during SLAM (malloc_trim(0); none before they existed)
        "heap_trims": trims[0],
        "heap_trim_cpu_s": round(trims[1], 4),
        "map_command_s": round(cli_s, 1),
        **_per_100(marks, len(rep.frames)),
        # pass 1 builds the map (cost grows with it); from pass 2 on the map is complete
        "growth_last_vs_second_pass": (
            round(per_pass[-1]["s_per_100_scans"] / per_pass[1]["s_per_100_scans"], 3)
            if len(per_pass) > 2
            else None
        ),
        # RSS growth per pass from the third on (least-squares slope of the RSS at the passes'
        # ends): ~0 when nothing but the per-scan state grows
        "rss_mb_per_pass_from_3": _slope([p_["rss_end_mb"] for p_ in per_pass][2:]),
        "ate_rmse_m_one_alignment": metrics.get("ate_rmse_m"),
        "gps_fixes_kept": metrics.get("gps_fixes_kept"),
        "per_pass": per_pass,
        "n_trees": metrics["n_trees"],
        "duplicates_1m": metrics["duplicates_1m"],
        # the back-end's own counters (graph size, localisation mode), where it has them
        "backend_stats": {
            k: v
            for k, v in res.stats.items()
            if k.startswith(("keyframes", "tracker_", "landmarks"))
            or k in ("factors", "isam2_updates")
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    ap.add_argument("--repeats", type=int, default=10, help="passes over the log (default 10)")
    ap.add_argument("--backends", default="isam2,ekf", help="comma list")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a back-end config setting (repeatable; value parsed as JSON; give one "
        "back-end with --backends when the setting exists only in its config)",
    )
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--result", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    settings = _parse_settings(ap, args.set)
    if args.worker:
        r = _worker(args.worker, args.repeats, args.data, settings)
        Path(args.result).write_text(json.dumps(r))
        return
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for be in [b for b in args.backends.split(",") if b]:
            for n in sorted({1, args.repeats}):
                name = f"{be}_x{n}"
                res_path = Path(tmp) / f"{name}.json"
                cmd = [sys.executable, __file__, "--worker", be, "--repeats", str(n)]
                cmd += ["--result", str(res_path)] + (["--data", args.data] if args.data else [])
                for item in args.set:
                    cmd += ["--set", item]
                t0 = time.perf_counter()
                proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
                if proc.returncode != 0 or not res_path.exists():
                    results[name] = {"error": proc.stderr.strip().splitlines()[-3:] or ["failed"]}
                    continue
                results[name] = json.loads(res_path.read_text())
                results[name]["wall_s"] = round(time.perf_counter() - t0, 1)
    out = {
        "benchmark": "soak",
        "repeats": args.repeats,
        "settings": settings,
        "results": results,
        "scenario": {
            "dataset": "ACFR Victoria Park (text redistribution), passes alternately forward "
            "and backward, `stemmap map` defaults",
            "cpu_count": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
        },
    }
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for k, v in out.items():
            print(k, v)


if __name__ == "__main__":
    main()
