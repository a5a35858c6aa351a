"""2D laser scan files: NPZ, CSV and ROS bags -> :class:`~stemmap.types.ScanBatch`.

Formats (see docs/algorithms/io.md for the full description):

NPZ (``np.savez`` archive, read without pickle)
    ``ranges`` (S, N) float metres, NaN/inf = no return; ``time`` (S,) seconds (``times`` is
    accepted too); scalars ``angle_min``, ``angle_increment`` (rad); optional scalars
    ``range_min``, ``range_max`` (m) and string ``frame``.

CSV (one scan per row)
    optional comment lines starting with ``#`` (``# frame=NAME`` sets the sensor frame), then
    the header ``time,angle_min,angle_increment,range_min,range_max,r0,r1,...,r{N-1}``, then one
    row per scan; seconds, radians, metres; ``nan`` (or an empty field) = no return,
    ``inf`` allowed for ``range_max``. Every row carries its own geometry.

ROS bags
    ``sensor_msgs/LaserScan`` of ROS1 ``.bag`` or ROS2 bags (folder, ``.db3``, ``.mcap``),
    see :mod:`stemmap.io.rosbag`.

A damaged frame of a long log (wrong beam count, truncated row, undecodable message, NaN time,
invalid geometry) is skipped with a warning and recorded in the optional ``skipped`` list;
a file that cannot be read at all is an :class:`~stemmap.errors.InputError`.
"""

from __future__ import annotations

import logging
import math
import re
import zipfile
import zlib
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError
from stemmap.io._util import PathLike, SkippedFrame, check_npz_sizes, existing_file, fmt_float
from stemmap.io.atomic import atomic_write
from stemmap.io.rosbag import indexed_laser_scans, is_bag
from stemmap.types import FloatArray, LaserScan, ScanBatch

__all__ = [
    "SCAN_CSV_FIXED_COLUMNS",
    "SkippedFrame",
    "iter_scans",
    "read_scans",
    "read_scans_indexed",
    "scan_file_kind",
    "stack_scans",
    "write_scans_csv",
    "write_scans_npz",
]

log = logging.getLogger(__name__)

#: The per-scan columns that precede the ranges ``r0..r{N-1}`` in the scans CSV.
SCAN_CSV_FIXED_COLUMNS = ("time", "angle_min", "angle_increment", "range_min", "range_max")

_FRAME_RE = re.compile(r"frame\s*[=:]\s*([^\s,;]+)")

ScanFileKind = Literal["npz", "csv", "bag"]


def scan_file_kind(path: PathLike) -> ScanFileKind:
    """``"npz"``, ``"csv"`` or ``"bag"`` from the path; InputError for anything else."""
    p = Path(path)
    if is_bag(p):
        return "bag"
    ext = p.suffix.lower()
    if ext == ".npz":
        return "npz"
    if ext in (".csv", ".txt"):
        return "csv"
    raise InputError(
        f"cannot tell the scan format of {str(p)!r} from its name; use .npz, .csv, a ROS1 .bag, "
        "or a ROS2 bag (folder with metadata.yaml, .db3 or .mcap)."
    )


def _record(skipped: list[SkippedFrame] | None, path: Path, k: int, t: float, why: str) -> None:
    log.warning("skipping scan %d of %s: %s.", k, path, why)
    if skipped is not None:
        skipped.append(SkippedFrame(k, t, why))


# --------------------------------------------------------------------------------------------
# NPZ
# --------------------------------------------------------------------------------------------


#: What numpy/zipfile raise on a damaged archive (found by the fuzz tests: NotImplementedError
#: for a header naming an unknown compression method or zip version, RuntimeError for a
#: flipped "encrypted" flag).
NPZ_ERRORS = (
    ValueError,
    zipfile.BadZipFile,
    OSError,
    EOFError,
    zlib.error,
    NotImplementedError,
    RuntimeError,
)


