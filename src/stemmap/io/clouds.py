"""Point-cloud readers: LAS/LAZ (laspy, chunked), PLY (our own), PCD (pypcd4), XYZ text, ROS bags.

Every reader returns a :class:`stemmap.types.PointCloud` (xyz in metres, float64) and fails with
:class:`stemmap.errors.InputError` naming the file and the problem (missing, empty, truncated,
wrong header, no x/y/z fields).

LAS/LAZ files can be streamed with :func:`iter_las_chunks` so that a 20-million-point cloud never
has to sit in memory at once; :func:`read_cloud` reads the whole file.

PLY is read by our own parser (:mod:`stemmap.io._ply`; the GPL-3 ``plyfile`` package cannot be
a dependency of an MIT library). PCD goes through ``pypcd4``, imported lazily so the rest of
stemmap works without it; a missing parser is reported as an InputError that names the package
to install.
"""

from __future__ import annotations

import io
import logging
import math
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError
from stemmap.types import PointCloud

if TYPE_CHECKING:
    from stemmap.io.conventions import CloudConvention

__all__ = [
    "CLOUD_EXTENSIONS",
    "check_las_file",
    "count_points",
    "iter_cloud_chunks",
    "iter_las_chunks",
    "point_fields",
    "read_cloud",
    "read_las",
    "read_pcd",
    "read_plot_cloud",
    "read_ply",
    "read_xyz",
]

log = logging.getLogger(__name__)

#: File extensions :func:`read_cloud` understands (lower case, with the dot).
CLOUD_EXTENSIONS = (".las", ".laz", ".ply", ".pcd", ".xyz", ".txt", ".csv", ".pts")
_BAG_EXTENSIONS = (".bag", ".db3", ".mcap")

PathLike = str | os.PathLike[str]


