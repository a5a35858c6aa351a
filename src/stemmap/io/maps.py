"""Stem maps and per-frame stem observations: CSV and GeoJSON, written atomically.

Formats (also in docs/algorithms/io.md):

* trees CSV: ``id,x,y,diameter,std_x,std_y,n_obs,diameter_std,confidence,cov_xy_m2,
  first_time_s,last_time_s`` -- metres, seconds; ``nan`` where unknown. Plain CSV without
  comment lines, so that spreadsheets and GIS tools read it as is; the frame / CRS are not
  stored in it.
* observations CSV (the ``stemmap detect`` output): ``scan_index,time_s,x,y,diameter,
  radius_std,n_points,arc_deg,width,quality,std_x,std_y`` -- sensor frame, metres, seconds, degrees.
* trees GeoJSON (RFC 7946): a FeatureCollection of Points, see :func:`write_trees_geojson`.
* trees information NPZ (``trees_information.npz`` beside ``trees.csv``): the map's joint
  information matrix (:attr:`~stemmap.types.StemMap.information`) with the tree ids it is
  ordered by, see :func:`write_trees_information`.

Every column is described in docs/outputs.md. Readers also accept the pre-0.2 names ``time``,
``first_time``, ``last_time``, ``cov_xy``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from stemmap.errors import InputError
from stemmap.io._util import (
    PathLike,
    check_npz_sizes,
    existing_file,
    fmt_row,
    parse_numeric_csv,
    read_text,
    require_finite,
    require_integer,
)
from stemmap.io.atomic import atomic_write
from stemmap.types import FloatArray, StemMap, StemObservations, Tree

__all__ = [
    "OBSERVATION_CSV_COLUMNS",
    "TREES_INFORMATION_NPZ",
    "TREE_CSV_COLUMNS",
    "local_to_lonlat",
    "lonlat_to_local",
    "read_observations_csv",
    "read_trees_csv",
    "read_trees_geojson",
    "read_trees_information",
    "tree_rows",
    "write_observations_csv",
    "write_trees_csv",
    "write_trees_geojson",
    "write_trees_information",
]

#: Columns of the trees CSV, in order. ``std_x``, ``std_y`` are sqrt of the covariance diagonal.
TREE_CSV_COLUMNS = (
    "id",
    "x",
    "y",
    "diameter",
    "std_x",
    "std_y",
    "n_obs",
    "diameter_std",
    "confidence",
    "cov_xy_m2",
    "first_time_s",
    "last_time_s",
)
_TREE_REQUIRED = ("id", "x", "y", "diameter")

#: Columns of the observations CSV written by ``stemmap detect``, in order.
OBSERVATION_CSV_COLUMNS = (
    "scan_index",
    "time_s",
    "x",
    "y",
    "diameter",
    "radius_std",
    "n_points",
    "arc_deg",
    "width",
    "quality",
    "std_x",
    "std_y",
)
_OBS_REQUIRED = ("scan_index", "time_s", "x", "y", "diameter")

# WGS84 ellipsoid (NIMA TR8350.2)
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_E2 = _WGS84_F * (2.0 - _WGS84_F)


# --------------------------------------------------------------------------------------------
# trees CSV
# --------------------------------------------------------------------------------------------


def _tree_row(t: Tree) -> tuple[Any, ...]:
    sx, sy = (math.sqrt(v) if v >= 0 else math.nan for v in (t.cov[0, 0], t.cov[1, 1]))
    return (
        int(t.id),
        t.x,
        t.y,
        t.diameter,
        sx,
        sy,
        int(t.n_obs),
        t.diameter_std,
        t.confidence,
        float(t.cov[0, 1]),
        t.first_time,
        t.last_time,
    )


def tree_rows(stem_map: StemMap) -> list[tuple[Any, ...]]:
    """One tuple per tree in :data:`TREE_CSV_COLUMNS` order (std from the covariance)."""
    return [_tree_row(t) for t in stem_map]


def write_trees_csv(path: PathLike, stem_map: StemMap) -> None:
    """Write one row per tree with columns :data:`TREE_CSV_COLUMNS`, atomically.

    Parameters
    ----------
    path : str or PathLike
        Output file; parent folders are created.
    stem_map : StemMap
        Coordinates in metres in ``stem_map.frame``; diameters in metres.

    Notes
    -----
    Floats are written with the shortest text that reads back to the same float64, so
    :func:`read_trees_csv` reproduces the map exactly (frame and CRS excepted).
    """
    with atomic_write(path) as fh:
        fh.write(",".join(TREE_CSV_COLUMNS) + "\n")
        for t in stem_map:
            fh.write(fmt_row(_tree_row(t)) + "\n")


def read_trees_csv(path: PathLike, *, frame: str = "map", crs: str | None = None) -> StemMap:
    """Read a trees CSV written by :func:`write_trees_csv` (or any CSV with at least
    ``id,x,y,diameter``; missing optional columns become NaN / 0 / 1).

    Parameters
    ----------
    path : str or PathLike
    frame, crs : str
        Frame name and CRS given to the map (the CSV does not store them).

    Raises
    ------
    InputError
        Missing or empty file; missing required column; malformed row; NaN/inf in
        ``id``, ``x``, ``y`` or ``diameter``; a non-integer or repeated id; a negative diameter.
    """
    what = "trees CSV"
    p = existing_file(path, what)
    table = parse_numeric_csv(p, read_text(p, what), _TREE_REQUIRED, TREE_CSV_COLUMNS, what)
    for c in _TREE_REQUIRED:
        require_finite(p, what, table, c)
    require_integer(p, what, table, "id")
    cols = table.columns
    ids = cols["id"].astype(np.int64)
    uniq, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        raise InputError(f"{what} {str(p)!r} repeats tree id {int(uniq[counts > 1][0])}.")
    if np.any(cols["diameter"] < 0):
        k = int(np.argmax(cols["diameter"] < 0))
        raise InputError(
            f"{what} {str(p)!r} line {table.lines[k]}: diameter {cols['diameter'][k]} is negative."
        )
    n = ids.shape[0]

    def col(name: str, default: float) -> FloatArray:
        return cols[name] if name in cols else np.full(n, default)

    if "n_obs" in cols:
        n_obs_f = np.nan_to_num(cols["n_obs"], nan=0.0)
        cols["n_obs"] = n_obs_f
        require_integer(p, what, table, "n_obs")
    sx, sy, cxy = col("std_x", math.nan), col("std_y", math.nan), col("cov_xy_m2", math.nan)
    if "cov_xy_m2" not in cols:
        cxy = np.where(np.isfinite(sx) & np.isfinite(sy), 0.0, math.nan)
    n_obs = col("n_obs", 0.0).astype(np.int64)
    dstd, conf = col("diameter_std", math.nan), col("confidence", 1.0)
    t0, t1 = col("first_time_s", math.nan), col("last_time_s", math.nan)
    trees = tuple(
        Tree(
            id=int(ids[i]),
            x=float(cols["x"][i]),
            y=float(cols["y"][i]),
            diameter=float(cols["diameter"][i]),
            cov=np.array([[sx[i] ** 2, cxy[i]], [cxy[i], sy[i] ** 2]]),
            n_obs=int(n_obs[i]),
            first_time=float(t0[i]),
            last_time=float(t1[i]),
            confidence=float(conf[i]),
            diameter_std=float(dstd[i]),
        )
        for i in range(n)
    )
    return StemMap(trees, frame=frame, crs=crs)


# --------------------------------------------------------------------------------------------
# joint information NPZ (beside trees.csv)
# --------------------------------------------------------------------------------------------

#: File name of the joint information written beside ``trees.csv`` (``stemmap map``).
TREES_INFORMATION_NPZ = "trees_information.npz"


def write_trees_information(path: PathLike, stem_map: StemMap) -> None:
    """Write ``stem_map.information`` with the tree ids it is ordered by, atomically.

    The NPZ holds ``tree_ids`` (int64, shape (N,): the ``id`` column of trees.csv, in the
    matrix's tree order) and ``information`` (float64, shape (2N, 2N), 1/m²: rows and columns
    ``x_0, y_0, x_1, y_1, ...`` of the trees in ``tree_ids`` order).

    Raises
    ------
    InputError
        The map has no joint information.
    """
    if stem_map.information is None:
        raise InputError("write_trees_information: the stem map has no joint information.")
    ids = np.array([int(t.id) for t in stem_map], dtype=np.int64)
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(
            fh, tree_ids=ids, information=np.asarray(stem_map.information, dtype=np.float64)
        )


def read_trees_information(path: PathLike, stem_map: StemMap) -> StemMap:
    """``stem_map`` (read from the trees CSV beside ``path``) with the joint information of
    ``path`` (:func:`write_trees_information`), reordered to the map's tree order by id.

    Raises
    ------
    InputError
        Missing or unreadable file, missing arrays, wrong shapes, non-finite values, or tree
        ids that differ from the map's (the NPZ belongs to another trees CSV).
    """
    what = "trees information NPZ"
    p = existing_file(path, what)
    try:
        with np.load(p, allow_pickle=False) as z:
            check_npz_sizes(z, p, what)
            ids = np.asarray(z["tree_ids"], dtype=np.int64)
            info = np.asarray(z["information"], dtype=np.float64)
    except InputError:
        raise
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(
            f"{what} {str(p)!r} is unreadable or lacks 'tree_ids' / 'information': {exc}."
        ) from exc
    n = ids.shape[0]
    if ids.ndim != 1 or info.shape != (2 * n, 2 * n) or not np.isfinite(info).all():
        raise InputError(
            f"{what} {str(p)!r}: information must be a finite ({2 * n}, {2 * n}) matrix for "
            f"{n} tree ids, got shape {info.shape}."
        )
    map_ids = np.array([int(t.id) for t in stem_map], dtype=np.int64)
    if n != map_ids.size or not np.array_equal(np.sort(ids), np.sort(map_ids)):
        raise InputError(
            f"{what} {str(p)!r} has {n} tree ids that differ from the {map_ids.size} trees of "
            "the trees CSV beside it; rewrite both with one `stemmap map` run (or delete the "
            "NPZ to use per-tree priors)."
        )
    pos = {int(i): k for k, i in enumerate(ids)}
    src = np.array([pos[int(i)] for i in map_ids], dtype=np.int64)
    cols = np.column_stack([2 * src, 2 * src + 1]).reshape(-1)
    return StemMap(
        stem_map.trees,
        frame=stem_map.frame,
        crs=stem_map.crs,
        information=info[np.ix_(cols, cols)],
    )


# --------------------------------------------------------------------------------------------
# GeoJSON
# --------------------------------------------------------------------------------------------


def _meridian_radii(lat_rad: float) -> tuple[float, float]:
    """Meridional (M) and prime-vertical (N) radii of curvature of WGS84 at a latitude, m."""
    s2 = math.sin(lat_rad) ** 2
    w = math.sqrt(1.0 - _WGS84_E2 * s2)
    m = _WGS84_A * (1.0 - _WGS84_E2) / w**3
    nrad = _WGS84_A / w
    return m, nrad


def local_to_lonlat(
    xy: FloatArray, origin_lonlat: tuple[float, float]
) -> tuple[FloatArray, FloatArray]:
    """Local east-north metres around ``origin_lonlat`` to WGS84 longitude/latitude (degrees).

    Tangent-plane (equirectangular) approximation with the WGS84 radii of curvature at the
    origin's latitude: lat = lat0 + y / M, lon = lon0 + x / (N cos lat0). The position error
    grows with the square of the distance: below 1 cm within 1 km of the origin (for
    latitudes below 70 degrees), ample for a forest stand. ``x`` must point east, ``y`` north.

    Parameters
    ----------
    xy : ndarray of shape (N, 2), metres
        East, north offsets from the origin.
    origin_lonlat : (float, float)
        WGS84 longitude in [-180, 180] and latitude in (-90, 90), degrees.

    Returns
    -------
    lon, lat : ndarray of shape (N,), degrees

    Raises
    ------
    InputError
        If the origin is not a valid longitude/latitude pair.

    Examples
    --------
    >>> import numpy as np
    >>> lon, lat = local_to_lonlat(np.array([[0.0, 110574.3]]), (0.0, 0.0))
    >>> round(float(lat[0]), 4)  # 1 degree of latitude at the equator is 110.574 km
    1.0
    """
    lon0, lat0 = float(origin_lonlat[0]), float(origin_lonlat[1])
    if not (-180.0 <= lon0 <= 180.0 and -90.0 < lat0 < 90.0):
        raise InputError(
            f"origin_lonlat must be (longitude, latitude) in degrees, got ({lon0}, {lat0})."
        )
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    m, nrad = _meridian_radii(math.radians(lat0))
    lat = lat0 + np.degrees(p[:, 1] / m)
    lon = lon0 + np.degrees(p[:, 0] / (nrad * math.cos(math.radians(lat0))))
    return lon, lat


def lonlat_to_local(
    lon: FloatArray, lat: FloatArray, origin_lonlat: tuple[float, float]
) -> FloatArray:
    """Inverse of :func:`local_to_lonlat`: WGS84 degrees to east-north metres, shape (N, 2).

    Parameters
    ----------
    lon, lat : ndarray of shape (N,), degrees
    origin_lonlat : (float, float)
        Longitude, latitude (degrees) of the local origin.

    Returns
    -------
    ndarray of shape (N, 2)
        East, north (m): x = rad(lon - lon0) N cos(lat0), y = rad(lat - lat0) M.
    """
    lon0, lat0 = float(origin_lonlat[0]), float(origin_lonlat[1])
    m, nrad = _meridian_radii(math.radians(lat0))
    x = np.radians(np.asarray(lon, dtype=np.float64) - lon0) * nrad * math.cos(math.radians(lat0))
    y = np.radians(np.asarray(lat, dtype=np.float64) - lat0) * m
    return np.column_stack((x, y))


def _json_num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def write_trees_geojson(
    path: PathLike,
    stem_map: StemMap,
    crs: str | None = None,
    *,
    origin_lonlat: tuple[float, float] | None = None,
    precision: int | None = None,
) -> None:
    """Write the map as a GeoJSON FeatureCollection of Points (RFC 7946), atomically.

    Each tree is a Point feature with ``"id"`` and properties ``diameter`` (m),
    ``diameter_std``, ``std_x``, ``std_y``, ``cov_xy_m2``, ``n_obs``, ``confidence``,
    ``first_time_s``, ``last_time_s``; unknown values are ``null`` (JSON has no NaN).

    Coordinates (:func:`stemmap.io.geo.geojson_coordinates`, docs/outputs.md):

    * a CRS is known (``crs``, ``stem_map.crs``, or ``origin_lonlat`` which makes the map a
      local east-north tangent plane, :func:`stemmap.io.geo.tangent_plane_crs`): RFC 7946,
      geometry in WGS84 longitude/latitude (8 decimals, 1 mm), no ``crs`` member; the native
      coordinates stay in properties ``x``, ``y``.
    * no CRS (a local metric frame): the geometry is in metres and the ``crs`` member names a
      local engineering CRS, which GDAL/QGIS read as ``LOCAL_CS`` metres -- never as degrees.

    The top-level foreign member ``"stemmap"`` records ``frame``, ``crs`` (native), ``units``
    of the geometry and ``origin_lonlat``.

    Parameters
    ----------
    path : str or PathLike
    stem_map : StemMap
    crs : str, optional
        Overrides ``stem_map.crs`` (EPSG code, WKT or PROJ string of the map's x, y).
    origin_lonlat : (float, float), optional
        WGS84 longitude, latitude (degrees) of the map origin; the map's x axis must point east.
        Ignored when a CRS is given.
    precision : int, optional
        Decimal places for the coordinates (default: 8 for degrees, full for metres).
    """
    from stemmap.io.geo import crs_label, geojson_coordinates, tangent_plane_crs

    crs = crs if crs is not None else stem_map.crs
    if crs is None and origin_lonlat is not None:
        crs = crs_label(tangent_plane_crs(origin_lonlat))
    coords, members, meta = geojson_coordinates(stem_map.xy, crs, stem_map.frame)
    meta["origin_lonlat"] = list(origin_lonlat) if origin_lonlat is not None else None
    if precision is not None:
        coords = np.round(coords, precision)
    features = []
    for t, (cx, cy) in zip(stem_map.trees, coords, strict=True):
        row = _tree_row(t)
        props: dict[str, Any] = {
            k: (_json_num(float(v)) if k not in ("id", "n_obs") else int(v))
            for k, v in zip(TREE_CSV_COLUMNS, row, strict=True)
            if k not in ("x", "y")
        }
        props["x"] = float(t.x)
        props["y"] = float(t.y)
        features.append(
            {
                "type": "Feature",
                "id": int(t.id),
                "geometry": {
                    "type": "Point",
                    "coordinates": [_json_num(float(cx)), _json_num(float(cy))],
                },
                "properties": props,
            }
        )
    doc: dict[str, Any] = {"type": "FeatureCollection", **members, "features": features}
    doc["stemmap"] = meta
    if len(coords):
        lo = coords.min(axis=0)
        hi = coords.max(axis=0)
        doc["bbox"] = [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]
    text = json.dumps(doc, allow_nan=False, separators=(",", ":"))
    with atomic_write(path) as fh:
        fh.write(text + "\n")


def read_trees_geojson(path: PathLike) -> StemMap:
    """Read a GeoJSON FeatureCollection of Point trees (as written by
    :func:`write_trees_geojson`) into a :class:`StemMap`.

    Tree positions come from the ``x``, ``y`` properties when present (the metric map frame),
    else from the Point coordinates. ``diameter`` is required in every feature's properties;
    ``id`` falls back to the feature order.

    Raises
    ------
    InputError
        Missing file, invalid JSON, not a FeatureCollection, a non-Point geometry, or a feature
        without a finite diameter.
    """
    p = existing_file(path, "trees GeoJSON")
    try:
        doc = json.loads(read_text(p, "trees GeoJSON", json=True))
    except json.JSONDecodeError as exc:
        raise InputError(f"trees GeoJSON {str(p)!r} is not valid JSON: {exc}.") from exc
    except RecursionError:  # json's C scanner recurses per nested array or object
        raise InputError(
            f"trees GeoJSON {str(p)!r} nests arrays or objects too deeply to be a tree map."
        ) from None
    if not isinstance(doc, Mapping) or doc.get("type") != "FeatureCollection":
        raise InputError(f"trees GeoJSON {str(p)!r} is not a FeatureCollection.")
    feats = doc.get("features")
    if not isinstance(feats, list):
        raise InputError(f"trees GeoJSON {str(p)!r} has no 'features' list.")
    meta = doc.get("stemmap") if isinstance(doc.get("stemmap"), Mapping) else {}
    assert isinstance(meta, Mapping)
    crs_member = doc.get("crs")
    crs = meta.get("crs")
    if crs is None and "crs" not in meta and isinstance(crs_member, Mapping):
        crs = crs_member.get("properties", {}).get("name")
        if isinstance(crs, str) and crs.lstrip().upper().startswith(("LOCAL_CS", "ENGCRS")):
            crs = None  # a local frame, not a CRS
    trees = []
    for k, f in enumerate(feats):
        geom = f.get("geometry") if isinstance(f, Mapping) else None
        if not isinstance(geom, Mapping) or geom.get("type") != "Point":
            raise InputError(f"trees GeoJSON {str(p)!r} feature {k} is not a Point feature.")
        props = f.get("properties") or {}

        def num(name: str, default: float, props: Mapping[str, Any] = props) -> float:
            v = props.get(name)
            return default if v is None else float(v)

        try:
            coords = [float(c) for c in geom["coordinates"][:2]]
            x = num("x", coords[0])
            y = num("y", coords[1])
            d = num("diameter", math.nan)
            sx, sy = num("std_x", math.nan), num("std_y", math.nan)
            cxy = num("cov_xy_m2", num("cov_xy", math.nan))
            tree = Tree(
                id=int(f.get("id", props.get("id", k))),
                x=x,
                y=y,
                diameter=d,
                cov=np.array([[sx * sx, cxy], [cxy, sy * sy]]),
                n_obs=int(props.get("n_obs") or 0),
                first_time=num("first_time_s", num("first_time", math.nan)),
                last_time=num("last_time_s", num("last_time", math.nan)),
                confidence=num("confidence", 1.0),
                diameter_std=num("diameter_std", math.nan),
            )
        except (TypeError, ValueError, KeyError, IndexError) as exc:
            raise InputError(
                f"trees GeoJSON {str(p)!r} feature {k} has a malformed field: {exc}."
            ) from exc
        if not (math.isfinite(tree.x) and math.isfinite(tree.y) and math.isfinite(d)):
            raise InputError(
                f"trees GeoJSON {str(p)!r} feature {k} lacks a finite position or diameter."
            )
        trees.append(tree)
    frame = str(meta.get("frame", "map"))
    return StemMap(tuple(trees), frame=frame, crs=None if crs is None else str(crs))


# --------------------------------------------------------------------------------------------
# observations CSV (stemmap detect)
# --------------------------------------------------------------------------------------------


def write_observations_csv(path: PathLike, obs: StemObservations) -> None:
    """Write one row per observation with columns :data:`OBSERVATION_CSV_COLUMNS`, atomically.

    This is the ``stemmap detect`` output. ``x``, ``y`` are the trunk centre in ``obs.frame``
    (the sensor frame for scan detections), metres; ``diameter`` = 2 r; ``radius_std``,
    ``std_x``, ``std_y`` = sqrt of the (r, r), (x, x), (y, y) covariance entries (``nan``
    where the fit gave no covariance); ``arc_deg`` in degrees, ``width`` the chord width (m).

    Parameters
    ----------
    path : str or PathLike
        Output file; parent folders are created. An empty batch writes the header only.
    obs : StemObservations
        ``index`` is written as ``scan_index`` (the frame's position in the input file).
    """
    var = np.diagonal(obs.covs, axis1=1, axis2=2)  # (K, 3): x, y, r
    with np.errstate(invalid="ignore"):
        std = np.where(var >= 0, np.sqrt(np.abs(var)), np.nan)
    with atomic_write(path) as fh:
        fh.write(",".join(OBSERVATION_CSV_COLUMNS) + "\n")
        for i in range(len(obs)):
            row = (
                int(obs.index[i]),
                obs.times[i],
                obs.centers[i, 0],
                obs.centers[i, 1],
                2.0 * obs.radii[i],
                std[i, 2],
                int(obs.n_points[i]),
                obs.arc_deg[i],
                obs.widths[i],
                obs.quality[i],
                std[i, 0],
                std[i, 1],
            )
            fh.write(fmt_row(row) + "\n")


def read_observations_csv(
    path: PathLike, *, source: str = "", frame: str = "laser"
) -> StemObservations:
    """Read an observations CSV (at least ``scan_index,time,x,y,diameter``).

    Covariances are rebuilt as diag(std_x^2, std_y^2, radius_std^2) (NaN when absent; the
    off-diagonal terms are not stored).

    Raises
    ------
    InputError
        Missing/empty file, missing column, malformed row, NaN/inf in a required column,
        non-integer ``scan_index`` or ``n_points``, negative diameter.
    """
    what = "observations CSV"
    p = existing_file(path, what)
    table = parse_numeric_csv(p, read_text(p, what), _OBS_REQUIRED, OBSERVATION_CSV_COLUMNS, what)
    for c in _OBS_REQUIRED:
        require_finite(p, what, table, c)
    require_integer(p, what, table, "scan_index")
    cols = table.columns
    k = cols["x"].shape[0]
    if np.any(cols["diameter"] < 0):
        i = int(np.argmax(cols["diameter"] < 0))
        raise InputError(
            f"{what} {str(p)!r} line {table.lines[i]}: diameter {cols['diameter'][i]} is negative."
        )
    if "n_points" in cols:
        require_integer(p, what, table, "n_points")

    def col(name: str, default: float) -> FloatArray:
        return cols[name] if name in cols else np.full(k, default)

    covs = np.zeros((k, 3, 3))
    covs[:, 0, 0] = col("std_x", math.nan) ** 2
    covs[:, 1, 1] = col("std_y", math.nan) ** 2
    covs[:, 2, 2] = col("radius_std", math.nan) ** 2
    return StemObservations(
        centers=np.column_stack((cols["x"], cols["y"])),
        radii=0.5 * cols["diameter"],
        covs=covs,
        n_points=col("n_points", 0.0).astype(np.int64),
        arc_deg=col("arc_deg", math.nan),
        widths=col("width", math.nan),
        quality=col("quality", 1.0),
        index=cols["scan_index"].astype(np.int64),
        times=cols["time_s"],
        source=source,
        frame=frame,
    )
