"""Where the soak's memory goes, pass by pass (issue 13): one back-end on the replayed drive.

Runs the back-end (``isam2`` or ``ekf``) in this process on ``benchmarks/soak.py``'s
``revisit_drive`` (ACFR Victoria Park, ``--repeats`` passes, alternately forward and backward)
and at the end of every pass (the back-end's progress call) records:

* ``rss_mb`` (``VmRSS``) and glibc's heap (``mallinfo2``): bytes in use (``malloc_inuse_mb``,
  which sees GTSAM's C++ and numba's allocations as well as Python's), free bytes kept in the
  arenas (``malloc_free_mb``: fragmentation) and mmapped blocks;
* with ``--trace``: ``tracemalloc``'s traced bytes (Python objects and numpy arrays) and the
  12 source lines whose allocations grew most since the previous pass (slow: ~5x);
* EKF (``--backend ekf``): the filter's per-drive state part by part, read from the
  back-end's own frame at the progress call (``sys._getframe``; nothing is changed): the
  smoother's association log (rows, rows spilled to its file, resident bytes, merge aliases),
  the co-seen landmark pairs (a Python set of tuples; bytes estimated from ``sys.getsizeof``),
  the landmark ids issued (the per-id bookkeeping arrays touched, 49 bytes per id), the
  filter poses written (24 bytes per frame), the compressed filter's state arrays and the
  pre-integrated odometry (allocated before the loop);
* iSAM2: the sizes of the ISAM2 object (factors, variables, cliques, Bayes tree non-zeros,
  cached separator marginals), the left-out store (keyframes, those spilled to its file,
  resident measurements and bytes), the revisit gate's place entries, and the keyframes by why
  they entered the graph (``RevisitGate.leave_out``'s answer: left out, not allowed = first /
  GNSS / lost tracker, a new tree, a young tree or loop closure) and the measurement factors;
* the end: ATE under one alignment against the screened GPS, trees, the back-end's counters,
  and least-squares slopes over passes 3..N of RSS, heap in use and traced bytes.

Instrumentation: subclasses of ``gtsam.ISAM2``, ``LeftOutMeasurements`` and ``RevisitGate``
swapped in for this process only (they record, they change nothing). Numbers from a shared
machine: memory is deterministic up to the allocator, times are not.

Usage: ``python benchmarks/soak_memory.py --json [--backend isam2|ekf] [--repeats 10]
[--trace] [--data DIR] [--set KEY=VALUE ...]``
"""

from __future__ import annotations

import argparse
import collections
import ctypes
import gc
import json
import resource
import sys
import time
import tracemalloc
from typing import Any

import numpy as np

from _soak_common import parse_settings as _parse_settings  # shared with soak.py
from _soak_common import revisit_drive
from _soak_common import rss_now_mb as _rss_now_mb


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (n, ctypes.c_size_t)
        for n in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
            "fordblks", "keepcost",
        )
    ]  # fmt: skip