def _npz_arrays(path: PathLike) -> dict[str, NDArray[Any]]:
    """Load and validate the NPZ arrays (no pickle). InputError names file and field."""
    p = existing_file(path, "scan NPZ")
    try:
        with p.open("rb") as fh:
            magic = fh.read(6)
    except OSError as exc:
        raise InputError(f"cannot read scan NPZ {str(p)!r}: {exc}.") from exc
    if not magic.startswith((b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY")):
        raise InputError(
            f"scan NPZ {str(p)!r} is not an NPZ (zip) archive: it starts with {magic!r}"
            + (" (text: is it a CSV named .npz?)" if magic.isascii() else "")
            + "; write scans with np.savez or `stemmap io convert-scans`."
        )
    try:
        z = np.load(p, allow_pickle=False)
    except NPZ_ERRORS as exc:
        raise InputError(
            f"scan NPZ {str(p)!r} cannot be read ({type(exc).__name__}: {exc}); the file may be "
            "truncated or not an .npz archive."
        ) from exc
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(
            f"scan NPZ {str(p)!r} holds a single array, not an archive with the fields "
            "ranges, time, angle_min, angle_increment (write it with np.savez)."
        )
    out: dict[str, NDArray[Any]] = {}
    with z:
        check_npz_sizes(z, p, "scan NPZ")
        keys = set(z.files)
        if "time" not in keys and "times" in keys:
            keys.add("time")
        missing = [k for k in ("ranges", "time", "angle_min", "angle_increment") if k not in keys]
        if missing:
            raise InputError(
                f"scan NPZ {str(p)!r} lacks field(s) {', '.join(missing)}; it has "
                f"{', '.join(sorted(z.files)) or 'no fields'}."
            )
        for key in ("ranges", "time", "angle_min", "angle_increment", "range_min", "range_max"):
            src = "times" if key == "time" and "time" not in z.files else key
            if src not in z.files:
                continue
            try:
                arr = z[src]
            except NPZ_ERRORS as exc:
                raise InputError(
                    f"scan NPZ {str(p)!r} field {src!r} cannot be read ({exc}); object arrays "
                    "are refused (no pickle) and a truncated file cannot be decoded."
                ) from exc
            if arr.dtype.kind not in "fiu":
                raise InputError(
                    f"scan NPZ {str(p)!r} field {src!r} has dtype {arr.dtype}; it must be "
                    "a real number array (float or int)."
                )
            out[key] = arr.astype(np.float64)
        if "frame" in z.files:
            try:
                fr = z["frame"]
            except NPZ_ERRORS as exc:
                raise InputError(f"scan NPZ {str(p)!r} field 'frame' cannot be read.") from exc
            if fr.dtype.kind != "U" or fr.size != 1:
                raise InputError(f"scan NPZ {str(p)!r} field 'frame' must be one string.")
            out["frame"] = fr
    r = out["ranges"]
    if r.ndim != 2:
        raise InputError(
            f"scan NPZ {str(p)!r} field 'ranges' must have shape (S, N) (scans x beams), "
            f"got {r.shape}."
        )
    t = out["time"].reshape(-1) if out["time"].ndim <= 1 else out["time"]
    if t.ndim != 1 or t.shape[0] != r.shape[0]:
        raise InputError(
            f"scan NPZ {str(p)!r} field 'time' must have shape ({r.shape[0]},) to match "
            f"ranges {r.shape}, got {out['time'].shape}."
        )
    out["time"] = t
    for key in ("angle_min", "angle_increment", "range_min", "range_max"):
        if key in out and out[key].size != 1:
            raise InputError(
                f"scan NPZ {str(p)!r} field {key!r} must be a scalar, got shape {out[key].shape}."
            )
    return out


def _read_npz(
    path: PathLike, skipped: list[SkippedFrame] | None
) -> tuple[ScanBatch, NDArray[np.int64]]:
    """The batch of scans with a finite time, and their row numbers in the file."""
    p = Path(path)
    a = _npz_arrays(p)
    t = a["time"]
    good = np.isfinite(t)
    for k in np.flatnonzero(~good):
        _record(skipped, p, int(k), math.nan, f"its time stamp is {t[k]}")
    if not good.any():
        raise InputError(f"scan NPZ {str(p)!r} holds no scan with a finite time stamp.")
    kw: dict[str, Any] = {}
    for key in ("range_min", "range_max"):
        if key in a:
            kw[key] = float(a[key].reshape(()))
    try:
        batch = ScanBatch(
            a["ranges"][good] if not good.all() else a["ranges"],
            t[good],
            float(a["angle_min"].reshape(())),
            float(a["angle_increment"].reshape(())),
            frame=str(a["frame"].reshape(())) if "frame" in a else "laser",
            **kw,
        )
    except InputError as exc:
        raise InputError(f"scan NPZ {str(p)!r} is invalid: {exc}") from exc
    return batch, np.flatnonzero(good)


def write_scans_npz(path: PathLike, batch: ScanBatch, *, compress: bool = True) -> None:
    """Write a :class:`ScanBatch` as an NPZ archive (the format :func:`read_scans` reads),
    atomically.

    Parameters
    ----------
    path : str or PathLike
        Output file (``.npz``); parent folders are created.
    batch : ScanBatch
    compress : bool
        ``np.savez_compressed`` (default) or plain ``np.savez``.

    Notes
    -----
    Fields: ``ranges`` (S, N) float64 m, ``time`` (S,) s, scalars ``angle_min``,
    ``angle_increment`` (rad), ``range_min``, ``range_max`` (m) and the string ``frame``.
    Lossless: :func:`read_scans` returns the same values bit for bit.
    """
    arrays = {
        "ranges": np.asarray(batch.ranges),
        "time": np.asarray(batch.times),
        "angle_min": np.float64(batch.angle_min),
        "angle_increment": np.float64(batch.angle_increment),
        "range_min": np.float64(batch.range_min),
        "range_max": np.float64(batch.range_max),
        "frame": np.array(batch.frame),
    }
    with atomic_write(path, "wb") as fh:
        if compress:
            np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
        else:
            np.savez(fh, **arrays)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# CSV
# --------------------------------------------------------------------------------------------


def _csv_lines(path: Path) -> Iterator[tuple[int, str]]:
    try:
        with path.open(encoding="utf-8-sig") as fh:
            for n, ln in enumerate(fh, start=1):
                yield n, ln.rstrip("\r\n")
    except UnicodeDecodeError as exc:
        raise InputError(f"scan CSV {str(path)!r} is not UTF-8 text: is it binary?") from exc


def _parse_float_fields(fields: Sequence[str]) -> FloatArray:
    try:
        return np.array(fields, dtype=np.float64)
    except ValueError:
        return np.array([float(f) if f.strip() else math.nan for f in fields], dtype=np.float64)


def _iter_csv(
    path: PathLike, skipped: list[SkippedFrame] | None, *, held: bool = False
) -> Iterator[tuple[int, LaserScan]]:
    """The scans of a scans CSV, one by one; ``held``: the caller keeps every one (read_scans),
    so the whole parse is checked against the read budget, not only the line length."""
    p = existing_file(path, "scan CSV")
    from stemmap.io._budget import check_text_budget

    # held: one LaserScan (~0.5 kB of objects) per line, float64 ranges (~1 B per byte of
    # text); streamed (iter_scans, `stemmap odometry`): one line at a time, bounded by its length
    check_text_budget(p, "scan CSV", per_byte=3.0 if held else 0.0, per_line=500.0 if held else 0.0)
    frame = "laser"
    header: list[str] | None = None
    pick: list[int] | None = None  # a rostopic CSV's columns, in the stemmap layout's order
    frame_col: int | None = None
    n_beams = 0
    k = -1
    for lineno, ln in _csv_lines(p):
        s = ln.strip()
        if not s:
            continue
        if s.startswith("#"):
            m = _FRAME_RE.search(s)
            if m and header is None:
                frame = m.group(1)
            continue
        if header is None:
            header = [h.strip() for h in s.split(",")]
            if header[0] == "%time":  # `rostopic echo -p` of a LaserScan topic
                pick, frame_col = _rostopic_columns(header, p, lineno)
                n_beams = len(pick) - 5
                continue
            if tuple(header[:5]) != SCAN_CSV_FIXED_COLUMNS or len(header) < 6:
                raise InputError(
                    f"scan CSV {str(p)!r} line {lineno}: the header must start with "
                    f"{','.join(SCAN_CSV_FIXED_COLUMNS)} followed by one column per beam "
                    f"(r0,r1,...); got {s[:120]!r}."
                )
            n_beams = _csv_beam_columns(header, p, lineno)
            continue
        k += 1
        fields = s.split(",")
        if len(fields) != len(header):
            _record(
                skipped,
                p,
                k,
                math.nan,
                f"line {lineno} has {len(fields) - 5} ranges but the header declares "
                f"{len(header) - 5} (truncated row or wrong beam count)",
            )
            continue
        try:
            if pick is not None:
                row_frame = fields[frame_col] if frame_col is not None else ""
                v = _parse_float_fields([fields[i] for i in pick])
                v[0] = _ns_to_s(fields[pick[0]], fields[0])
            else:
                v = _parse_float_fields(fields)
        except ValueError as exc:
            _record(skipped, p, k, math.nan, f"line {lineno} holds a non-number ({exc})")
            continue
        if pick is not None and row_frame:
            frame = row_frame
        try:
            scan = LaserScan(
                v[5 : 5 + n_beams],
                v[1],
                v[2],
                time=v[0],
                range_min=v[3] if np.isfinite(v[3]) else 0.0,
                range_max=v[4] if not np.isnan(v[4]) else math.inf,
                frame=frame,
            )
        except InputError as exc:
            _record(skipped, p, k, float(v[0]), f"line {lineno} is invalid: {exc}")
        else:
            yield k, scan
    if header is None:
        raise InputError(f"scan CSV {str(p)!r} is empty (no header line).")


_INTENSITY_RE = re.compile(r"(i|intensity|intensities)_?(\d+)$", re.IGNORECASE)

#: The ``rostopic echo -p`` columns of a sensor_msgs/LaserScan that give the stemmap layout's
#: fixed columns (the time is the header stamp, integer nanoseconds).
_ROSTOPIC_FIXED = (
    "field.header.stamp",
    "field.angle_min",
    "field.angle_increment",
    "field.range_min",
    "field.range_max",
)


def _rostopic_columns(header: list[str], p: Path, lineno: int) -> tuple[list[int], int | None]:
    """The columns of a ``rostopic echo -p /scan`` CSV (``%time,field.header.seq,
    field.header.stamp,field.header.frame_id,field.angle_min,...,field.ranges0,...,
    field.intensities0,...``) in the stemmap layout's order (stamp, angle_min,
    angle_increment, range_min, range_max, ranges...), and the frame_id column. Its times are
    integer nanoseconds: read as seconds, a log 10 scans a second would span 3 years a scan."""
    at = {c: i for i, c in enumerate(header)}
    missing = [c for c in _ROSTOPIC_FIXED if c not in at]
    ranges: list[int] = []
    while f"field.ranges{len(ranges)}" in at:
        ranges.append(at[f"field.ranges{len(ranges)}"])
    if missing or not ranges:
        raise InputError(
            f"scan CSV {str(p)!r} line {lineno}: a `rostopic echo -p` header (%time,...) "
            "without the sensor_msgs/LaserScan columns "
            f"{', '.join(missing) if missing else 'field.ranges0..'}: is it a LaserScan topic?"
        )
    return [at[c] for c in _ROSTOPIC_FIXED] + ranges, at.get("field.header.frame_id")


def _ns_to_s(stamp: str, receipt: str) -> float:
    """Integer nanoseconds (a ROS stamp as rostopic writes it) -> seconds, exactly as a float
    allows; the receipt time (``%time``) when the stamp is 0 (an unstamped message)."""
    text = stamp.strip()
    if not text.lstrip("-").isdigit() or int(text) == 0:
        text = receipt.strip()
    ns = int(text) if text.lstrip("-").isdigit() else int(float(text))
    return ns // 1_000_000_000 + (ns % 1_000_000_000) / 1e9


def _csv_beam_columns(header: list[str], p: Path, lineno: int) -> int:
    """Number of range columns of a scans CSV header: ``r0..r{N-1}`` right after the fixed
    columns, optionally followed by as many intensity columns (``i0..``, ``intensity0..``),
    which are ignored. Any other column is an InputError: read as ranges, a LaserScan CSV
    exported with its intensities gave twice the beams, the second half spread past the
    scanner's field of view (a 180-degree scan became a 360-degree one without a word)."""
    rest = header[5:]
    n = 0
    while n < len(rest) and rest[n] == f"r{n}":
        n += 1
    extra = rest[n:]
    if n == 0:
        raise InputError(
            f"scan CSV {str(p)!r} line {lineno}: the beam columns must be named r0,r1,... "
            f"after {','.join(SCAN_CSV_FIXED_COLUMNS)}; got {','.join(rest[:3])},..."
        )
    if not extra:
        return n
    idx = [_INTENSITY_RE.match(c) for c in extra]
    if len(extra) == n and all(m is not None and int(m.group(2)) == i for i, m in enumerate(idx)):
        log.info("%s: ignoring the %d intensity columns %s..", p, n, extra[0])
        return n
    raise InputError(
        f"scan CSV {str(p)!r} line {lineno}: after the {n} beam columns r0..r{n - 1} the header "
        f"has {len(extra)} other column(s) ({','.join(extra[:3])}"
        f"{',...' if len(extra) > 3 else ''}); "
        f"only {n} intensity columns i0..i{n - 1} may follow the ranges. Rename the beam "
        "columns r0,r1,... or drop the extra columns."
    )


def _fmt_block(a: FloatArray) -> list[str]:
    """Rows of ``a`` (2-D) as exact-round-trip CSV text ('nan' for NaN)."""
    rows = []
    for row in a:
        rows.append(",".join(fmt_float(float(v)) for v in row))
    return rows


def write_scans_csv(path: PathLike, batch: ScanBatch) -> None:
    """Write a :class:`ScanBatch` in the scans CSV layout (module docstring), atomically.

    Parameters
    ----------
    path : str or PathLike
        Output file (``.csv``); parent folders are created.
    batch : ScanBatch

    Notes
    -----
    A ``# ... frame=NAME`` comment line, the header
    ``time,angle_min,angle_increment,range_min,range_max,r0..r{N-1}``, then one row per scan.
    Floats are written with the shortest text that reads back to the same float64 (``nan`` for
    no return), so :func:`read_scans` returns the same values bit for bit.
    """
    n = batch.n_beams
    head = ",".join((*SCAN_CSV_FIXED_COLUMNS, *(f"r{i}" for i in range(n))))
    fixed = f"{fmt_float(batch.angle_min)},{fmt_float(batch.angle_increment)}," + (
        f"{fmt_float(batch.range_min)},{fmt_float(batch.range_max)}"
    )
    with atomic_write(path) as fh:
        fh.write(
            f"# stemmap scans CSV: one scan per row, ranges in metres, nan = no return; "
            f"frame={batch.frame}\n"
        )
        fh.write(head + "\n")
        for start in range(0, len(batch), 1024):
            block = batch.ranges[start : start + 1024]
            times = batch.times[start : start + 1024]
            for t, row in zip(times, _fmt_block(block), strict=True):
                fh.write(f"{fmt_float(float(t))},{fixed},{row}\n")


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------


def iter_scans(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> Iterator[LaserScan]:
    """Lazily yield the scans of a file one by one (for long logs).

    Each scan keeps its own geometry (unlike :func:`read_scans`, which keeps the dominant one).

    Parameters
    ----------
    path : str or PathLike
        ``.npz``, ``.csv``, ROS1 ``.bag`` or ROS2 bag (folder, ``.db3``, ``.mcap``).
    topic : str, optional
        LaserScan topic of a bag; default the only one. Ignored for NPZ and CSV.
    skipped : list, optional
        Receives a :class:`SkippedFrame` per damaged frame.

    Raises
    ------
    InputError
        If the file cannot be read at all.
    """
    for _, scan in _indexed(path, topic, skipped):
        yield scan


def _indexed(
    path: PathLike, topic: str | None, skipped: list[SkippedFrame] | None, *, held: bool = False
) -> Iterator[tuple[int, LaserScan]]:
    kind = scan_file_kind(path)
    if kind == "bag":
        yield from indexed_laser_scans(path, topic, skipped=skipped)
    elif kind == "csv":
        yield from _iter_csv(path, skipped, held=held)
    else:
        batch, rows = _read_npz(path, skipped)
        for k, i in enumerate(rows):
            yield int(i), batch[k]


def _geometry_key(s: LaserScan) -> tuple[int, float, float]:
    return (len(s), round(s.angle_min, 9), round(s.angle_increment, 12))


def stack_scans(
    scans: Sequence[LaserScan],
    *,
    indices: Sequence[int] | None = None,
    skipped: list[SkippedFrame] | None = None,
    source: str = "scans",
) -> ScanBatch:
    """Stack scans into a :class:`ScanBatch`, keeping the dominant beam geometry.

    The geometry (beam count, ``angle_min``, ``angle_increment``) shared by most scans wins;
    scans with another geometry are skipped, logged and recorded (with their position in
    ``indices``, default 0..len-1, in the :class:`SkippedFrame`). If the kept scans declare
    different range windows, the batch takes the widest window and each scan's returns
    outside its own window are set to NaN, so no scan gains returns its sensor called invalid.

    Raises
    ------
    InputError
        If ``scans`` is empty.
    """
    return _stack(scans, indices, skipped, source)[0]


def _stack(
    scans: Sequence[LaserScan],
    indices: Sequence[int] | None,
    skipped: list[SkippedFrame] | None,
    source: str,
    *,
    consume: bool = False,
) -> tuple[ScanBatch, NDArray[np.int64]]:
    """:func:`stack_scans` and the kept indices. ``consume`` (``scans`` a list the caller
    owns): empty ``scans`` once stacked, so its float64 scans are freed before the batch
    copies the stack (the peak is two copies of the ranges, not three)."""
    if not scans:
        raise InputError(f"{source} holds no usable laser scan.")
    keys = [_geometry_key(s) for s in scans]
    counts = Counter(keys)
    best, n_best = counts.most_common(1)[0]
    if len(counts) > 1:
        others = "; ".join(
            f"{c} scan(s) with {k[0]} beams from {k[1]:.6g} rad step {k[2]:.6g} rad"
            for k, c in counts.items()
            if k != best
        )
        log.warning(
            "%s mixes beam geometries: keeping the %d scans with %d beams from %.6g rad step "
            "%.6g rad; dropping %s.",
            source,
            n_best,
            best[0],
            best[1],
            best[2],
            others,
        )
    idx = list(range(len(scans))) if indices is None else list(indices)
    kept = []
    kept_idx = []
    for k, s, key in zip(idx, scans, keys, strict=True):
        if key == best:
            kept.append(s)
            kept_idx.append(k)
        else:
            why = (
                f"its geometry ({key[0]} beams from {key[1]:.6g} rad, step {key[2]:.6g} rad) "
                f"differs from the dominant one ({best[0]} beams from {best[1]:.6g} rad, "
                f"step {best[2]:.6g} rad)"
            )
            log.info("skipping scan %d of %s: %s.", k, source, why)
            if skipped is not None:
                skipped.append(SkippedFrame(k, s.time, why))
    ranges = np.stack([s.ranges for s in kept])
    rmin = np.array([s.range_min for s in kept])
    rmax = np.array([s.range_max for s in kept])
    lo, hi = float(rmin.min()), float(rmax.max())
    if np.any(rmin != lo) or np.any(rmax != hi):
        log.info("%s: scans declare different range windows; using [%g, %g].", source, lo, hi)
        with np.errstate(invalid="ignore"):
            outside = (ranges <= rmin[:, None]) | (ranges >= rmax[:, None])
        ranges = np.where(outside, np.nan, ranges)
    frames = Counter(s.frame for s in kept)
    if len(frames) > 1:
        log.warning("%s: scans name several frames %s; using the first.", source, dict(frames))
    s0 = kept[0]
    times = np.array([s.time for s in kept])
    angle_min, angle_increment, frame = s0.angle_min, s0.angle_increment, s0.frame
    if consume and isinstance(scans, list):
        del s0, s  # the loop above leaves its last scan in ``s``
        kept.clear()
        scans.clear()
    batch = ScanBatch(ranges, times, angle_min, angle_increment, lo, hi, frame)
    return batch, np.asarray(kept_idx, dtype=np.int64)


def read_scans(
    path: PathLike,
    *,
    topic: str | None = None,
    skipped: list[SkippedFrame] | None = None,
    range_unit: str | None = None,
) -> ScanBatch:
    """Read every scan of a file into one :class:`ScanBatch`.

    Parameters
    ----------
    path : str or PathLike
        ``.npz`` / ``.csv`` in the layouts of the module docstring, a ROS1 ``.bag`` or a ROS2
        bag (folder, ``.db3``, ``.mcap``) with ``sensor_msgs/LaserScan``.
    topic : str, optional
        LaserScan topic of a bag; default the only one (InputError lists the topics if there
        are none or several). Ignored for NPZ and CSV.
    skipped : list, optional
        Receives a :class:`SkippedFrame` (index, time, reason) per damaged or mismatched frame;
        each is also logged as a warning.
    range_unit : str, optional
        The ranges' unit (``m``, ``cm``, ``mm``, ``ft``, ``us-ft``), converted to metres.
        Without it, scans whose median return lies beyond 500 m are refused (millimetres or
        centimetres read as metres gave no trunks without a word): see
        :mod:`stemmap.io.conventions`.

    Returns
    -------
    ScanBatch
        The scans of the dominant beam geometry, in file order.

    Raises
    ------
    InputError
        Missing file, unknown format, truncated or malformed NPZ (wrong fields, shapes or
        dtypes), CSV without a valid header, unreadable bag, no usable scan at all, an
        ``angle_min`` beyond one turn (degrees), ranges that cannot be metres.

    Examples
    --------
    >>> import numpy as np, tempfile, pathlib
    >>> from stemmap.types import ScanBatch
    >>> b = ScanBatch(np.full((2, 3), 5.0), np.array([0.0, 0.1]), -0.1, 0.1)
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "scans.npz"
    >>> write_scans_npz(p, b)
    >>> read_scans(p).ranges.shape
    (2, 3)
    >>> read_scans(p.with_suffix(".csv"))  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    stemmap.errors.InputError: scan CSV file '...scans.csv' does not exist.
    """
    return read_scans_indexed(path, topic=topic, skipped=skipped, range_unit=range_unit)[0]


def read_scans_indexed(
    path: PathLike,
    *,
    topic: str | None = None,
    skipped: list[SkippedFrame] | None = None,
    range_unit: str | None = None,
) -> tuple[ScanBatch, NDArray[np.int64]]:
    """:func:`read_scans` plus the position in the file (row / message index, 0-based) of
    every scan in the batch, so that results can be reported against the original frames
    when damaged or mismatched frames were skipped."""
    batch, rows = _read_indexed(path, topic, skipped)
    return _checked_conventions(batch, str(path), range_unit), rows


def _check_angle_min(angle_min: float, source: str) -> None:
    if abs(angle_min) > 2.0 * math.pi + 1e-9:
        raise InputError(
            f"{source}: angle_min is {angle_min:g} rad, beyond one turn: is it in "
            "degrees? Scan angles are radians (angle_min, angle_increment)."
        )


def check_scan_conventions(angle_min: float, ranges: NDArray[Any], source: str) -> None:
    """InputError for scans that cannot be metres and radians: an ``angle_min`` beyond one
    turn (degrees) or a median return beyond 500 m (millimetres or centimetres;
    :func:`stemmap.io.conventions.check_scan_ranges`). :func:`read_scans` applies it to the
    whole batch; the streaming readers of ``stemmap odometry`` to the first scan."""
    from stemmap.io.conventions import check_scan_ranges

    _check_angle_min(angle_min, source)
    check_scan_ranges(ranges, source)


def _checked_conventions(batch: ScanBatch, source: str, range_unit: str | None) -> ScanBatch:
    """The batch in metres and radians: InputError for an ``angle_min`` beyond one turn (a
    start angle in degrees, e.g. -90) and, without ``range_unit``, for ranges that cannot be
    metres (:func:`stemmap.io.conventions.check_scan_ranges`); ``range_unit`` (a key of
    :data:`stemmap.io.conventions.UNIT_SCALES`) scales the ranges and the range window."""
    from stemmap.io.conventions import check_scan_period, check_times, unit_scale

    check_times(batch.times, source, "scan time")
    check_scan_period(batch.times, source)  # relative ms: a warning
    if range_unit is None:
        check_scan_conventions(batch.angle_min, batch.ranges, source)
        return batch
    _check_angle_min(batch.angle_min, source)
    scale = unit_scale(range_unit, "--range-unit")
    if scale == 1.0:
        return batch
    return ScanBatch(
        batch.ranges * scale,
        batch.times,
        batch.angle_min,
        batch.angle_increment,
        batch.range_min * scale,
        batch.range_max * scale,
        batch.frame,
    )


def _read_indexed(
    path: PathLike, topic: str | None, skipped: list[SkippedFrame] | None
) -> tuple[ScanBatch, NDArray[np.int64]]:
    kind = scan_file_kind(path)
    if kind == "npz":
        return _read_npz(path, skipped)
    local: list[SkippedFrame] = []
    pairs = _held_scans(path, topic, local, bag=kind == "bag")
    if skipped is not None:
        skipped.extend(local)
    if not pairs:
        raise InputError(
            f"{str(path)!r} holds no usable laser scan"
            + (f" ({len(local)} damaged frame(s) skipped)." if local else ".")
        )
    scans, rows = [s for _, s in pairs], [i for i, _ in pairs]
    del pairs  # the scans are in ``scans`` alone: _stack frees them once stacked
    return _stack(scans, rows, skipped, str(path), consume=True)


def _held_scans(
    path: PathLike, topic: str | None, skipped: list[SkippedFrame], *, bag: bool
) -> list[tuple[int, LaserScan]]:
    """Every (index, scan) of ``path``, for :func:`read_scans`, which holds them all and then
    their stack. A bag's chunks are bounded one at a time, not its topic: a ROS 1 bag of bz2
    chunks of zero ranges holds ~1 GB of scans per MB on disk. So the scans' bytes and their
    stack's are summed as they are read and compared with the read budget taken when the read
    starts (later, the scans held would lower the memory available); ReadLimitError once
    they pass it, with at most the budget (and one chunk) held. A CSV's parse is bounded
    before it is read (``check_text_budget``)."""
    from stemmap.io._budget import ReadLimitError, human_bytes, read_budget, read_limit_text

    pairs: list[tuple[int, LaserScan]] = []
    if not bag:
        pairs.extend(_indexed(path, topic, skipped, held=True))
        return pairs
    limit = read_budget()  # now: the scans held later lower the memory available
    held = stacked = 0
    for i, s in _indexed(path, topic, skipped, held=True):
        pairs.append((i, s))
        held += s.ranges.nbytes + (0 if s.intensities is None else s.intensities.nbytes)
        stacked += s.ranges.nbytes  # float64, as in the batch
        if held + stacked > limit[0]:
            what = f"topic {topic!r}" if topic else "its LaserScan topic"
            need = held + stacked
            raise ReadLimitError(
                f"ROS bag {str(path)!r}, {what}: "
                + read_limit_text(
                    need,
                    f"its first {len(pairs):,} scans hold {human_bytes(held)} in memory and "
                    f"their stack {human_bytes(stacked)} more, ~{human_bytes(need)} so far "
                    "(the whole topic is held in memory, and more of it is left to read)",
                    partial=True,
                    limit=limit,
                )
            )
    return pairs
