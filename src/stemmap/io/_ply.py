"""PLY reader (private; the public entry point is :func:`stemmap.io.clouds.read_ply`).

Implements the PLY polygon file format as specified by Greg Turk, "The PLY Polygon File Format"
(Stanford, 1994; the text distributed with the Stanford 3D Scanning Repository):

* header: ``ply``, ``format {ascii|binary_little_endian|binary_big_endian} 1.0``, ``comment``
  and ``obj_info`` lines, ``element NAME COUNT``, ``property TYPE NAME``,
  ``property list COUNT_TYPE ITEM_TYPE NAME``, ``end_header``;
* scalar types ``char uchar short ushort int uint float double`` and the sized aliases
  ``int8 uint8 int16 uint16 int32 uint32 float32 float64`` (written by VTK, PCL, Open3D);
* elements stored one after another in header order; binary records are packed (no
  alignment); ascii records are one per line.

Only the ``vertex`` element is decoded. Elements before it are skipped (list properties such as
``face`` too, which needs the list lengths); elements after it are not read at all. Binary
vertex blocks are one packed structured dtype over the memory-mapped file (``np.memmap``);
ascii blocks one ``np.loadtxt`` call.
"""

from __future__ import annotations

import io
import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError

__all__ = [
    "PlyElement",
    "PlyHeader",
    "PlyProperty",
    "PlyVertices",
    "read_ply_header",
    "read_ply_vertices",
]

#: PLY scalar type names -> numpy type codes (without byte order).
PLY_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
#: numpy type codes -> struct format characters (for the record-by-record slow path).
_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER = 1 << 20  # a header longer than 1 MiB is not a PLY header


@dataclass(frozen=True)
class PlyProperty:
    """One property: ``dtype`` a numpy code (``"f4"``); lists also have ``count_dtype``."""

    name: str
    dtype: str
    count_dtype: str | None = None

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


@dataclass(frozen=True)
class PlyElement:
    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def has_lists(self) -> bool:
        return any(p.is_list for p in self.properties)

    def record_dtype(self, byte_order: str) -> np.dtype[Any]:
        """Packed structured dtype of one record (scalar properties only)."""
        return np.dtype([(p.name, byte_order + p.dtype) for p in self.properties])


@dataclass(frozen=True)
class PlyHeader:
    """A parsed header; ``data_offset`` is the byte where the body starts."""

    format: str
    elements: tuple[PlyElement, ...]
    comments: tuple[str, ...]
    obj_info: tuple[str, ...]
    data_offset: int

    @property
    def byte_order(self) -> str:
        return _FORMATS[self.format]

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


def _ptype(path: Path, lineno: int, name: str) -> str:
    code = PLY_TYPES.get(name)
    if code is None:
        raise InputError(
            f"PLY file {str(path)!r} header line {lineno}: unknown property type {name!r}; "
            f"the PLY types are {', '.join(PLY_TYPES)}."
        )
    return code


