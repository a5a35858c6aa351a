"""Every column a writer produces is documented in docs/outputs.md, in the product's section.

Each writer runs on a small simulated input; the test reads back what was WRITTEN (CSV
header, GeoJSON properties, GeoPackage fields via GDAL, JSON keys, LAS dimensions) and checks
every name against the backticked names of that product's section of docs/outputs.md. A new
column without documentation fails here, so the docs cannot drift from the code again.
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pytest
from pyogrio import list_layers, read_info

from stemmap.cli._detect import _write_rejected_csv
from stemmap.cli._stems_products import write_forestry_products
from stemmap.cloud.export import write_stems_csv, write_stems_geojson, write_stems_gpkg
from stemmap.cloud.result import CloudStems
from stemmap.engine.manifest import Manifest
from stemmap.eval.trajectory import AteResult, RpeResult
from stemmap.io.geo import write_map_gpkg
from stemmap.io.maps import (
    write_observations_csv,
    write_trees_csv,
    write_trees_geojson,
    write_trees_information,
)
from stemmap.io.trajectory import write_trajectory_csv
from stemmap.types import StemMap, StemObservations, Trajectory, Tree

DOC = Path(__file__).resolve().parents[2] / "docs" / "outputs.md"


def _section(heading: str) -> set[str]:
    """Names in backticks (split on anything but identifier characters) of the ``##`` section
    whose heading starts with ``heading``, up to the next ``##`` heading."""
    text = DOC.read_text(encoding="utf-8")
    parts = re.split(r"^## ", text, flags=re.M)
    hits = [p for p in parts if p.startswith(heading)]
    assert len(hits) == 1, f"docs/outputs.md has no single section '## {heading}'"
    names: set[str] = set()
    for code in re.findall(r"`([^`]+)`", hits[0]):
        names.update(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", code))
    return names


def _undocumented(written: list[str] | set[str], heading: str) -> list[str]:
    """Names not in the section; ``PREFIX_*`` in the docs covers ``PREFIX_<documented>``."""
    doc = _section(heading)
    text = re.split(r"^## ", DOC.read_text(encoding="utf-8"), flags=re.M)
    sec = next(p for p in text if p.startswith(heading))
    prefixes = re.findall(r"`([A-Za-z0-9_]+_)\*`", sec)

    def ok(c: str) -> bool:
        return c in doc or any(c.startswith(p) and c[len(p) :] in doc for p in prefixes)

    return sorted(c for c in written if not ok(c))


def _header(path: Path) -> list[str]:
    with open(path, newline="") as fh:
        return next(csv.reader(fh))


def _stems(k: int = 3) -> CloudStems:
    cov = np.tile(np.diag([1e-4, 2e-4]), (k, 1, 1))
    f = np.full(k, 0.5)
    return CloudStems(
        np.array([[0.0, 0.0], [4.0, 1.0], [-3.0, 3.0]])[:k],
        np.full(k, 1.3), np.array([0.2, 0.3, 0.25])[:k], np.full(k, 80), f, np.full(k, 300.0),
        np.full(k, 0.003), np.full(k, 4), f * 0, np.full(k, 12.0), np.full(k, np.nan),
        diameter_std=np.full(k, 0.004), xy_cov=cov, dbh_height=np.full(k, 1.3),
        dbh_rule=np.full(k, "breast height", dtype=object), method="ours", base="ground",
    )  # fmt: skip


def _stem_map() -> StemMap:
    trees = (
        Tree(1, 1.0, 2.0, 0.3, cov=np.diag([0.01, 0.02]), n_obs=5, first_time=0.0, last_time=3.0),
        Tree(2, 5.0, 2.0, 0.2, n_obs=2, confidence=0.4, diameter_std=0.01),
    )
    return StemMap(trees)


def _trajectory() -> Trajectory:
    t = np.arange(4.0)
    return Trajectory(t, np.column_stack((t, np.zeros(4), np.zeros(4))))


def test_the_check_catches_an_undocumented_column() -> None:
    assert _undocumented(["diameter", "no_such_column"], "stems CSV") == ["no_such_column"]
    # a name documented for another product does not count here
    assert _undocumented(["confidence"], "stems CSV") == ["confidence"]


def test_stems_csv_geojson_gpkg_documented(tmp_path: Path) -> None:
    s = _stems()
    write_stems_csv(tmp_path / "s.csv", s)
    assert _undocumented(_header(tmp_path / "s.csv"), "stems CSV") == []
    write_stems_geojson(tmp_path / "s.geojson", s)
    props = json.loads((tmp_path / "s.geojson").read_text())["features"][0]["properties"]
    assert _undocumented(set(props), "stems CSV") == []
    write_stems_gpkg(tmp_path / "s.gpkg", s)
    fields = list(read_info(tmp_path / "s.gpkg", layer="stems")["fields"])
    assert {"cov_xx", "cov_xy", "cov_yy", "dbh_rule", "base", "diameter_std"} <= set(fields)
    assert _undocumented(fields, "stems CSV") == []


def test_forestry_products_documented(tmp_path: Path, rng: np.random.Generator) -> None:
    """Profile CSV, metrics JSON and labelled LAS from a cloud of three simulated stems."""
    s = _stems()
    pts = []
    for (cx, cy), d in zip(s.xy, s.diameter, strict=True):
        t = rng.uniform(0, 2 * math.pi, 3000)
        z = rng.uniform(0.0, 4.0, 3000)
        r = d / 2 * (1 - 0.02 * z) + rng.normal(0, 0.002, 3000)
        pts.append(np.column_stack((cx + r * np.cos(t), cy + r * np.sin(t), z)))
    pts.append(np.column_stack((rng.uniform(-6, 6, (3000, 2)), rng.normal(0, 0.01, 3000))))
    cloud = tmp_path / "plot.xyz"
    np.savetxt(cloud, np.vstack(pts), fmt="%.4f")
    prof, met, lab = tmp_path / "p.csv", tmp_path / "m.json", tmp_path / "l.las"
    s = CloudStems(**{**s.__dict__, "z": np.full(3, 1.3)})
    write_forestry_products(cloud, s, 10**6, None, profile=prof, metrics=met, labels=lab)
    assert _undocumented(_header(prof), "stems CSV") == []  # the --profile bullet
    doc = json.loads(met.read_text())
    keys = set(doc) | set(doc["dbh_histogram"]) | {k for t in doc["trees"] for k in t}
    assert doc["trees"], "no per-tree metrics: the check below would be empty"
    assert _undocumented(keys, "stems CSV") == []
    dims = set(laspy.read(lab).point_format.extra_dimension_names)
    assert dims == {"tree_id"} and _undocumented(dims, "stems CSV") == []


def test_map_products_documented(tmp_path: Path) -> None:
    m = _stem_map()
    write_trees_csv(tmp_path / "t.csv", m)
    assert _undocumented(_header(tmp_path / "t.csv"), "trees.csv") == []
    write_trees_geojson(tmp_path / "t.geojson", m)
    feats = json.loads((tmp_path / "t.geojson").read_text())["features"]
    props = {k for f in feats for k in f["properties"]} | {
        k for f in feats for k in f if k != "type"
    }
    assert _undocumented(props - {"geometry", "properties"}, "trees.csv") == []
    write_trajectory_csv(tmp_path / "tr.csv", _trajectory(), covs=np.stack([np.eye(3)] * 4))
    assert len(_header(tmp_path / "tr.csv")) == 10  # with the covariance columns
    assert _undocumented(_header(tmp_path / "tr.csv"), "trajectory.csv") == []
    info = np.eye(2 * len(m)) * 100.0
    write_trees_information(tmp_path / "ti.npz", replace(m, information=info))
    with np.load(tmp_path / "ti.npz") as z:
        assert _undocumented(list(z.files), "trees_information.npz") == []
    write_map_gpkg(tmp_path / "m.gpkg", m, _trajectory())
    for layer, _ in list_layers(tmp_path / "m.gpkg"):
        fields = list(read_info(tmp_path / "m.gpkg", layer=layer)["fields"])
        where = "trees.csv" if layer == "trees" else "map.gpkg"
        assert _undocumented([layer], "map.gpkg") == []
        assert _undocumented(fields, where) == [], layer


def test_gnss_track_documented(tmp_path: Path) -> None:
    """``stemmap map --gnss``: trajectory_gnss.csv, its GeoJSON and its map.gpkg layers."""
    from stemmap.cli._map_gnss import (
        GnssTrack,
        gnss_track_layers,
        write_gnss_track,
    )

    tr = _trajectory()
    track = GnssTrack(tr, np.full(4, 0.3), np.stack([np.eye(3)] * 4), {})
    names = write_gnss_track(
        tmp_path, track, crs="EPSG:32633", frame="map", trajectory_format="csv"
    )
    assert names == ["trajectory_gnss.csv", "trajectory_gnss.geojson"]
    assert _undocumented(_header(tmp_path / names[0]), "trajectory_gnss.csv") == []
    feats = json.loads((tmp_path / names[1]).read_text())["features"]
    props = {k for f in feats for k in f["properties"]}
    assert _undocumented(props, "trajectory_gnss.csv") == []
    write_map_gpkg(tmp_path / "m.gpkg", _stem_map(), tr, extra_layers=gnss_track_layers(track))
    for layer, _ in list_layers(tmp_path / "m.gpkg"):
        fields = list(read_info(tmp_path / "m.gpkg", layer=layer)["fields"])
        where = "trees.csv" if layer == "trees" else "map.gpkg"
        assert _undocumented([layer], "map.gpkg") == []
        assert _undocumented(fields, where) == [], layer


def test_detect_products_documented(tmp_path: Path) -> None:
    k = 2
    obs = StemObservations(
        np.array([[2.0, 0.5], [4.0, -1.0]]), np.array([0.1, 0.15]),
        np.tile(np.eye(3) * 1e-4, (k, 1, 1)), np.array([12, 20]), np.array([60.0, 80.0]),
        np.array([0.2, 0.3]), np.array([0.9, 0.8]), np.array([0, 1]), np.array([0.0, 0.1]),
    )  # fmt: skip
    write_observations_csv(tmp_path / "d.csv", obs)
    assert _undocumented(_header(tmp_path / "d.csv"), "detections.csv") == []
    part = {
        "scan_index": np.array([0]), "time": np.array([0.0]), "reason": np.array(["min_points"]),
        "n_points": np.array([2]), "bearing_deg": np.array([10.0]), "range": np.array([3.0]),
        "width": np.array([0.05]), "partial": np.array([False]), "x": np.array([np.nan]),
        "y": np.array([np.nan]), "radius": np.array([np.nan]), "rms": np.array([np.nan]),
        "sigma": np.array([np.nan]), "failed_test": ["min_points"], "pieces": np.array([0]),
        "pieces_accepted": np.array([0]),
    }  # fmt: skip
    assert _write_rejected_csv(tmp_path / "r.csv", [part]) == 1
    assert _undocumented(_header(tmp_path / "r.csv"), "rejected candidates CSV") == []


def test_catalog_manifest_documented(tmp_path: Path) -> None:
    man = Manifest(tmp_path / "work")
    man.append("c0_0", "failed", {"a.laz": "00"}, "ff", seconds=1.0, error="boom")
    man.append(
        "c0_0", "done", {"a.laz": "00"}, "ff", seconds=1.0, n_points=10, n_stems=1, result="ab"
    )
    lines = (tmp_path / "work" / "manifest.jsonl").read_text().splitlines()
    keys = {k for ln in lines for k in json.loads(ln)}
    assert _undocumented(keys, "stems catalog work folder") == []


def test_multilog_summary_documented(tmp_path: Path) -> None:
    from stemmap.cli._multilog import _write_summary

    _write_summary(tmp_path / "summary.csv", [{"log": "a", "status": "done", "n_trees": 3}])
    assert _undocumented(_header(tmp_path / "summary.csv"), "summary.csv") == []


@pytest.mark.parametrize("res", ["ate", "rpe"])
def test_trajectory_metric_keys_documented(res: str) -> None:
    z = np.zeros(0)
    r = (
        AteResult(0.0, 0.0, 0.0, 0.0, 1, z, None)
        if res == "ate"
        else RpeResult(0.0, 0.0, 0.0, 0.0, 0.0, 1, 10.0, "m", z, z)
    )
    keys = set(r.as_dict())
    if res == "ate":  # the map command also scores dead reckoning and, with GNSS, unaligned
        keys |= {p + k[4:] for k in keys for p in ("dead_reckoning_ate_", "ate_unaligned_")}
    assert _undocumented(keys, "metrics.json") == []
