"""Helpers shared by the readers and writers (private)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError

PathLike = str | os.PathLike[str]


class SkippedFrame(NamedTuple):
    """A frame of a long log that could not be used and was skipped.

    Attributes
    ----------
    frame_index : int
        Position of the frame in the file (row, message or array index, 0-based).
    time : float
        Time stamp of the frame in seconds, NaN when it could not be read.
    reason : str
        Full-sentence reason, naming the field and value at fault.
    """

    frame_index: int
    time: float
    reason: str


def existing_file(path: PathLike, what: str) -> Path:
    """``path`` as a Path; InputError if it does not exist or is not a regular file."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{what} file {str(p)!r} does not exist.")
    if not p.is_file():
        raise InputError(f"{what} path {str(p)!r} is not a regular file.")
    return p


#: Parse memory of a line-oriented text table, per byte of file and per line (measured with
#: tracemalloc on :func:`parse_numeric_csv`: 1 M lines of ``0,0,0`` peak at 210 MB, 1 M lines
#: of three 12-digit numbers (40 MB) at 310 MB; the estimate gives 218 and 320 MB).
TABLE_PER_BYTE, TABLE_PER_LINE = 3.0, 200.0
#: Parse memory of JSON per byte of file: ``json.loads`` makes a Python object per number,
#: list or dict (``[1,`` = 3 bytes -> a 32-byte float and its slot; ``{},`` -> a 72-byte dict).
JSON_PER_BYTE = 25.0


def read_text(path: Path, what: str, *, json: bool = False) -> str:
    """Read a UTF-8 text file; InputError naming the file on decode/OS errors.

    Before reading, the file is checked against the read budget
    (:func:`stemmap.io._budget.check_text_budget`): a line-oriented table (the default) may
    not have a line over 1 MB and its parse (~3 B per byte + ~200 B per line) must fit the
    budget; ``json`` files are estimated at :data:`JSON_PER_BYTE` per byte, with no line limit.
    """
    from stemmap.io._budget import check_text_budget

    try:
        if json:
            check_text_budget(path, what, per_byte=JSON_PER_BYTE, per_line=0.0, max_line=None)
        else:
            check_text_budget(path, what, per_byte=TABLE_PER_BYTE, per_line=TABLE_PER_LINE)
    except OSError as exc:
        raise InputError(f"cannot read {what} file {str(path)!r}: {exc}.") from exc
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{what} file {str(path)!r} is not UTF-8 text (byte {exc.start}): is it binary?"
        ) from exc
    except OSError as exc:
        raise InputError(f"cannot read {what} file {str(path)!r}: {exc}.") from exc


def fmt_float(v: float) -> str:
    """Shortest text that reads back to the same float64 ('nan', 'inf', '-inf' for non-finite)."""
    if math.isnan(v):
        return "nan"
    return repr(float(v))


def fmt_row(values: Sequence[Any]) -> str:
    """One CSV line from ints and floats, exact round trip for float64."""
    out = []
    for v in values:
        if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
            out.append(str(int(v)))
        else:
            out.append(fmt_float(float(v)))
    return ",".join(out)


class CsvTable(NamedTuple):
    """Numeric columns of a CSV file plus the 1-based file line number of each data row."""

    header: list[str]
    columns: dict[str, NDArray[np.float64]]
    lines: NDArray[np.int64]


#: Old column name -> current name with its unit; readers accept both.
COLUMN_ALIASES = {
    "time": "time_s",
    "first_time": "first_time_s",
    "last_time": "last_time_s",
    "cov_xy": "cov_xy_m2",
}


