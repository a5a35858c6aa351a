"""Run the dendromatics (3DFIN) stem/DBH pipeline with its documented defaults on LAS/LAZ files.

Executed by benchmarks/cloud_stems.py with a separate Python interpreter that has dendromatics
installed (it pins older laspy / scipy / scikit-learn, so it is kept out of stemmap's own
environment). Prints ONE JSON line: per file, stems found, DBH per stem, time, or the error.

The pipeline follows the order of 3DFIN's processing: CSF ground -> DTM -> normalised heights
(clouds whose z extent is below 1 m are taken as already normalised, as stemmap does) ->
stripe 0.7-3.5 m -> verticality clustering -> individualize_trees -> compute_sections every
0.2 m from 0.3 m -> tilt_detection -> tree_locator (DBH at 1.3 m). All parameters are the
dendromatics defaults unless noted in the JSON.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import time
from typing import Any

import numpy as np


def run_one(path: str, n_points: int = 1000, h_range: float = 1.0) -> dict[str, Any]:
    import dendromatics as dm
    import laspy

    las = laspy.read(path)
    xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)
    t0 = time.perf_counter()
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink):
        if np.ptp(xyz[:, 2]) < 1.0:
            z0 = xyz[:, 2] - (xyz[:, 2].min() - 1.2 if xyz[:, 2].min() > 3.0 else 0.0)
            normalisation = "pre-cut slice: z taken as height (shifted to start at 1.2 m if high)"
        else:
            clean = dm.clean_ground(xyz)
            cloth = dm.generate_dtm(clean)
            cloth = dm.clean_cloth(cloth)
            dtm = dm.complete_dtm(cloth)
            z0 = dm.normalize_heights(xyz, dtm)
            normalisation = "CSF DTM (dendromatics defaults)"
        cloud = np.column_stack((xyz, z0))
        lo, hi = 0.7, 3.5
        stripe = cloud[(cloud[:, 3] > lo) & (cloud[:, 3] < hi)]
        clust = dm.verticality_clustering(stripe, n_points=n_points)  # x, y, z, z0 (as 3DFIN)
        assigned, tree_vector, _heights = dm.individualize_trees(
            cloud, clust, stripe_lower_limit=lo, stripe_upper_limit=hi, h_range=h_range
        )
        stems = assigned[assigned[:, 5] < 0.5]  # points near an axis (3DFIN: stem search radius)
        sections = np.arange(0.3, 3.5, 0.2)
        X_c, Y_c, R, _check, _second, sector_perct, _n_in = dm.compute_sections(stems, sections)
        outliers = dm.tilt_detection(X_c, Y_c, R, sections)
        dbh, loc = dm.tree_locator(sections, X_c, Y_c, tree_vector, sector_perct, R, outliers)
    dt = time.perf_counter() - t0
    d = np.asarray(dbh).reshape(-1)
    return {
        "time_s": round(dt, 3),
        "verticality_n_points": n_points,
        "h_range_fraction_of_stripe": h_range,
        "normalisation": normalisation,
        "n_stems": int(d.size),
        "n_stems_with_dbh": int((d > 0).sum()),
        "stems": [
            {
                "x": round(float(loc[k, 0]), 3),
                "y": round(float(loc[k, 1]), 3),
                "dbh_cm": round(100 * float(d[k]), 1),
            }
            for k in range(d.size)
        ],
    }


def main() -> None:
    from importlib.metadata import version

    out: dict[str, Any] = {"version": version("dendromatics"), "files": {}}
    for path in sys.argv[1:]:
        key = path.rsplit("/", 2)[-2] + "/" + path.rsplit("/", 1)[-1]
        out["files"][key] = {}
        # the defaults (n_points=1000; h_range=1: stems must span the whole 0.7-3.5 m stripe),
        # then a relaxed variant for lower-density clouds
        variants = (("defaults", 1000, 1.0), ("n_points_100_h_range_0.5", 100, 0.5))
        for label, n, hr in variants:
            try:
                out["files"][key][label] = run_one(path, n, hr)
            except Exception as exc:  # report the peer's failure, do not hide it
                out["files"][key][label] = {"error": f"{type(exc).__name__}: {exc}"[:500]}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