def _heap() -> dict[str, float]:
    """glibc heap statistics (MB), empty where ``mallinfo2`` is missing."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
        mi = libc.mallinfo2()
    except (OSError, AttributeError):
        return {}
    mb = 1.0 / 2**20
    return {
        "malloc_inuse_mb": round(mi.uordblks * mb, 2),
        "malloc_free_mb": round(mi.fordblks * mb, 2),
        "malloc_mmap_mb": round(mi.hblkhd * mb, 2),
    }


def _instrument(box: dict[str, Any], why: collections.Counter[str]) -> None:
    """Record the ISAM2 object, the left-out store and the revisit gate of the next run."""
    import gtsam

    import stemmap.slam.graph as graph

    class ISAM2(gtsam.ISAM2):  # type: ignore[misc]
        def __init__(self, *a: Any) -> None:
            super().__init__(*a)
            box["isam"] = self

    class Store(graph.LeftOutMeasurements):
        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            box["store"] = self

    class Gate(graph.RevisitGate):
        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            box["gate"] = self

        def leave_out(self, xy: Any, s: float, trees: Any, in_graph: Any, *a: Any, **k: Any):  # type: ignore[no-untyped-def]
            out = super().leave_out(xy, s, trees, in_graph, *a, **k)
            allowed = k.get("allowed", a[1] if len(a) > 1 else True)
            if out:
                why["left_out"] += 1
            elif not allowed:
                why["not_allowed"] += 1
            elif trees.size and not np.all(in_graph[trees]):
                why["new_tree"] += 1
            else:
                why["young_tree_or_loop"] += 1
            return out

        def entered(self, xy: Any, s: float, anchored: bool = False) -> None:
            why["entered"] += 1
            why["anchored"] += bool(anchored)
            super().entered(xy, s, anchored)

        def factored(self, trees: Any, s: float = 0.0) -> None:
            why["measurement_factors"] += int(trees.size)
            super().factored(trees, s)

    gtsam.ISAM2 = ISAM2
    graph.LeftOutMeasurements = Store  # type: ignore[misc]
    graph.RevisitGate = Gate  # type: ignore[misc]


def _sizes(box: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    isam, st, gate = box.get("isam"), box.get("store"), box.get("gate")
    if isam is not None:
        out |= {
            "isam_factors": isam.getFactorsUnsafe().size(),
            "isam_variables": isam.getLinearizationPoint().size(),
            "isam_cliques": isam.size(),
            "isam_tree_nnz": isam.treeNnz(),
            "isam_cached_marginals": isam.numCachedSeparatorMarginals(),
        }
    if st is not None:
        out |= {
            "store_keyframes": len(st),
            "store_spilled_keyframes": getattr(st, "spilled", 0),
            "store_resident_mb": round(
                sum(a.nbytes for a in (st._kf, st._ptr, st._tree, st._val)) / 2**20, 2
            ),
        }
    if gate is not None:
        out |= {
            "place_counter_entries": sum(len(v) for v in gate.places._cells.values()),
            "place_visits_entries": sum(len(v) for v in gate.visits._cells.values()),
        }
    return out


def _ekf_parts(fr: Any) -> dict[str, Any]:
    """The EKF back-end's per-drive state, from its run frame's locals (module docstring)."""
    if fr is None:
        return {}
    loc = fr.f_locals
    mb = 1.0 / 2**20
    out: dict[str, Any] = {}
    olog = loc.get("olog")
    if olog is not None:
        if hasattr(olog, "resident_nbytes"):
            res, n, spilled = olog.resident_nbytes, len(olog), olog.spilled
        else:  # before the log spilled: four growing arrays
            res = sum(getattr(olog, k).nbytes for k in ("_f", "_id", "_r", "_b"))
            n, spilled = olog._n, 0
        out |= {
            "olog_rows": n,
            "olog_spilled_rows": spilled,
            "olog_resident_mb": round(res * mb, 3),
            "olog_alias_entries": len(olog._alias),
        }
    coseen = loc.get("coseen")
    if coseen is not None:
        per = sys.getsizeof((0, 0)) + 2 * sys.getsizeof(10**6)  # a tuple of two large ints
        out["coseen_pairs"] = len(coseen)
        out["coseen_mb_est"] = round((sys.getsizeof(coseen) + len(coseen) * per) * mb, 3)
    if "n_ids" in loc:  # compressed filter: arrays indexed by landmark id
        out["landmark_ids"] = int(loc["n_ids"])
        out["landmark_ids_touched_mb"] = round(int(loc["n_ids"]) * 49 * mb, 3)
    elif "lm_id" in loc:  # full filter: Python lists per alive landmark
        out["landmarks_alive"] = len(loc["lm_id"])
    if "f" in loc and "poses" in loc:
        out["poses_written_mb"] = round((int(loc["f"]) + 1) * 24 * mb, 3)
    st = loc.get("st")
    if st is not None:
        arrs = [v for v in vars(st).values() if isinstance(v, np.ndarray)]
        out["compressed_state_mb"] = round(sum(a.nbytes for a in arrs) * mb, 3)
        out["compressed_active_rows"] = int(st.nA)
    pre = loc.get("pre")
    if pre is not None:
        out["preintegrated_mb"] = round((pre.deltas.nbytes + pre.covs.nbytes) * mb, 2)
    return out


def _slope(rows: list[dict[str, Any]], key: str) -> float | None:
    y = [r[key] for r in rows[2:] if key in r]
    if len(y) < 2:
        return None
    return round(float(np.polyfit(np.arange(len(y)), y, 1)[0]), 3)


def run(backend: str, repeats: int, data: str | None, trace: bool, settings: dict[str, Any]):  # type: ignore[no-untyped-def]
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import ate
    from stemmap.slam.base import make_backend

    vp = load_victoria_park(data)
    make_backend(backend).run(vp.slice(0.0, 60.0).problem())  # compile numba kernels
    rep, spans = revisit_drive(vp, repeats)
    ends = [int(np.searchsorted(rep.frames.times, b, side="right")) for _, b in spans]
    box: dict[str, Any] = {}
    why: collections.Counter[str] = collections.Counter()
    if backend == "isam2":
        _instrument(box, why)
    rows: list[dict[str, Any]] = []
    last: list[Any] = [None]
    c0 = time.process_time()
    if trace:
        tracemalloc.start(1)

    def measure(p: int, caller: Any) -> None:
        gc.collect()
        row: dict[str, Any] = {"pass": p + 1, "rss_mb": _rss_now_mb(), **_heap()}
        row["cpu_s"] = round(time.process_time() - c0, 1)
        row |= dict(why) | _sizes(box)
        if backend == "ekf":
            row |= _ekf_parts(caller)
        if trace:
            snap = tracemalloc.take_snapshot()
            row["traced_mb"] = round(tracemalloc.get_traced_memory()[0] / 2**20, 2)
            if last[0] is not None:
                row["traced_growth_kb_top"] = [
                    [str(d.traceback), round(d.size_diff / 1024, 1), d.count_diff]
                    for d in snap.compare_to(last[0], "lineno")[:12]
                ]
            last[0] = snap
        rows.append(row)

    nxt = [0]

    def progress(done: int, total: int) -> None:
        while nxt[0] < len(ends) and done >= ends[nxt[0]]:
            measure(nxt[0], sys._getframe(1))  # the back-end's run (EKF parts)
            nxt[0] += 1

    res = make_backend(backend, **settings).run(rep.problem(name="replay"), progress=progress)
    if trace:
        tracemalloc.stop()
    r1 = ate(
        res.trajectory, rep.gps_times, rep.gps_xy, offset=rep.model.sensor_offset,
        keep=rep.screened_gps(),
    )  # fmt: skip
    return {
        "benchmark": "soak_memory",
        "backend": backend,
        "repeats": repeats,
        "settings": settings,
        "per_pass": rows,
        # least-squares slopes over passes 3..N (MB per pass)
        "rss_mb_per_pass_from_3": _slope(rows, "rss_mb"),
        "malloc_inuse_mb_per_pass_from_3": _slope(rows, "malloc_inuse_mb"),
        "traced_mb_per_pass_from_3": _slope(rows, "traced_mb"),
        **{
            f"{k}_per_pass_from_3": _slope(rows, k)
            for k in (
                "olog_resident_mb",
                "coseen_mb_est",
                "landmark_ids_touched_mb",
                "poses_written_mb",
                "compressed_state_mb",
            )
            if backend == "ekf" and any(k in r for r in rows)
        },
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "rss_end_mb": _rss_now_mb(),
        "ate_rmse_m_one_alignment": round(float(r1.rmse), 3) if r1 else None,
        "n_trees": len(res.stem_map.trees),
        "backend_stats": {k: v for k, v in res.stats.items() if isinstance(v, int)},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--backend", default="isam2", choices=("isam2", "ekf"))
    ap.add_argument("--repeats", type=int, default=10, help="passes over the log (default 10)")
    ap.add_argument("--trace", action="store_true", help="tracemalloc at every pass end")
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    out = run(args.backend, args.repeats, args.data, args.trace, _parse_settings(ap, args.set))
    print(json.dumps(out, indent=1 if args.json else None))


if __name__ == "__main__":
    main()
