"""Georeferencing of stemmap products: CRS handling (pyproj), GeoJSON coordinates, GeoPackage.

Rules (also in docs/outputs.md, "Coordinate reference systems"):

* A **known CRS** (``--crs EPSG:32633``, a LAS file's own CRS, or a local tangent plane built
  from an origin longitude/latitude by :func:`tangent_plane_crs`): GeoJSON is written per RFC
  7946 -- WGS84 longitude/latitude, no ``crs`` member -- and the native coordinates stay in the
  ``x``, ``y`` properties; the GeoPackage keeps the native CRS.
* **No CRS** (a SLAM map in its odometry frame, a cloud in scanner coordinates): the frame is
  declared *local*. RFC 7946 has no way to say so, so the GeoJSON carries the (pre-RFC, GDAL
  honoured) ``crs`` member naming a local engineering CRS in metres (:func:`local_crs`): GDAL
  and QGIS then read the coordinates as metres in an unknown place, never as degrees. The
  GeoPackage gets the same engineering CRS.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError

__all__ = [
    "GeoLayer",
    "array_fields",
    "crs_label",
    "georeference_features",
    "las_crs",
    "local_crs",
    "parse_crs",
    "tangent_plane_crs",
    "to_lonlat",
    "write_gpkg",
    "write_map_gpkg",
]

#: Decimal places of a WGS84 degree in GeoJSON: 1e-8 deg = 1.1 mm (RFC 7946 §11.2 suggests 6-7;
#: we keep millimetres so that a round trip does not blur a stem position).
LONLAT_DECIMALS = 8


def _crs_module() -> Any:
    import pyproj

    return pyproj


def parse_crs(text: str, *, what: str = "--crs", allow_geographic: bool = False) -> Any:
    """A :class:`pyproj.CRS` from an EPSG code, WKT, PROJ string or authority name.

    Raises
    ------
    ConfigError
        When pyproj does not know it, or it is geographic (stem maps and clouds are metric: a
        map in degrees cannot be drawn to scale, pass the projected CRS, e.g. a UTM zone).
    """
    pyproj = _crs_module()
    try:
        crs = pyproj.CRS.from_user_input(text)
    except pyproj.exceptions.CRSError as exc:
        raise ConfigError(
            f"{what} {text!r} is not a CRS pyproj knows ({exc}); give e.g. EPSG:32633."
        ) from exc
    if crs.is_geographic and not allow_geographic:
        raise ConfigError(
            f"{what} {text!r} is geographic (degrees); stemmap coordinates are metres: "
            "give the projected CRS they are in (e.g. the UTM zone, EPSG:326xx)."
        )
    return crs


def crs_label(crs: Any) -> str:
    """``AUTHORITY:CODE`` when the CRS has one, else its WKT2 text."""
    auth = crs.to_authority(min_confidence=90)
    return f"{auth[0]}:{auth[1]}" if auth else str(crs.to_wkt())


def local_crs(frame: str) -> Any:
    """A local engineering CRS (metres, x east-like, y north-like) named after ``frame``.

    Declares coordinates that are metric but not placed on the Earth (a SLAM map in its
    odometry frame). GDAL writes it as ``LOCAL_CS`` (GeoJSON ``crs`` member, GeoPackage
    ``gpkg_spatial_ref_sys``).
    """
    pyproj = _crs_module()
    name = f"stemmap local frame '{frame}' (metres, not georeferenced)".replace('"', "'")
    return pyproj.CRS.from_wkt(
        f'ENGCRS["{name}",EDATUM["{frame} origin"],CS[Cartesian,2],'
        'AXIS["x",east,ORDER[1],LENGTHUNIT["metre",1]],'
        'AXIS["y",north,ORDER[2],LENGTHUNIT["metre",1]]]'
    )


def tangent_plane_crs(origin_lonlat: tuple[float, float]) -> Any:
    """Transverse Mercator centred on ``origin_lonlat`` (WGS84, scale 1, metres).

    The CRS of a local east-north map whose origin's longitude/latitude is known: within
    1 km of the origin it differs from a true tangent plane by < 1 cm (scale error
    ~ d^2 / 2R^2).
    """
    lon0, lat0 = float(origin_lonlat[0]), float(origin_lonlat[1])
    if not (-180.0 <= lon0 <= 180.0 and -90.0 < lat0 < 90.0):
        raise InputError(
            f"origin_lonlat must be (longitude, latitude) in degrees, got ({lon0}, {lat0})."
        )
    return _crs_module().CRS.from_proj4(
        f"+proj=tmerc +lat_0={lat0!r} +lon_0={lon0!r} +k=1 +x_0=0 +y_0=0 +datum=WGS84 "
        "+units=m +no_defs"
    )


def to_lonlat(xy: ArrayLike, crs: Any) -> NDArray[np.float64]:
    """Native coordinates (N, 2) in ``crs`` to WGS84 (longitude, latitude) degrees, (N, 2)."""
    pyproj = _crs_module()
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    tr = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(p[:, 0], p[:, 1])
    return np.column_stack((np.asarray(lon, np.float64), np.asarray(lat, np.float64)))


def las_crs(path: str | os.PathLike[str]) -> str | None:
    """The CRS a LAS/LAZ header declares (GeoTIFF keys or OGC WKT VLR), or None.

    Returned as ``EPSG:code`` when pyproj finds one, else as WKT. Files that are not LAS or
    whose header has no CRS give None.
    """
    p = Path(path)
    if p.suffix.lower() not in (".las", ".laz"):
        return None
    import laspy

    from stemmap.io.clouds import check_las_file

    check_las_file(p)  # missing, empty, not LAS, a damaged VLR count: before laspy reads it
    try:
        with laspy.open(p) as fh:
            crs = fh.header.parse_crs()
    except Exception as exc:  # laspy raises many kinds on a bad CRS VLR
        raise InputError(f"LAS file {str(p)!r} has an unreadable CRS record: {exc}.") from exc
    return None if crs is None else crs_label(crs)


# --------------------------------------------------------------------------------------------
# GeoJSON coordinates
# --------------------------------------------------------------------------------------------


def geojson_coordinates(
    xy: ArrayLike, crs: str | None, frame: str
) -> tuple[NDArray[np.float64], dict[str, Any], dict[str, Any]]:
    """Coordinates, top-level members and ``stemmap`` metadata for a GeoJSON of ``xy``.

    Returns
    -------
    coords : ndarray (N, 2)
        WGS84 lon/lat rounded to :data:`LONLAT_DECIMALS` when ``crs`` is known, else ``xy``.
    members : dict
        ``{"crs": ...}`` naming the local engineering CRS when ``crs`` is None, else empty.
    meta : dict
        The ``stemmap`` foreign member: ``frame``, ``crs`` (native), ``units`` of the geometry,
        ``x_y_properties`` (what the ``x``, ``y`` properties hold).
    """
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if crs is None:
        wkt = local_crs(frame).to_wkt(version="WKT1_GDAL")
        return (
            p,
            {"crs": {"type": "name", "properties": {"name": wkt}}},
            {
                "frame": frame,
                "crs": None,
                "units": "m",
                "geometry": "local metres (declared by the crs member as a local "
                "engineering CRS; not WGS84)",
                "x_y_properties": f"metres in the local frame '{frame}'",
            },
        )
    c = parse_crs(crs, what="CRS", allow_geographic=True)
    ll = np.round(to_lonlat(p, c), LONLAT_DECIMALS)
    return (
        ll,
        {},
        {
            "frame": frame,
            "crs": crs_label(c),
            "units": "degrees",
            "geometry": "WGS84 longitude, latitude (RFC 7946)",
            "x_y_properties": f"metres in {crs_label(c)}",
        },
    )


def georeference_features(
    doc: dict[str, Any], xy: ArrayLike, crs: str | None, frame: str
) -> dict[str, Any]:
    """Put a FeatureCollection of Points (one per row of ``xy``, native coordinates) on the
    Earth per the module rules: geometry in WGS84 lon/lat (known CRS) or declared local
    metres (no CRS); native ``x``, ``y`` added to the properties; ``stemmap`` metadata and a
    ``bbox`` set. Returns the same (modified) dict."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    coords, members, meta = geojson_coordinates(p, crs, frame)
    for f, (cx, cy), (x, y) in zip(doc["features"], coords, p, strict=True):
        f["geometry"] = {"type": "Point", "coordinates": [float(cx), float(cy)]}
        f.setdefault("properties", {}).update(x=float(x), y=float(y))
    doc.pop("crs", None)
    doc.update(members)
    doc["stemmap"] = meta
    if len(coords):
        lo, hi = coords.min(axis=0), coords.max(axis=0)
        doc["bbox"] = [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]
    return doc