def parse_numeric_csv(
    path: Path,
    text: str,
    required: Sequence[str],
    optional: Sequence[str],
    what: str,
) -> CsvTable:
    """Parse a header + numeric-rows CSV into float64 columns (an empty field is NaN).

    Lines starting with ``#`` and blank lines are ignored. Every data row must have as many
    fields as the header and every field must parse as a float, else InputError naming the
    line. Returns the header, the required and present optional columns, and line numbers.
    """
    numbered = [
        (k + 1, ln)
        for k, ln in enumerate(text.splitlines())
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not numbered:
        raise InputError(f"{what} file {str(path)!r} is empty (no header line).")
    header = [h.strip() for h in numbered[0][1].split(",")]
    # columns renamed to carry their unit (stemmap < 0.2 wrote the bare names)
    header = [
        COLUMN_ALIASES[h] if h in COLUMN_ALIASES and COLUMN_ALIASES[h] not in header else h
        for h in header
    ]
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(
            f"{what} file {str(path)!r} lacks column(s) {', '.join(missing)}; "
            f"its header has {', '.join(header)} but needs {', '.join(required)}."
        )
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise InputError(f"{what} file {str(path)!r} repeats column(s) {', '.join(dup)}.")
    ncol = len(header)
    rows = numbered[1:]
    for lineno, ln in rows:
        if ln.count(",") != ncol - 1:
            raise InputError(
                f"{what} file {str(path)!r} line {lineno} has {ln.count(',') + 1} fields but "
                f"the header has {ncol}: the row is truncated or malformed."
            )
    linenos = np.array([n for n, _ in rows], dtype=np.int64)
    data = np.zeros((0, ncol)) if not rows else _parse_fast(path, rows, header, what)
    cols = {c: data[:, header.index(c)] for c in (*required, *optional) if c in header}
    return CsvTable(header, cols, linenos)


def _parse_fast(
    path: Path, rows: Sequence[tuple[int, str]], header: Sequence[str], what: str
) -> NDArray[np.float64]:
    """numpy's C parser; on any failure fall back to :func:`_parse_slow` for the message."""
    ncol = len(header)
    try:
        data = np.loadtxt([ln for _, ln in rows], delimiter=",", ndmin=2, dtype=np.float64)
        return np.asarray(data.reshape(len(rows), ncol), dtype=np.float64)
    except ValueError:
        return _parse_slow(path, rows, header, what)


def _parse_slow(
    path: Path, rows: Sequence[tuple[int, str]], header: Sequence[str], what: str
) -> NDArray[np.float64]:
    """Field-by-field parse: empty field = NaN; InputError naming the first bad field."""
    data = np.empty((len(rows), len(header)), dtype=np.float64)
    for r, (lineno, ln) in enumerate(rows):
        for c, f in enumerate(ln.split(",")):
            s = f.strip()
            if not s:
                data[r, c] = np.nan
                continue
            try:
                data[r, c] = float(s)
            except ValueError:
                raise InputError(
                    f"{what} file {str(path)!r} line {lineno}, column {header[c]!r}: "
                    f"{s!r} is not a number."
                ) from None
    return data


def require_finite(path: Path, what: str, table: CsvTable, name: str) -> None:
    """InputError naming the first line where column ``name`` is NaN or infinite."""
    values = table.columns[name]
    bad = ~np.isfinite(values)
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(
            f"{what} file {str(path)!r} line {table.lines[k]}: column {name!r} is {values[k]}, "
            "but must be a finite number."
        )


def require_integer(path: Path, what: str, table: CsvTable, name: str) -> None:
    """InputError naming the first line where column ``name`` is not a whole number."""
    values = table.columns[name]
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(values) | (values != np.round(values))
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(
            f"{what} file {str(path)!r} line {table.lines[k]}: column {name!r} is {values[k]}, "
            "but must be a whole number."
        )


#: The most a deflate stream can expand (RFC 1951: a 258-byte match per 2 bits is ~1032:1).
_DEFLATE_MAX_RATIO = 1032


def check_npz_sizes(archive: Any, path: PathLike, what: str) -> None:
    """Refuse an NPZ whose arrays are damaged or too large to load, before numpy allocates.

    ``archive`` is what ``np.load`` returned. numpy allocates every array at the shape its
    ``.npy`` header announces before reading a byte of it. Two checks, per member and then for
    the whole archive:

    * **damage**: a member holds at most its uncompressed size, and a deflated member at most
      :data:`_DEFLATE_MAX_RATIO` times its compressed size (which itself fits in the file), so
      an announced size above either is a damaged or hostile header (shape ``(10**6, 10**6)``
      in a 1 kB file);
    * **budget**: the arrays' total announced size must fit the read budget
      (:func:`stemmap.io._budget.check_read_budget`): an honest zip bomb (20 MB of deflated
      zeros holding 20 GB of array; bzip2 and LZMA members expand further still) is
      consistent, and is refused only because loading it would exhaust the machine.

    Members whose header cannot be read are left to numpy's own reader, whose error the
    caller reports.

    Raises
    ------
    InputError
        Naming the file, the member, the announced shape and dtype, and the sizes.
    """
    import zipfile
    import zlib

    from numpy.lib import format as npy_format

    from stemmap.io._budget import check_read_budget, human_bytes

    zf = getattr(archive, "zip", None)
    if not isinstance(zf, zipfile.ZipFile):
        return
    try:
        file_size = os.path.getsize(path)
    except OSError:
        return
    total = 0
    largest: tuple[int, str, tuple[int, ...], Any] = (0, "", (), None)
    for info in zf.infolist():
        if not info.filename.endswith(".npy"):
            continue
        try:
            with zf.open(info) as fh:
                version = npy_format.read_magic(fh)
                if version == (1, 0):
                    shape, _, dtype = npy_format.read_array_header_1_0(fh)
                elif version == (2, 0):
                    shape, _, dtype = npy_format.read_array_header_2_0(fh)
                else:
                    continue
                header_len = fh.tell()
        except (
            ValueError,
            OSError,
            EOFError,
            zipfile.BadZipFile,
            zlib.error,
            NotImplementedError,
            RuntimeError,
        ):
            continue  # damage that numpy's own reader reports to the caller
        announced = math.prod(int(s) for s in shape) * int(dtype.itemsize)
        stored = min(info.compress_size, file_size)
        room = info.file_size
        if info.compress_type == zipfile.ZIP_STORED:
            room = min(room, stored)
        elif info.compress_type == zipfile.ZIP_DEFLATED:
            room = min(room, stored * _DEFLATE_MAX_RATIO)
        # (bzip2 and LZMA expand without a useful bound: the budget below catches those)
        room = max(room - header_len, 0)
        name = info.filename.removesuffix(".npy")
        if announced > room:
            raise InputError(
                f"{what} {os.fspath(path)!r} field {name!r} "
                f"announces shape {tuple(shape)} of {dtype} ({human_bytes(announced)}) but "
                f"holds at most {human_bytes(room)}: the file is damaged or truncated."
            )
        total += announced
        if announced >= largest[0]:
            largest = (announced, name, tuple(int(s) for s in shape), dtype)
    if total:
        _, name, shape, dtype = largest
        check_read_budget(
            total,
            path,
            what,
            f"its arrays hold {human_bytes(total)} when decompressed ({human_bytes(file_size)} "
            f"on disk; the largest, {name!r}, is {shape} of {dtype})",
        )