def read_ply_header(fh: BinaryIO, path: Path) -> PlyHeader:
    """Parse the header of an open PLY file (positioned at byte 0).

    Raises
    ------
    InputError
        No ``ply`` magic, no ``end_header`` within 1 MiB, non-ASCII text, an unknown keyword,
        format or type, a property outside an element, a bad count, a repeated name.
    """
    magic = fh.readline(16)
    if magic.rstrip(b"\r\n") != b"ply":
        raise InputError(
            f"{str(path)!r} is not a PLY file: it does not start with the line 'ply' "
            f"(starts with {magic[:16]!r})."
        )
    lines: list[str] = []
    offset = len(magic)
    while True:
        raw = fh.readline(_MAX_HEADER)
        if not raw:
            raise InputError(
                f"PLY file {str(path)!r} has no 'end_header' line: the header is cut short."
            )
        offset += len(raw)
        if offset > _MAX_HEADER:
            raise InputError(
                f"PLY file {str(path)!r} has no 'end_header' line within its first 1 MiB."
            )
        try:
            line = raw.decode("ascii").rstrip("\r\n")
        except UnicodeDecodeError as exc:
            raise InputError(
                f"PLY file {str(path)!r} header line {len(lines) + 2} is not ASCII text."
            ) from exc
        lines.append(line)
        if line.strip() == "end_header":
            break
    fmt: str | None = None
    comments: list[str] = []
    obj_info: list[str] = []
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    for k, line in enumerate(lines[:-1], start=2):
        tok = line.split()
        if not tok:
            continue  # blank header lines: not in the spec, harmless
        key = tok[0]
        where = f"PLY file {str(path)!r} header line {k}"
        if key == "comment":
            comments.append(line.split(None, 1)[1] if len(tok) > 1 else "")
        elif key == "obj_info":
            obj_info.append(line.split(None, 1)[1] if len(tok) > 1 else "")
        elif key == "format":
            if fmt is not None:
                raise InputError(f"{where}: a second 'format' line.")
            if len(tok) != 3:
                raise InputError(f"{where}: expected 'format TYPE 1.0', got {line!r}.")
            if tok[1] not in _FORMATS:
                raise InputError(
                    f"{where}: unsupported format {tok[1]!r}; PLY formats are "
                    f"{', '.join(_FORMATS)}."
                )
            try:
                version = float(tok[2])
            except ValueError:
                version = float("nan")
            if version != 1.0:
                raise InputError(f"{where}: unsupported PLY version {tok[2]!r} (only 1.0 exists).")
            fmt = tok[1]
        elif key == "element":
            if len(tok) != 3:
                raise InputError(f"{where}: expected 'element NAME COUNT', got {line!r}.")
            try:
                count = int(tok[2])
            except ValueError:
                count = -1
            if count < 0:
                raise InputError(f"{where}: element count {tok[2]!r} is not an integer >= 0.")
            if any(e[0] == tok[1] for e in elements):
                raise InputError(f"{where}: element {tok[1]!r} is declared twice.")
            elements.append((tok[1], count, []))
        elif key == "property":
            if not elements:
                raise InputError(f"{where}: 'property' before any 'element' line.")
            props = elements[-1][2]
            if len(tok) >= 2 and tok[1] == "list":
                if len(tok) != 5:
                    raise InputError(
                        f"{where}: expected 'property list COUNT_TYPE ITEM_TYPE NAME', "
                        f"got {line!r}."
                    )
                ctype = _ptype(path, k, tok[2])
                if ctype[0] == "f":
                    raise InputError(f"{where}: a list count type must be an integer type.")
                prop = PlyProperty(tok[4], _ptype(path, k, tok[3]), ctype)
            else:
                if len(tok) != 3:
                    raise InputError(f"{where}: expected 'property TYPE NAME', got {line!r}.")
                prop = PlyProperty(tok[2], _ptype(path, k, tok[1]))
            if any(p.name == prop.name for p in props):
                raise InputError(
                    f"{where}: property {prop.name!r} appears twice in element {elements[-1][0]!r}."
                )
            props.append(prop)
        else:
            raise InputError(f"{where}: unknown header keyword {key!r}.")
    if fmt is None:
        raise InputError(f"PLY file {str(path)!r} has no 'format' line in its header.")
    return PlyHeader(
        fmt,
        tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements),
        tuple(comments),
        tuple(obj_info),
        offset,
    )


# --------------------------------------------------------------------------------------------
# binary bodies
# --------------------------------------------------------------------------------------------


def _truncated(path: Path, elem: PlyElement, detail: str) -> InputError:
    return InputError(
        f"PLY file {str(path)!r} is truncated: element {elem.name!r} announces {elem.count} "
        f"records but {detail}."
    )


def _walk_binary(
    buf: Any, offset: int, elem: PlyElement, bo: str, path: Path, keep: bool
) -> tuple[int, dict[str, NDArray[Any]]]:
    """Step through ``elem`` record by record (list lengths that vary); return the end offset
    and, if ``keep``, the scalar properties. The slow path of :func:`_binary_lists`."""
    steps = [
        (p, struct.Struct(bo + _STRUCT[p.count_dtype or p.dtype]), np.dtype(p.dtype).itemsize)
        for p in elem.properties
    ]
    cols: dict[str, list[Any]] = {p.name: [] for p in elem.properties if not p.is_list}
    off = offset
    k = 0
    try:
        for k in range(elem.count):  # noqa: B007 - k names the record in the error
            for p, s, item in steps:
                (v,) = s.unpack_from(buf, off)
                off += s.size
                if p.is_list:
                    off += int(v) * item
                elif keep:
                    cols[p.name].append(v)
    except struct.error:
        raise _truncated(path, elem, f"the file ends inside record {k}") from None
    if off > len(buf):
        raise _truncated(path, elem, "the file ends inside its last record")
    if not keep:
        return off, {}
    return off, {
        p.name: np.asarray(cols[p.name], dtype=np.dtype(p.dtype))
        for p in elem.properties
        if not p.is_list
    }