# --------------------------------------------------------------------------------------------
# GeoPackage
# --------------------------------------------------------------------------------------------


@dataclass
class GeoLayer:
    """One GeoPackage layer: Points (``xy`` shape (N, 2)) or one LineString (``line=True``).

    ``fields`` maps a column name to an array of length N (points) or 1 (line): float, int or
    str; NaN floats become NULL.
    """

    name: str
    xy: NDArray[np.float64]
    fields: Mapping[str, Sequence[Any] | NDArray[Any]] = field(default_factory=dict)
    line: bool = False


def _wkb_points(xy: NDArray[np.float64]) -> NDArray[np.object_]:
    out = np.empty(len(xy), dtype=object)
    for k, (x, y) in enumerate(xy):
        out[k] = b"\x01\x01\x00\x00\x00" + np.array([x, y], "<f8").tobytes()
    return out


def _wkb_line(xy: NDArray[np.float64]) -> NDArray[np.object_]:
    out = np.empty(1, dtype=object)
    n = np.array([len(xy)], "<u4").tobytes()
    out[0] = b"\x01\x02\x00\x00\x00" + n + np.ascontiguousarray(xy, "<f8").tobytes()
    return out


def _field_array(values: Sequence[Any] | NDArray[Any]) -> NDArray[Any]:
    """A field column for pyogrio: text as an object array of str (GPKG TEXT), else as is."""
    a = np.asarray(values)
    return a.astype(object) if a.dtype.kind in "US" else a