def _check_file(path: PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(f"point-cloud file {str(p)!r} does not exist.")
    if p.is_file() and p.stat().st_size == 0:
        raise InputError(f"point-cloud file {str(p)!r} is empty (0 bytes).")
    return p


def _float32_warning(xyz: NDArray[Any], path: Path, stored_float32: bool = False) -> None:
    """Warn when float32 coordinates are too coarse for stems where the cloud lies.

    A float32 holds 24 bits of mantissa: at a UTM easting of 500 000 m its step is 3 cm, at
    a northing of 6 200 000 m 50 cm (a PLY or PCD written without the exporter's global
    shift). The points are then snapped to that grid before stemmap sees them; nothing
    downstream can recover the lost digits (docs/algorithms/cloud.md, "Robustness to user
    exports"); the stem detector measures the step on the points themselves and refuses a
    cloud coarser than 2 cm (:mod:`stemmap.cloud.quantisation`). ``stored_float32``: the
    file stored them as float32 (a reader that already promoted them to float64 says so)."""
    if not (stored_float32 or xyz.dtype == np.float32) or xyz.size == 0:
        return
    finite = np.abs(xyz[np.isfinite(xyz)])
    if finite.size == 0:
        return
    big = float(finite.max())
    # float32 step at |big| (24-bit mantissa), computed in float64: NaN/inf coordinates (dropped
    # later) and values a float32 cannot hold must not raise an overflow here
    step = math.ldexp(1.0, math.frexp(big)[1] - 24)
    if step > 1e-3:
        from stemmap.cloud.quantisation import MAX_COORDINATE_STEP

        log.warning(
            "%s: coordinates are float32 and reach %.0f m, where float32 steps are %.3f m: "
            "the digits below that step are lost (`stemmap stems` refuses steps above "
            "%.2f m near the stems). Export in float64 (or LAS/LAZ), or with the "
            "coordinates shifted near 0.",
            path,
            big,
            step,
            MAX_COORDINATE_STEP,
        )


def _finish(xyz: NDArray[Any], path: Path, fields: dict[str, NDArray[Any]]) -> PointCloud:
    _float32_warning(xyz, path)
    xyz = np.asarray(xyz, dtype=np.float64)
    finite_xyz = np.isfinite(xyz)
    if finite_xyz.all():  # the usual case; a flat all() is ~8x faster than all(axis=1)
        return PointCloud(xyz, frame=path.stem, fields=fields)
    finite = finite_xyz[:, 0] & finite_xyz[:, 1] & finite_xyz[:, 2]
    if not np.all(finite):
        n_bad = int((~finite).sum())
        log.info("%s: dropping %d points with NaN/inf coordinates", path, n_bad)
        xyz = xyz[finite]
        fields = {k: v[finite] for k, v in fields.items()}
    return PointCloud(xyz, frame=path.stem, fields=fields)


# --------------------------------------------------------------------------------------------
# LAS / LAZ
# --------------------------------------------------------------------------------------------

_LAS_FIELDS = ("intensity", "return_number", "classification", "gps_time")


def _las_fields(points: Any, names: tuple[str, ...]) -> dict[str, NDArray[Any]]:
    present = set(points.point_format.dimension_names)
    return {k: np.asarray(points[k]) for k in names if k in present}


#: Smallest LAS VLR: its 54-byte header with an empty payload (LAS 1.4 R15 §2.5).
_VLR_HEADER_BYTES = 54


def _check_las_layout(p: Path) -> None:
    """InputError if the fixed LAS header cannot describe this file (before laspy parses it).

    laspy trusts ``number_of_vlrs``: a damaged count (e.g. 2^32 - 1) made it loop for minutes
    reading empty records (found by benchmarks/fuzz.py). The VLRs lie between the header and
    the point data, so ``header_size + 54 * number_of_vlrs <= offset_to_point_data <= size``.
    """
    import struct

    try:
        with p.open("rb") as fh:
            head = fh.read(104)
    except OSError as exc:
        raise InputError(f"cannot read {str(p)!r}: {exc}.") from exc
    if head[:4] != b"LASF":
        raise InputError(
            f"{str(p)!r} is not a LAS/LAZ file: it does not start with the 'LASF' signature "
            f"(it starts with {head[:4]!r})."
        )
    if len(head) < 104:
        raise InputError(
            f"{str(p)!r} is truncated: its LAS header stops after {len(head)} bytes "
            "(at least 104 are needed)."
        )
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    size = p.stat().st_size
    if not (header_size <= offset <= size) or header_size + _VLR_HEADER_BYTES * n_vlrs > offset:
        raise InputError(
            f"{str(p)!r}: the LAS header is corrupt: header size {header_size} B, "
            f"{n_vlrs} VLR(s) and point data at byte {offset} do not fit a {size}-byte file."
        )


def check_las_file(path: PathLike) -> Path:
    """InputError unless ``path`` exists, is not empty and starts with a LAS header that fits
    the file (:func:`_check_las_layout`); call it before handing the file to laspy, which
    loops for minutes on a damaged VLR count and reports a missing or empty file as a
    parse error."""
    p = _check_file(path)
    _check_las_layout(p)
    return p


def _check_las_header(p: Path, header: Any) -> None:
    """InputError on a LAS header that contradicts itself or the file (issue 13).

    * every scale factor must be finite and non-zero (a zero scale maps every point onto the
      offset: a silently collapsed cloud);
    * an uncompressed file must hold exactly ``point_count`` records between the point-data
      offset and the first extended VLR (or the end of the file). A header announcing fewer
      points than the file holds would silently read part of the cloud; fewer bytes than it
      announces is a truncated file. LAZ is compressed (no size rule); its reader reports a
      short file.
    """
    scales = np.asarray(header.scales, dtype=np.float64)
    if scales.shape != (3,) or not np.all(np.isfinite(scales)) or np.any(scales == 0):
        raise InputError(
            f"{str(p)!r}: the LAS header's scale factors are {scales.tolist()}; each must be a "
            "finite non-zero number (typically 0.001 or 0.01)."
        )
    if header.are_points_compressed:
        return
    rec = int(header.point_format.size)
    start = int(header.offset_to_point_data)
    size = p.stat().st_size
    end = size
    evlr = int(getattr(header, "start_of_first_evlr", 0) or 0)
    if int(getattr(header, "number_of_evlrs", 0) or 0) > 0 and start < evlr <= size:
        end = evlr
    if rec <= 0 or start > size:
        raise InputError(
            f"{str(p)!r}: the LAS header puts the point data at byte {start} of a {size}-byte "
            f"file (record length {rec}); the header is corrupt."
        )
    held = (end - start) // rec
    expected = int(header.point_count)
    if held > expected:
        raise InputError(
            f"{str(p)!r}: the LAS header announces {expected} points but the file holds "
            f"{held} point records ({end - start} bytes of {rec}-byte records); the header's "
            "point count is wrong, so part of the cloud would be ignored. Repair the header "
            "(e.g. `las2las` / laspy) or regenerate the file."
        )
    if held < expected:
        raise InputError(
            f"{str(p)!r} is truncated: its header announces {expected} points but the file "
            f"holds only {held} ({size} bytes)."
        )


def iter_las_chunks(
    path: PathLike, chunk_size: int = 2_000_000, *, fields: tuple[str, ...] = ()
) -> Iterator[PointCloud]:
    """Stream a LAS/LAZ file as point clouds of at most ``chunk_size`` points.

    Parameters
    ----------
    path : str or path-like
        A ``.las`` or ``.laz`` file (LAZ via the ``lazrs`` backend of laspy).
    chunk_size : int, > 0
        Points per chunk; memory use is bounded by a few times ``chunk_size * 24`` bytes.
    fields : tuple of str
        Extra LAS dimensions to carry along (e.g. ``("intensity",)``); absent ones are skipped.

    Yields
    ------
    PointCloud
        Scaled coordinates (metres) of each chunk, in file order.

    Raises
    ------
    InputError
        If the file is missing, is not LAS/LAZ, or is truncated (fewer points than its header
        announces).
    """
    import laspy

    p = _check_file(path)
    if chunk_size <= 0:
        raise InputError(f"chunk_size must be > 0, got {chunk_size}.")
    _check_las_layout(p)
    try:
        reader = laspy.open(p)
    except Exception as exc:
        raise InputError(f"{str(p)!r} is not a readable LAS/LAZ file: {exc}") from exc
    with reader:
        _check_las_header(p, reader.header)
        expected = int(reader.header.point_count)
        seen = 0
        try:
            for chunk in reader.chunk_iterator(chunk_size):
                n = len(chunk)
                if n == 0:
                    break
                xyz = np.column_stack((chunk.x, chunk.y, chunk.z))
                seen += n
                yield _finish(xyz, p, _las_fields(chunk, fields))
        except InputError:
            raise
        except Exception as exc:
            raise InputError(
                f"{str(p)!r} is truncated or corrupt: reading failed after {seen} of {expected} "
                f"points ({exc})."
            ) from exc
        if seen < expected:
            raise InputError(
                f"{str(p)!r} is truncated: its header announces {expected} points but only "
                f"{seen} could be read."
            )


def read_las(path: PathLike, *, fields: tuple[str, ...] = _LAS_FIELDS) -> PointCloud:
    """Read a whole LAS/LAZ file (see :func:`iter_las_chunks` for streaming).

    Extra dimensions present in the file and named in ``fields`` (default: intensity,
    return_number, classification, gps_time) are kept in ``PointCloud.fields``.
    """
    from stemmap.io._budget import check_read_budget, human_bytes

    all_fields = tuple(fields)
    n = count_points(path)  # header checks; the count is what the chunks will add up to
    if n:
        # the whole cloud is held as float64 xyz + one 8-byte column per field, twice while
        # the chunks are concatenated (a LAZ file is ~10x smaller than that)
        need = 2 * n * (24 + 8 * len(all_fields))
        check_read_budget(
            need,
            path,
            "point cloud",
            f"its header announces {n:,} points, ~{human_bytes(need)} to load whole (a "
            "command that streams LAS, `stemmap stems`, does not hold it)",
        )
    parts = list(iter_las_chunks(path, chunk_size=5_000_000, fields=all_fields))
    p = Path(path)
    if not parts:
        raise InputError(f"{str(p)!r} holds no points.")
    xyz = np.concatenate([c.xyz for c in parts])
    out_fields = {k: np.concatenate([c.fields[k] for c in parts]) for k in parts[0].fields}
    return PointCloud(xyz, frame=p.stem, fields=out_fields)


# --------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------


def read_ply(path: PathLike) -> PointCloud:
    """Read the ``vertex`` element of a PLY file (ascii, binary little or big endian).

    Our own reader of the PLY format (Turk 1994; see :mod:`stemmap.io._ply`): binary vertex
    blocks are one structured dtype over the memory-mapped file, ascii blocks one
    ``np.loadtxt``; elements before
    the vertices (with list properties such as faces, too) are skipped, elements after them are
    not read. Scalar vertex properties other than x, y, z are kept as fields in their declared
    type (e.g. intensity, red/green/blue); list properties of the vertex element are dropped.

    Raises
    ------
    InputError
        Missing or empty file, malformed header (the message names the line), unsupported
        format or type, no vertex element, no x/y/z, no vertices, a body shorter than its
        header announces.
    """
    from stemmap.io._ply import read_ply_vertices

    p = _check_file(path)
    xyz, fields, header = read_ply_vertices(p)
    vertex = header.element("vertex")
    assert vertex is not None  # read_ply_vertices refuses files without one
    if xyz is None:
        have = [q.name for q in vertex.properties if not q.is_list]
        missing = [c for c in ("x", "y", "z") if c not in have]
        raise InputError(
            f"PLY file {str(p)!r} vertex element lacks the coordinate(s) "
            f"{', '.join(missing)}; it has {', '.join(have) or 'none'}."
        )
    if vertex.count == 0:
        raise InputError(f"PLY file {str(p)!r} holds no vertices.")
    f4 = any(q.name in ("x", "y", "z") and q.dtype == "f4" for q in vertex.properties)
    _float32_warning(xyz, p, stored_float32=f4)
    return _finish(xyz, p, fields)


# --------------------------------------------------------------------------------------------
# PCD
# --------------------------------------------------------------------------------------------


def _check_pcd_size(p: Path) -> None:
    """Reject a ``DATA binary`` PCD whose body is shorter than its header announces, and a
    ``DATA ascii`` one too short to hold its announced points (two bytes a value).

    (The parser would otherwise return garbage or fewer points without complaint.)
    """
    header: dict[str, list[str]] = {}
    with p.open("rb") as fh:
        offset = 0
        for _ in range(64):
            raw = fh.readline()
            if not raw:
                break
            offset += len(raw)
            line = raw.decode("ascii", errors="replace").strip()
            if not line or line.startswith("#"):
                continue
            key, *vals = line.split()
            header[key.upper()] = vals
            if key.upper() == "DATA":
                break
    if "DATA" not in header:
        raise InputError(f"{str(p)!r} is not a PCD file: no DATA line in its header.")
    data = header["DATA"][:1]
    if data not in (["binary"], ["ascii"]):
        return
    try:
        sizes = [int(v) for v in header["SIZE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(sizes))]
        n = int(header["POINTS"][0])
    except (KeyError, ValueError, IndexError) as exc:
        raise InputError(f"PCD file {str(p)!r} has a malformed header: {exc}.") from exc
    if data == ["binary"]:
        need = n * sum(s * c for s, c in zip(sizes, counts, strict=False))
    else:  # ascii: >= one character and a separator per value
        need = n * 2 * sum(counts)
    have = p.stat().st_size - offset
    if have < need:
        raise InputError(
            f"PCD file {str(p)!r} is truncated: its header announces {n} points "
            f"({need} bytes{' at least' if data == ['ascii'] else ''}) but only {have} bytes "
            "follow the header."
        )


def read_pcd(path: PathLike) -> PointCloud:
    """Read a PCL ``.pcd`` file (DATA ascii, binary or binary_compressed).

    Uses the ``pypcd4`` package. Scalar fields other than x, y, z are kept as fields.
    """
    p = _check_file(path)
    try:
        from pypcd4 import PointCloud as PcdCloud
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise InputError(
            f"reading {str(p)!r} needs the 'pypcd4' package; install it with `pip install pypcd4`."
        ) from exc
    _check_pcd_size(p)
    try:
        pc = PcdCloud.from_path(str(p))
        names = tuple(pc.fields)
        arr = pc.numpy()
    except Exception as exc:
        raise InputError(f"{str(p)!r} is not a readable PCD file (truncated?): {exc}") from exc
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise InputError(
            f"PCD file {str(p)!r} lacks the field(s) {', '.join(missing)}; "
            f"it has {', '.join(names)}."
        )
    arr = np.asarray(arr)
    if arr.ndim != 2 or arr.shape[0] == 0:
        raise InputError(f"PCD file {str(p)!r} holds no points.")
    points = getattr(pc, "points", None)  # the header's POINTS
    announced = points if isinstance(points, int) else arr.shape[0]
    if arr.shape[0] < announced:
        raise InputError(
            f"PCD file {str(p)!r} is truncated: its header announces {announced} points but "
            f"only {arr.shape[0]} could be read."
        )
    idx = {n: i for i, n in enumerate(names)}
    xyz = arr[:, [idx["x"], idx["y"], idx["z"]]]
    fields = {n: arr[:, i] for n, i in idx.items() if n not in ("x", "y", "z") and i < arr.shape[1]}
    return _finish(xyz, p, fields)


# --------------------------------------------------------------------------------------------
# XYZ text
# --------------------------------------------------------------------------------------------


#: Most columns a text point file may have (x y z and fields such as intensity, RGB, normals,
#: time: real exports have 3-20). Each extra column becomes a field array.
_MAX_XYZ_COLUMNS = 256


def read_xyz(path: PathLike) -> PointCloud:
    """Read a text file of points, one per line: ``x y z [more columns]``.

    Columns may be separated by whitespace, commas or semicolons; lines starting with ``#`` and
    a single non-numeric header line are skipped. Extra columns become fields ``col3``, ``col4``...
    Semicolon-separated files may use decimal commas (``12,5;3,25;1,3``, as spreadsheet and
    CloudCompare exports in many locales write them): with ``;`` as the separator a comma can
    only be a decimal sign.
    """
    from stemmap.io._budget import check_text_budget

    p = _check_file(path)
    # numpy's C parser: float64 per number (~1 B per byte of text), plus its row buffers
    check_text_budget(p, "point file", per_byte=4.0, per_line=0.0)
    try:
        with p.open("r", encoding="utf-8", errors="strict") as fh:
            lines: list[str] = []
            for line in fh:
                if line.strip() and not line.lstrip().startswith("#"):
                    lines.append(line)
                    if len(lines) == 2:
                        break
    except UnicodeDecodeError as exc:
        raise InputError(f"{str(p)!r} is not a text point file (binary content).") from exc
    if not lines:
        raise InputError(f"{str(p)!r} holds no points.")
    first = lines[0]
    delim: str | None = None
    for d in (";", ","):
        if d in first:
            delim = d
            break
    decimal_comma = delim == ";" and any("," in ln for ln in lines)
    if decimal_comma:
        first = first.replace(",", ".")
    tokens = [t for t in (first.split(delim) if delim else first.split()) if t.strip()]
    if len(tokens) > _MAX_XYZ_COLUMNS:
        raise InputError(
            f"{str(p)!r} has {len(tokens):,} columns on its first line; a point line holds "
            f"x y z and a few fields (at most {_MAX_XYZ_COLUMNS}): is it the right file?"
        )
    try:
        [float(t) for t in tokens]
        skip = 0
    except ValueError:
        skip = 1
    try:
        with warnings.catch_warnings():  # numpy's "input contained no data": reported below
            warnings.simplefilter("ignore", UserWarning)
            src: Any = p
            if decimal_comma:
                src = io.StringIO(p.read_text(encoding="utf-8").replace(",", "."))
            arr = np.loadtxt(src, delimiter=delim, comments="#", skiprows=skip, ndmin=2)
    except ValueError as exc:
        raise InputError(
            f"{str(p)!r} has a malformed line (every line needs the same number of numeric "
            f"columns, at least x y z): {exc}"
        ) from exc
    if arr.shape[0] == 0:
        raise InputError(f"{str(p)!r} holds no points.")
    if arr.shape[1] < 3:
        raise InputError(f"{str(p)!r} has {arr.shape[1]} column(s); need at least x y z.")
    fields = {f"col{i}": arr[:, i] for i in range(3, arr.shape[1])}
    return _finish(arr[:, :3], p, fields)


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------


def _read_bag(path: Path, topic: str | None) -> PointCloud:
    import importlib

    try:
        rosbag = importlib.import_module("stemmap.io.rosbag")
    except ImportError as exc:
        raise InputError(
            f"reading the bag {str(path)!r} needs stemmap.io.rosbag, which is not available."
        ) from exc
    reader = getattr(rosbag, "read_pointclouds", None)
    if reader is None:
        raise InputError(
            f"reading the bag {str(path)!r} needs stemmap.io.rosbag.read_pointclouds, which is "
            "not available in this version."
        )
    clouds = list(reader(path, topic=topic))
    if not clouds:
        raise InputError(f"bag {str(path)!r} holds no sensor_msgs/PointCloud2 messages.")
    xyz = np.concatenate([c.xyz for c in clouds])
    return PointCloud(xyz, time=clouds[0].time, frame=clouds[0].frame)


def read_cloud(
    path: PathLike, *, topic: str | None = None, convention: CloudConvention | None = None
) -> PointCloud:
    """Read a point cloud, choosing the reader from the file extension.

    ``.las``/``.laz`` -> :func:`read_las`; ``.ply`` -> :func:`read_ply`; ``.pcd`` ->
    :func:`read_pcd`; ``.xyz``/``.txt``/``.csv``/``.pts`` -> :func:`read_xyz`; ROS bags
    (``.bag``, ``.db3``, ``.mcap`` or a ROS2 bag folder) -> every PointCloud2 message of ``topic``
    (or of all topics) stacked in the sensor frame (no motion compensation). ``convention``:
    the file's units and up axis, converted to metres, z up
    (:class:`stemmap.io.conventions.CloudConvention`).

    Raises
    ------
    InputError
        Unknown extension, missing/empty/truncated file, or no x/y/z coordinates.
    """
    return _converted(_read_any(Path(path), topic), convention)


def _read_any(p: Path, topic: str | None) -> PointCloud:
    ext = p.suffix.lower()
    if p.is_dir() or ext in _BAG_EXTENSIONS:
        if not p.exists():
            raise InputError(f"bag {str(p)!r} does not exist.")
        return _read_bag(p, topic)
    if ext in (".las", ".laz"):
        return read_las(p)
    if ext == ".ply":
        return read_ply(p)
    if ext == ".pcd":
        return read_pcd(p)
    if ext in (".xyz", ".txt", ".csv", ".pts"):
        return read_xyz(p)
    raise InputError(
        f"cannot read {str(p)!r}: unknown point-cloud extension {ext!r}; "
        f"use one of {', '.join(CLOUD_EXTENSIONS + _BAG_EXTENSIONS)}."
    )


def count_points(path: PathLike) -> int | None:
    """Number of points announced by a LAS/LAZ or PLY header (None for other formats)."""
    p = Path(path)
    if p.suffix.lower() == ".ply":
        from stemmap.io._ply import read_ply_header

        _check_file(p)
        with p.open("rb") as fh:
            vertex = read_ply_header(fh, p).element("vertex")
        return None if vertex is None else vertex.count
    if p.suffix.lower() not in (".las", ".laz"):
        return None
    import laspy

    _check_file(p)
    _check_las_layout(p)
    try:
        reader = laspy.open(p)
    except Exception as exc:
        raise InputError(f"{str(p)!r} is not a readable LAS/LAZ file: {exc}") from exc
    with reader:
        _check_las_header(p, reader.header)  # a count the file cannot hold is damage
        return int(reader.header.point_count)


def point_fields(path: PathLike) -> tuple[str, ...] | None:
    """Names of the per-point fields a LAS/LAZ or PLY header declares (None for other formats,
    whose fields are known only after reading). LAS names are laspy's dimension names
    (``gps_time``, ``intensity``, extra bytes...); PLY names are the vertex's scalar properties.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".ply":
        from stemmap.io._ply import read_ply_header

        _check_file(p)
        with p.open("rb") as fh:
            vertex = read_ply_header(fh, p).element("vertex")
        return () if vertex is None else tuple(q.name for q in vertex.properties if not q.is_list)
    if ext not in (".las", ".laz"):
        return None
    import laspy

    _check_file(p)
    _check_las_layout(p)
    try:
        with laspy.open(p) as reader:
            return tuple(reader.header.point_format.dimension_names)
    except Exception as exc:
        raise InputError(f"{str(p)!r} is not a readable LAS/LAZ file: {exc}") from exc


def iter_cloud_chunks(
    path: PathLike,
    chunk_size: int = 2_000_000,
    *,
    fields: tuple[str, ...] = (),
    topic: str | None = None,
    convention: CloudConvention | None = None,
) -> Iterator[PointCloud]:
    """Stream any supported cloud: LAS/LAZ in chunks (carrying the extra dimensions named in
    ``fields``), other formats as one chunk (with all their fields; ``topic`` for bags):
    :func:`read_plot_cloud`, so a cloud of NaN is an InputError. ``convention``: the file's
    units and up axis (:class:`stemmap.io.conventions.CloudConvention`), converted to metres,
    z up as each chunk is read."""
    p = Path(path)
    if p.suffix.lower() in (".las", ".laz"):
        for chunk in iter_las_chunks(p, chunk_size, fields=fields):
            yield _converted(chunk, convention)
    else:
        yield read_plot_cloud(p, topic=topic, convention=convention)


def _converted(cloud: PointCloud, convention: CloudConvention | None) -> PointCloud:
    if convention is None or convention.is_identity:
        return cloud
    return PointCloud(
        convention.apply(cloud.xyz), time=cloud.time, frame=cloud.frame, fields=cloud.fields
    )


def read_plot_cloud(
    path: PathLike, *, topic: str | None = None, convention: CloudConvention | None = None
) -> PointCloud:
    """:func:`read_cloud` of a cloud to measure stems in: InputError when not one point has
    finite coordinates -- a whole cloud of NaN is a broken export, not an empty plot
    (:func:`read_cloud` returns it empty: a lidar frame of a blocked sensor is all NaN in an
    organised PCD). ``convention`` as in :func:`iter_cloud_chunks`."""
    cloud = read_cloud(path, topic=topic, convention=convention)
    if cloud.xyz.shape[0] == 0:
        raise InputError(
            f"{str(path)!r} holds no point with finite coordinates (none, or all NaN / "
            "infinite): nothing to measure. Check the export's columns and no-data value."
        )
    return cloud