def _uniform_list_dtype(buf: Any, offset: int, elem: PlyElement, bo: str) -> np.dtype[Any] | None:
    """Record dtype if every record had the list lengths of the first one (lists become
    sub-array fields; count fields are named ``NAME#count``); None if the first record is cut."""
    fields: list[tuple[Any, ...]] = []
    off = offset
    try:
        for p in elem.properties:
            if p.count_dtype is None:
                fields.append((p.name, bo + p.dtype))
                off += np.dtype(p.dtype).itemsize
            else:
                s = struct.Struct(bo + _STRUCT[p.count_dtype])
                (n,) = s.unpack_from(buf, off)
                fields.append((f"{p.name}#count", bo + p.count_dtype))
                fields.append((p.name, bo + p.dtype, (int(n),)))
                off += s.size + int(n) * np.dtype(p.dtype).itemsize
    except struct.error:
        return None
    return np.dtype(fields)


def _binary_lists(
    buf: Any,
    offset: int,
    elem: PlyElement,
    bo: str,
    path: Path,
    keep: bool,
) -> tuple[int, dict[str, NDArray[Any]]]:
    """An element with list properties: fast path when all list lengths equal the first
    record's (triangle meshes), checked on a strided view; else the record-by-record walk."""
    dt = _uniform_list_dtype(buf, offset, elem, bo)
    if dt is not None and elem.count * dt.itemsize <= len(buf) - offset:
        rec = np.frombuffer(buf, dtype=dt, count=elem.count, offset=offset)
        counts = [n for n in dt.names or () if n.endswith("#count")]
        if all(np.all(rec[n] == rec[n][0]) for n in counts):
            out = (
                {p.name: rec[p.name].astype(p.dtype) for p in elem.properties if not p.is_list}
                if keep
                else {}
            )
            del rec
            return offset + elem.count * dt.itemsize, out
        del rec
    return _walk_binary(buf, offset, elem, bo, path, keep)


class PlyVertices(NamedTuple):
    """The decoded vertex element: ``xyz`` (N, 3) float64 (None without x, y and z), the other
    scalar properties in native byte order and their declared types, and the header."""

    xyz: NDArray[np.float64] | None
    fields: dict[str, NDArray[Any]]
    header: PlyHeader


_XYZ = ("x", "y", "z")


def _assemble(cols: Any, elem: PlyElement, header: PlyHeader, views: bool = False) -> PlyVertices:
    """Split columns (a structured record array, possibly memory-mapped, or a dict) into the
    (N, 3) float64 coordinates and the other properties in native byte order (copies, or with
    ``views`` the columns themselves when they are native already)."""
    names = {p.name for p in elem.properties if not p.is_list}
    xyz = None
    if all(c in names for c in _XYZ):
        # one pass per column: byte swap and widening straight into the output
        xyz = np.empty((elem.count, 3), dtype=np.float64)
        for i, c in enumerate(_XYZ):
            xyz[:, i] = cols[c]
    fields = {}
    for p in elem.properties:
        if p.is_list or (xyz is not None and p.name in _XYZ):
            continue
        col = np.asarray(cols[p.name])
        fields[p.name] = col if views and col.dtype.isnative else col.astype(p.dtype)
    return PlyVertices(xyz, fields, header)


def _read_binary(fh: BinaryIO, path: Path, header: PlyHeader) -> PlyVertices:
    bo = header.byte_order
    size = path.stat().st_size
    offset = header.data_offset
    for elem in header.elements:
        is_vertex = elem.name == "vertex"
        if not elem.has_lists:
            dt = elem.record_dtype(bo)
            need = elem.count * dt.itemsize
            if offset + need > size:
                have = max(size - offset, 0)
                raise _truncated(
                    path,
                    elem,
                    f"only {have} of their {need} bytes ({have // max(dt.itemsize, 1)} "
                    "records) are in the file",
                )
            if not is_vertex:
                offset += need
                continue
            if elem.count == 0 or dt.itemsize == 0:  # nothing to map
                return _assemble(np.zeros(elem.count, dtype=dt), elem, header)
            # memory-mapped: the records come straight from the page cache; the coordinates
            # are copied (swapped and widened in the same pass), the other columns stay views
            # of the mapping when they are in native byte order (the caller copies them; the
            # mapping closes when the last view goes)
            rec = np.memmap(path, dtype=dt, mode="r", offset=offset, shape=(elem.count,))
            return _assemble(rec, elem, header, views=True)
        # list properties: needs the bytes (memory-mapped, not read)
        fh.seek(0)
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            offset, cols = _binary_lists(mm, offset, elem, bo, path, is_vertex)
        if is_vertex:
            return _assemble(cols, elem, header)
    raise AssertionError("unreachable: the caller checked that a vertex element exists")


# --------------------------------------------------------------------------------------------
# ascii bodies
# --------------------------------------------------------------------------------------------