def write_gpkg(
    path: str | os.PathLike[str], layers: Sequence[GeoLayer], crs: str | None, frame: str
) -> None:
    """Write ``layers`` into one GeoPackage in the native ``crs`` (local engineering CRS named
    after ``frame`` when None), atomically (temporary file beside it, then renamed).
    """
    from pyogrio.raw import write as ogr_write

    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    c = local_crs(frame) if crs is None else parse_crs(crs, what="CRS", allow_geographic=True)
    wkt = c.to_wkt()
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp.gpkg")
    tmp.unlink(missing_ok=True)
    try:
        for k, lay in enumerate(layers):
            xy = np.asarray(lay.xy, dtype=np.float64).reshape(-1, 2)
            if not np.all(np.isfinite(xy)):
                xy = xy[np.all(np.isfinite(xy), axis=1)]
            geom = _wkb_line(xy) if lay.line else _wkb_points(xy)
            names = list(lay.fields)
            data = [_field_array(lay.fields[n]) for n in names]
            ogr_write(
                str(tmp),
                geometry=geom,
                field_data=data,
                fields=names,
                layer=lay.name,
                driver="GPKG",
                geometry_type="LineString" if lay.line else "Point",
                crs=wkt,
                append=k > 0,
            )
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def array_fields(
    obj: Any, n: int, skip: Sequence[str] = (), constants: Sequence[str] = ()
) -> dict[str, NDArray[Any]]:
    """The per-row attributes of a dataclass (e.g. a :class:`~stemmap.cloud.stems.CloudStems`)
    as GeoPackage fields, in declaration order.

    * 1-D arrays of length ``n``: numeric (int, float, bool) or text (str / object arrays,
      written as GPKG TEXT);
    * (n, 2, 2) x/y covariance arrays: three fields ``cov_xx``, ``cov_xy``, ``cov_yy`` (m^2)
      for ``xy_cov`` or ``cov``, ``NAME_cov_xx``... for ``NAME_cov``;
    * the scalar attributes named in ``constants`` (e.g. ``method``), repeated on every row.
    """
    import dataclasses

    out: dict[str, NDArray[Any]] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if f.name in skip:
            continue
        if f.name in constants:
            out[f.name] = np.full(n, v, dtype=object if isinstance(v, str) else None)
            continue
        if not isinstance(v, np.ndarray) or v.shape[:1] != (n,):
            continue
        if v.ndim == 1 and v.dtype.kind in "biufUO":
            out[f.name] = v.astype(object) if v.dtype.kind in "UO" else v
        elif v.ndim == 3 and v.shape[1:] == (2, 2) and v.dtype.kind == "f":
            stem = f.name.replace("cov", "").strip("_")
            pre = "cov_" if stem in ("", "xy") else f"{stem}_cov_"
            out[pre + "xx"] = v[:, 0, 0]
            out[pre + "xy"] = v[:, 0, 1]
            out[pre + "yy"] = v[:, 1, 1]
    return out


def write_map_gpkg(
    path: str | os.PathLike[str],
    stem_map: Any,
    trajectory: Any = None,
    crs: str | None = None,
    extra_layers: Sequence[GeoLayer] = (),
) -> None:
    """A GeoPackage of a stem map in its native CRS: layer ``trees`` (Points, the trees CSV
    columns as fields) and, with a trajectory, ``trajectory`` (one LineString with its start
    and end time) and ``poses`` (Points: time_s, theta); then ``extra_layers`` (e.g. the
    GNSS-frame track of ``stemmap map --gnss``).

    ``crs`` overrides ``stem_map.crs``; neither means a local engineering CRS (module doc).
    """
    from stemmap.io.maps import TREE_CSV_COLUMNS, tree_rows

    rows = tree_rows(stem_map)
    cols = {
        c: np.array([r[k] for r in rows], dtype=np.int64 if c in ("id", "n_obs") else float)
        for k, c in enumerate(TREE_CSV_COLUMNS)
    }
    layers = [GeoLayer("trees", stem_map.xy, cols)]
    if trajectory is not None and len(trajectory):
        t = np.asarray(trajectory.times, dtype=np.float64)
        layers.append(
            GeoLayer(
                "trajectory",
                trajectory.xy,
                {"t_start_s": t[:1], "t_end_s": t[-1:], "n_poses": np.array([len(t)])},
                line=True,
            )
        )
        layers.append(
            GeoLayer("poses", trajectory.xy, {"time_s": t, "theta": trajectory.poses[:, 2]})
        )
    layers += list(extra_layers)
    write_gpkg(path, layers, crs if crs is not None else stem_map.crs, stem_map.frame)
