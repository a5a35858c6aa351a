"""What the first-echo detections of a real slice contain, view by view (issue 11, Dec 6,
"Junction merges on lidR" in docs/algorithms/scan-detection.md).

Replays ``first_echo_dbh_z.py``'s nearest-return scans (``_real_scanning.scene_batches``, the
same seed, vantage points and noise draws; ``--only`` keeps the other slices' seeds), runs the
``stemmap`` preset set up for a first-echo scanner (``--set``: overrides), and for every matched
visible view records which returns the output candidate holds, each classified on the
*noise-free* scan: ``stem`` (a beam of the reference trunk's cluster whose noise-free return
lies within ``--tol`` of the reference ring), ``branch`` (a beam of the trunk's cluster off the
ring: a branch, the collar beyond ``--tol``), ``other`` (a beam of anything else: another
trunk, understory). For each view also the error of the same detector on the stem beams alone
(every other beam masked: perfect segmentation), so that the share of the DBH error and of the
|z| excess that the merged returns explain can be read off: ``merged`` views are those with a
non-stem return in the candidate.

Return rule: nearest-return scans only. The averaging (SICK-class) scans ``scene_batches``
draws besides are skipped; their rule is passed by name, ``_real_scanning.ANY_HIT`` (any
sub-ray), and changes no draw here (the noise is drawn by the scans' shape).

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/junction_trace.py --only lidr_dbh --vantage 60

One JSON object on stdout (``views``: one row per matched view; ``summary`` per noise level).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _real_scanning import ANY_HIT, greedy_match, matched, scene_batches
from real_geometry import visible_trunks
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.types import ScanBatch


class _Beams:
    """Records the beams of every output candidate, keyed by (scan, centre), by wrapping
    ``_output_columns`` (diagnostics only; detections unchanged)."""

    def __init__(self) -> None:
        self.table: dict[tuple[int, float, float], np.ndarray] = {}
        self.jack: dict[tuple[int, float, float], dict[str, float]] = {}
        self.cfg: DetectorConfig | None = None

    def install(self) -> None:
        import stemmap.scan._pieces as pieces
        import stemmap.scan.detect as detect
        from stemmap.scan._segment_fits import _output_columns

        def wrapped(segs: Any, fitted: Any, ok: Any, cfg: Any = None) -> dict[str, np.ndarray]:
            cols = _output_columns(segs, fitted, ok, cfg)
            for j in np.flatnonzero(ok):
                a, b = int(segs.start[j]), int(segs.stop[j])
                c = fitted.centers[j]
                key = (int(segs.scan[j]), float(c[0]), float(c[1]))
                self.table[key] = segs.points.beam[a:b].copy()
            if self.cfg is not None and np.any(ok):
                self._jack(segs.select(ok), fitted, ok)
            return cols

        detect._output_columns = wrapped  # type: ignore[attr-defined]
        pieces._output_columns = wrapped  # type: ignore[attr-defined]

    def _jack(self, segs: Any, fitted: Any, ok: Any) -> None:
        from stemmap.scan._segment_fits import _fit_segments, fit_sigma

        cfg = self.cfg
        assert cfg is not None
        sig = fitted.sigma[ok]
        fs = fit_sigma(cfg.fit_noise_floor, segs, sig)
        sig = sig if fs is None else fs
        n = segs.counts
        full = _fit_segments(segs, cfg.fit_method, sig, residuals=cfg.fit_residuals,
                             edge_window=cfg.edge_window_share())  # fmt: skip
        drops = []
        for i in range(int(n.max())):
            kp = np.ones(len(segs.points), dtype=bool)
            has = n > i + 2  # keep >= 3 returns
            kp[(segs.start + i)[has]] = False
            sub = segs.drop(kp)
            sub = type(sub)(sub.points, sub.start, sub.stop, sub.scan,
                            sub.occluded_start | (has & (i == 0)),
                            sub.occluded_end | (has & (i == n - 1)),
                            sub.truncated_start, sub.truncated_end)  # fmt: skip
            _, r, _, okk = _fit_segments(sub, cfg.fit_method, sig, residuals=cfg.fit_residuals,
                                         edge_window=cfg.edge_window_share())  # fmt: skip
            drops.append(np.where(has & okk, r, np.nan))
        d = np.array(drops)  # (max n, K)
        for j in range(len(segs)):
            rj = d[: n[j], j]
            rj = rj[np.isfinite(rj)]
            m = rj.size
            var = (m - 1) / m * np.sum((rj - rj.mean()) ** 2) if m >= 3 else np.nan
            e = [d[0, j], d[n[j] - 1, j]]
            c = fitted.centers[ok][j]
            self.jack[(int(segs.scan[j]), float(c[0]), float(c[1]))] = {
                "r_refit": float(full[1][j]),
                "jack_sd": float(2 * np.sqrt(var)) if np.isfinite(var) else None,
                "end_shift": float(2 * np.nanmax(np.abs(np.array(e) - full[1][j]))),
            }


BEAMS = _Beams()
JACK = False


def beam_classes(
    ranges0: np.ndarray, hit: np.ndarray, batch: ScanBatch, rel: np.ndarray, r: float, t: int,
    tol: float,
) -> np.ndarray:  # fmt: skip
    """Per beam of one scan: 0 stem (the noise-free return within ``tol`` of the reference
    ring, whichever sub-ray of the footprint returned it), 1 branch (a beam labelled with the
    trunk's cluster, off the ring), 2 other, -1 no return (noise-free scan)."""
    n = ranges0.shape[0]
    th = batch.angle_min + batch.angle_increment * np.arange(n)
    with np.errstate(invalid="ignore"):
        x, y = ranges0 * np.cos(th), ranges0 * np.sin(th)
        dev = np.hypot(x - rel[0], y - rel[1]) - r
    out = np.where(hit == t, 1, 2)
    out[np.abs(dev) <= tol] = 0  # on the ring, whichever ray of the footprint hit it
    out[~np.isfinite(ranges0)] = -1
    return out


def trace(
    ddir: Path, n_vantage: int, seed: int, only: list[str], overrides: dict[str, Any], tol: float
) -> list[dict[str, Any]]:
    """One row per matched visible view (module docstring)."""
    base = DetectorConfig.preset("stemmap", **overrides)
    rows: list[dict[str, Any]] = []
    for sc in scene_batches(ddir, n_vantage, seed, return_rule=ANY_HIT, names=only):
        if sc.model != "nearest":
            continue
        cfg = matched(base, "nearest", sc.res)
        det = ScanTrunkDetector(cfg)
        BEAMS.table.clear()
        BEAMS.jack.clear()
        BEAMS.cfg = cfg if JACK else None
        obs = det.detect_batch(sc.batch)
        BEAMS.cfg = None
        table = dict(BEAMS.table)
        jack = dict(BEAMS.jack)
        sl, vp, hit, b = sc.sl, sc.vp, sc.hit, sc.batch
        assert sc.ranges0 is not None
        diam = sl.diameters
        n_hits = np.stack([(hit == t).sum(axis=1) for t in range(len(sl.refs))], axis=1)
        for s in range(vp.shape[0]):
            rel = sl.centers - vp[s]
            vis, rng_t = visible_trunks(n_hits[s], rel, diam, cfg, 4)
            m = np.flatnonzero(obs.index == s)
            match = greedy_match(obs.centers[m], rel, diam / 2.0 + 0.05)
            for t in np.flatnonzero(vis & (match >= 0)):
                k = m[match[t]]
                cls = beam_classes(sc.ranges0[s], hit[s], b, rel[t], diam[t] / 2.0, int(t), tol)
                beams = table.get((s, *map(float, obs.centers[k])), np.zeros(0, np.int64))
                c = cls[beams]
                stem_beams = np.flatnonzero(cls == 0)
                masked = b.ranges.copy()  # the batch with scan s's non-stem beams masked:
                masked[s] = np.where(cls == 0, b.ranges[s], np.inf)  # the batch statistics stay
                o = det.detect_batch(replace(b, ranges=masked))
                o = o.select(o.index == s)
                ks = greedy_match(o.centers, rel[t : t + 1], diam[t : t + 1] / 2.0 + 0.05)[0]
                foreign = np.flatnonzero(c != 0)
                cov = obs.covs[k].reshape(3, 3)
                rows.append(
                    {
                        "dataset": sl.name,
                        "step": sc.res,
                        "noise": sc.noise,
                        "scan": int(s),
                        "trunk": int(t),
                        "range": round(float(rng_t[t]), 3),
                        "dbh": float(diam[t]),
                        "err": float(2.0 * obs.radii[k] - diam[t]),
                        "sd": float(2.0 * math.sqrt(max(cov[2, 2], 0.0))),
                        "n": int(obs.n_points[k]),
                        "n_stem": int((c == 0).sum()),
                        "n_branch": int((c == 1).sum()),
                        "n_other": int((c == 2).sum()),
                        "stem_beams_visible": int(stem_beams.size),
                        # where the non-stem returns sit in the candidate: 0 first ... n-1 last
                        "foreign_pos": foreign.tolist(),
                        **jack.get((s, *map(float, obs.centers[k])), {}),
                        "beams": [int(beams[0]), int(beams[-1])] if beams.size else [],
                        "solo_err": float(2.0 * o.radii[ks] - diam[t]) if ks >= 0 else None,
                        "solo_sd": (
                            float(2.0 * math.sqrt(max(o.covs[ks].reshape(3, 3)[2, 2], 0.0)))
                            if ks >= 0
                            else None
                        ),
                    }
                )
    return rows


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per noise level: views, merged views, median |z|, RMSE; and the same with each merged
    view's error and std replaced by its stem-only detection's (where it has one)."""
    out: dict[str, Any] = {}
    for noise in sorted({r["noise"] for r in rows}):
        rr = [r for r in rows if r["noise"] == noise]
        err = np.array([r["err"] for r in rr])
        sd = np.array([r["sd"] for r in rr])
        merged = np.array([r["n_branch"] + r["n_other"] > 0 for r in rr])
        z = np.abs(err) / sd
        e2, s2 = err.copy(), sd.copy()
        for i, r in enumerate(rr):
            if merged[i] and r["solo_err"] is not None:
                e2[i], s2[i] = r["solo_err"], r["solo_sd"]
        z2 = np.abs(e2) / s2
        out[f"{100 * noise:g}cm"] = {
            "views": len(rr),
            "merged": int(merged.sum()),
            "med_z": round(float(np.median(z)), 3),
            "med_z_unmerged_only": round(float(np.median(z[~merged])), 3) if (~merged).any()
            else None,
            "med_z_merged_only": round(float(np.median(z[merged])), 3) if merged.any() else None,
            "med_z_merged_replaced_by_stem_only": round(float(np.median(z2)), 3),
            "rmse_cm": round(100 * float(np.sqrt(np.mean(err**2))), 2),
            "rmse_unmerged_cm": round(100 * float(np.sqrt(np.mean(err[~merged] ** 2))), 2)
            if (~merged).any() else None,
            "rmse_merged_replaced_cm": round(100 * float(np.sqrt(np.mean(e2**2))), 2),
            "sum_sq_share_merged": round(float((err[merged] ** 2).sum() / (err**2).sum()), 3),
        }  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=Path, default=None)
    ap.add_argument("--vantage", type=int, default=60)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--only", nargs="+", default=["lidr_dbh"])
    ap.add_argument("--set", default="{}", help="JSON overrides of the stemmap preset")
    ap.add_argument("--tol", type=float, default=0.025, help="ring tolerance (m) of a stem beam")
    ap.add_argument("--jack", action="store_true", help="delete-one refits of every output")
    args = ap.parse_args(argv)
    BEAMS.install()
    global JACK
    JACK = args.jack
    ddir = require_datasets_dir(args.datasets)
    rows = trace(ddir, args.vantage, args.seed, args.only, json.loads(args.set), args.tol)
    print(json.dumps({"benchmark": "junction_trace", "set": args.set, "tol": args.tol,
                      "summary": summary(rows), "views": rows}))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