def _ascii_cast(path: Path, prop: PlyProperty, v: NDArray[np.float64]) -> NDArray[Any]:
    """Cast parsed text to the declared type; integers must be integral and in range."""
    dt = np.dtype(prop.dtype)
    if dt.kind in "iu":
        info = np.iinfo(dt)
        bad = (v != np.round(v)) | (v < info.min) | (v > info.max)
        if np.any(bad):
            k = int(np.argmax(bad))
            raise InputError(
                f"PLY file {str(path)!r}: vertex {k} property {prop.name!r} is "
                f"{float(v[k]):g}, not a {dt.name} value."
            )
    return v.astype(dt)


def _ascii_walk_vertex(
    text: io.TextIOBase, path: Path, elem: PlyElement
) -> dict[str, NDArray[Any]]:
    """Vertex records with list properties (variable token count): one line at a time."""
    cols: dict[str, list[float]] = {p.name: [] for p in elem.properties if not p.is_list}
    for k in range(elem.count):
        line = text.readline()
        if not line:
            raise _truncated(path, elem, f"the file ends after {k} of them")
        tok = line.split()
        j = 0
        try:
            for p in elem.properties:
                if p.is_list:
                    j += 1 + int(tok[j])
                else:
                    cols[p.name].append(float(tok[j]))
                    j += 1
        except (IndexError, ValueError) as exc:
            raise InputError(
                f"PLY file {str(path)!r}: vertex line {k + 1} of the body is malformed "
                f"({line.strip()[:60]!r})."
            ) from exc
    return {
        p.name: _ascii_cast(path, p, np.asarray(cols[p.name], dtype=np.float64))
        for p in elem.properties
        if not p.is_list
    }


def _read_ascii(fh: BinaryIO, path: Path, header: PlyHeader) -> dict[str, NDArray[Any]]:
    fh.seek(header.data_offset)
    text = io.TextIOWrapper(fh, encoding="ascii", errors="strict", newline=None)
    try:
        for elem in header.elements:
            if elem.name != "vertex":
                for k in range(elem.count):  # one record per line
                    if not text.readline():
                        raise _truncated(path, elem, f"the file ends after {k} of them")
                continue
            if elem.has_lists:
                return _ascii_walk_vertex(text, path, elem)
            n = len(elem.properties)
            # a record is >= n numbers of one character, each followed by a space or newline:
            # read at most one record more than the body can hold (np.loadtxt allocates
            # max_rows rows first: 4e9 announced vertices were an out-of-memory error); a
            # short body is then reported as truncated below
            room = max(os.fstat(fh.fileno()).st_size - header.data_offset, 0) // (2 * n)
            try:
                arr = np.loadtxt(
                    text,
                    dtype=np.float64,
                    comments=None,
                    ndmin=2,
                    max_rows=min(elem.count, room + 1),
                )
            except ValueError as exc:
                raise InputError(
                    f"PLY file {str(path)!r}: the vertex block is malformed or truncated (each "
                    f"of its {elem.count} lines needs {n} numbers): {exc}"
                ) from exc
            if arr.shape[0] < elem.count:
                raise _truncated(path, elem, f"the file ends after {arr.shape[0]} of them")
            if arr.shape[1] != n:
                raise InputError(
                    f"PLY file {str(path)!r}: vertex lines have {arr.shape[1]} numbers, the "
                    f"header declares {n} ({', '.join(p.name for p in elem.properties)})."
                )
            return {p.name: _ascii_cast(path, p, arr[:, i]) for i, p in enumerate(elem.properties)}
    except UnicodeDecodeError as exc:
        raise InputError(
            f"PLY file {str(path)!r} says 'format ascii' but its body holds non-ASCII bytes "
            "(a binary file with a wrong header?)."
        ) from exc
    finally:
        text.detach()
    raise AssertionError("unreachable: the caller checked that a vertex element exists")


def read_ply_vertices(path: Path) -> PlyVertices:
    """The ``vertex`` element: coordinates as one (N, 3) float64 array, the other scalar
    properties (native byte order, declared types), and the header. List properties of the
    vertex element are skipped. Properties of a binary file may be read-only views of the
    memory-mapped file (copy what you keep: :func:`stemmap.io.clouds.read_ply` does).

    Raises
    ------
    InputError
        Malformed header (see :func:`read_ply_header`), no vertex element, a body shorter than
        the header announces, malformed ascii lines.
    """
    try:
        with path.open("rb") as fh:
            header = read_ply_header(fh, path)
            if header.element("vertex") is None:
                names = ", ".join(e.name for e in header.elements) or "none"
                raise InputError(
                    f"PLY file {str(path)!r} has no 'vertex' element (its elements: {names})."
                )
            if header.format == "ascii":
                vertex = header.element("vertex")
                assert vertex is not None
                return _assemble(_read_ascii(fh, path, header), vertex, header)
            return _read_binary(fh, path, header)
    except OSError as exc:
        raise InputError(f"cannot read PLY file {str(path)!r}: {exc}.") from exc
