"""Our PLY reader (stemmap.io._ply via read_ply / read_cloud), against files written byte by
byte from the PLY specification (Turk 1994) by the small writer below, and against plyfile
(a cross-check only; skipped when plyfile is not installed)."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import InputError
from stemmap.io._ply import PLY_TYPES
from stemmap.io.clouds import count_points, read_cloud, read_ply

_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
_BO = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}

# An element: (name, [(prop name, type) or (prop name, ("list", count type, item type))], rows)
# where each row is a list of values (a list property's value is a list).
Element = tuple[str, list[tuple[str, Any]], list[list[Any]]]


def _fmt(v: Any) -> str:
    if isinstance(v, float | np.floating):
        return repr(float(v))
    return str(int(v))


def write_ply(
    path: Path,
    fmt: str,
    elements: list[Element],
    *,
    comments: tuple[str, ...] = ("written by stemmap's tests",),
    eol: str = "\n",
) -> None:
    """A PLY file exactly as the specification lays it out (header, then the elements in
    order; packed binary records or one ascii line per record)."""
    head = ["ply", f"format {fmt} 1.0", *(f"comment {c}" for c in comments)]
    for name, props, rows in elements:
        head.append(f"element {name} {len(rows)}")
        for pname, ptype in props:
            if isinstance(ptype, tuple):
                head.append(f"property list {ptype[1]} {ptype[2]} {pname}")
            else:
                head.append(f"property {ptype} {pname}")
    head.append("end_header")
    body = bytearray((eol.join(head) + eol).encode())
    bo = _BO[fmt]
    for _, props, rows in elements:
        for row in rows:
            if fmt == "ascii":
                tok: list[str] = []
                for (_, ptype), v in zip(props, row, strict=True):
                    if isinstance(ptype, tuple):
                        tok += [str(len(v)), *(_fmt(x) for x in v)]
                    else:
                        tok.append(_fmt(v))
                body += (" ".join(tok) + eol).encode()
                continue
            for (_, ptype), v in zip(props, row, strict=True):
                if isinstance(ptype, tuple):
                    body += struct.pack(bo + _STRUCT[PLY_TYPES[ptype[1]]], len(v))
                    body += struct.pack(bo + _STRUCT[PLY_TYPES[ptype[2]]] * len(v), *v)
                else:
                    body += struct.pack(bo + _STRUCT[PLY_TYPES[ptype]], v)
    path.write_bytes(bytes(body))


FORMATS = ["ascii", "binary_little_endian", "binary_big_endian"]
XYZ = [("x", "float"), ("y", "float"), ("z", "float")]


def _vertices(n: int, seed: int = 0) -> list[list[Any]]:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-50, 50, (n, 3)).astype(np.float32)
    return [[*map(float, p), int(rng.integers(0, 256))] for p in xyz]


def _faces(n_vertices: int, n: int, sizes: tuple[int, ...] = (3,)) -> list[list[Any]]:
    rng = np.random.default_rng(1)
    return [[list(map(int, rng.integers(0, n_vertices, sizes[k % len(sizes)])))] for k in range(n)]


FACE = ("vertex_indices", ("list", "uchar", "int"))


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_type_round_trips_exactly(tmp_path: Path, fmt: str) -> None:
    """All 16 type names (8 types and their sized aliases), extreme values of each."""
    props = [("x", "double"), ("y", "float64"), ("z", "float32")]
    row_lo: list[Any] = [-1.5e300, 2.0**-1074, float(np.float32(1e-30))]
    row_hi: list[Any] = [7.0, -0.0, float(np.float32(3.4e38))]
    for name, code in PLY_TYPES.items():
        if code[0] == "f":
            continue
        info = np.iinfo(code)
        props.append((f"p_{name}", name))
        row_lo.append(int(info.min))
        row_hi.append(int(info.max))
    f = tmp_path / "types.ply"
    write_ply(f, fmt, [("vertex", props, [row_lo, row_hi])])
    cloud = read_ply(f)
    np.testing.assert_array_equal(cloud.xyz, np.array([row_lo[:3], row_hi[:3]]))
    for (pname, ptype), lo, hi in zip(props[3:], row_lo[3:], row_hi[3:], strict=True):
        col = cloud.fields[pname]
        assert col.dtype == np.dtype(PLY_TYPES[ptype]) and col.dtype.isnative
        assert col.tolist() == [lo, hi]


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("where", ["after", "before", "before_mixed"])
def test_faces_before_or_after_the_vertices(tmp_path: Path, fmt: str, where: str) -> None:
    """A mesh: faces after the vertices (the usual order) are not read; faces before them are
    skipped by their list lengths, uniform (triangles: the vectorised path) or mixed
    (triangles and quads: the record-by-record path), with an extra scalar in the face."""
    verts = _vertices(300)
    sizes = (3, 4, 3, 5) if where == "before_mixed" else (3,)
    faces = [[*r, k % 7] for k, r in enumerate(_faces(300, 200, sizes))]
    vertex: Element = ("vertex", [*XYZ, ("intensity", "uchar")], verts)
    face: Element = ("face", [FACE, ("flags", "ushort")], faces)
    edges: Element = ("edge", [("v1", "int"), ("v2", "int")], [[0, 1], [1, 2]])
    elems = [vertex, face] if where == "after" else [edges, face, vertex]
    f = tmp_path / "mesh.ply"
    write_ply(f, fmt, elems)
    cloud = read_cloud(f)
    np.testing.assert_array_equal(cloud.xyz, np.array([v[:3] for v in verts]))
    assert cloud.fields["intensity"].tolist() == [v[3] for v in verts]
    assert set(cloud.fields) == {"intensity"}


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("sizes", [(2,), (0, 3, 1)])
def test_list_property_inside_the_vertex_element(
    tmp_path: Path, fmt: str, sizes: tuple[int, ...]
) -> None:
    """A per-vertex list (uniform or varying length) is stepped over and dropped."""
    verts = _vertices(50)
    rows = [[*v[:3], [k] * sizes[k % len(sizes)], v[3]] for k, v in enumerate(verts)]
    props = [*XYZ, ("nbrs", ("list", "uint8", "uint16")), ("i", "uchar")]
    f = tmp_path / "vl.ply"
    write_ply(f, fmt, [("vertex", props, rows)])
    cloud = read_ply(f)
    np.testing.assert_array_equal(cloud.xyz, np.array([v[:3] for v in verts]))
    assert cloud.fields["i"].tolist() == [v[3] for v in verts]
    assert "nbrs" not in cloud.fields


def test_big_endian_bytes_by_hand(tmp_path: Path) -> None:
    """Big-endian floats written with struct '>' (not by our writer): 1.0 is 3f 80 00 00."""
    body = struct.pack(">fffH", 1.0, -2.5, 1024.0, 513) + struct.pack(">fffH", 0.0, 3.0, -1.0, 1)
    assert body[:4] == b"\x3f\x80\x00\x00"
    f = tmp_path / "be.ply"
    f.write_bytes(
        b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n"
        b"property float y\nproperty float z\nproperty ushort intensity\nend_header\n" + body
    )
    cloud = read_ply(f)
    np.testing.assert_array_equal(cloud.xyz, [[1.0, -2.5, 1024.0], [0.0, 3.0, -1.0]])
    assert cloud.fields["intensity"].tolist() == [513, 1]


@pytest.mark.parametrize("fmt", FORMATS)
def test_header_edge_cases_that_are_valid(tmp_path: Path, fmt: str) -> None:
    """CRLF line ends, comments and obj_info anywhere, a blank header line, no comments, an
    empty element, NaN vertices (dropped like every reader does)."""
    verts = _vertices(20)
    verts[5][0] = float("nan")
    f = tmp_path / "crlf.ply"
    write_ply(
        f,
        fmt,
        [("empty", [("a", "int")], []), ("vertex", [*XYZ, ("i", "uchar")], verts)],
        comments=(),
        eol="\r\n",
    )
    raw = f.read_bytes()
    raw = raw.replace(b"element vertex", b"obj_info scanner xyz\r\n\r\ncomment c\r\nelement vertex")
    f.write_bytes(raw)
    cloud = read_ply(f)
    assert len(cloud) == 19
    np.testing.assert_array_equal(cloud.xyz, np.array([v[:3] for v in verts if v != verts[5]]))


_GOOD_HEAD = (
    "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
    "property float y\nproperty float z\nend_header\n"
)


@pytest.mark.parametrize(
    ("head", "match"),
    [
        ("plx\n" + _GOOD_HEAD[4:], "does not start with the line 'ply'"),
        (_GOOD_HEAD.replace("end_header\n", ""), "no 'end_header'"),
        (_GOOD_HEAD.replace("format binary_little_endian 1.0\n", ""), "no 'format' line"),
        (_GOOD_HEAD.replace("binary_little_endian", "binary_middle_endian"), "unsupported format"),
        (_GOOD_HEAD.replace("1.0", "2.0"), "unsupported PLY version"),
        (_GOOD_HEAD.replace("property float y", "propery float y"), "line 5.*unknown.*'propery'"),
        (_GOOD_HEAD.replace("float y", "float128 y"), "unknown property type 'float128'"),
        (_GOOD_HEAD.replace("float y", "float x"), "'x' appears twice"),
        (_GOOD_HEAD.replace("vertex 1", "vertex -1"), "not an integer >= 0"),
        (_GOOD_HEAD.replace("vertex 1", "vertex many"), "not an integer >= 0"),
        (_GOOD_HEAD.replace("element vertex 1\n", "") + "", "'property' before any 'element'"),
        (
            _GOOD_HEAD.replace("property float z", "property list float int z"),
            "count type must be an integer",
        ),
        (_GOOD_HEAD.replace("property float z", "property list uchar z"), "property list"),
        (_GOOD_HEAD.replace("vertex", "point"), "no 'vertex' element.*point"),
        (_GOOD_HEAD.replace("property float z\n", ""), "lacks the coordinate.*z"),
        (_GOOD_HEAD.replace("element vertex 1\n", "element vertex 1\nelement vertex 1\n"), "twice"),
        (_GOOD_HEAD.replace("vertex 1", "vertex 0"), "no vertices"),
        (_GOOD_HEAD.replace("format", "format format"), "expected 'format TYPE 1.0'"),
        (_GOOD_HEAD.replace("comment", "") + "", "truncated"),  # body missing: 0 of 12 bytes
    ],
)
def test_malformed_headers_name_the_problem(tmp_path: Path, head: str, match: str) -> None:
    f = tmp_path / "bad.ply"
    f.write_bytes(head.encode() + (b"" if "truncated" in match else b"\0" * 12))
    with pytest.raises(InputError, match=match) as err:
        read_cloud(f)
    assert "bad.ply" in str(err.value)


def test_non_ascii_header_and_binary_body_under_ascii(tmp_path: Path) -> None:
    f = tmp_path / "u.ply"
    f.write_bytes(_GOOD_HEAD.replace("vertex 1\n", "vertex 1\ncomment caf\xe9\n").encode("latin1"))
    with pytest.raises(InputError, match="not ASCII"):
        read_ply(f)
    g = tmp_path / "wrong.ply"
    g.write_bytes(_GOOD_HEAD.replace("binary_little_endian", "ascii").encode() + b"\xff\xfe\x00")
    with pytest.raises(InputError, match=r"non-ASCII|malformed"):
        read_ply(g)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("cut", ["vertex", "face_before"])
def test_truncated_bodies(tmp_path: Path, fmt: str, cut: str) -> None:
    """The vertex block, or a face block before it (mixed list lengths), cut short."""
    verts = _vertices(100)
    faces = _faces(100, 40, (3, 4))
    elems: list[Element] = [("vertex", [*XYZ, ("i", "uchar")], verts)]
    if cut == "face_before":
        elems.insert(0, ("face", [FACE], faces))
    f = tmp_path / "cut.ply"
    write_ply(f, fmt, elems)
    raw = f.read_bytes()
    if cut == "vertex":
        f.write_bytes(raw[: len(raw) - (len(raw) - raw.index(b"end_header")) // 3])
    else:
        head_end = raw.index(b"end_header") + len(b"end_header\n")
        f.write_bytes(raw[: head_end + 20 * (4 if fmt != "ascii" else 3)])
    with pytest.raises(InputError, match=r"cut\.ply.*truncated") as err:
        read_cloud(f)
    assert cut.split("_")[0] in str(err.value)


def test_ascii_bad_values(tmp_path: Path) -> None:
    base = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
    f = tmp_path / "a.ply"
    f.write_text(base + "property float z\nproperty uchar r\nend_header\n1 2 3 4\n1 2 3 256\n")
    with pytest.raises(InputError, match=r"vertex 1 property 'r' is 256"):
        read_ply(f)
    f.write_text(base + "property float z\nend_header\n1 2 3\n1 2\n")
    with pytest.raises(InputError, match="malformed"):
        read_ply(f)
    f.write_text(base + "property float z\nend_header\n1 2 3 9\n1 2 3 9\n")
    with pytest.raises(InputError, match="4 numbers, the header declares 3"):
        read_ply(f)
    f.write_text(base + "property float z\nend_header\n1 2 3\n1 2 zz\n")
    with pytest.raises(InputError, match="malformed"):
        read_ply(f)


def test_count_points_reads_the_ply_header(tmp_path: Path) -> None:
    f = tmp_path / "n.ply"
    write_ply(f, "binary_little_endian", [("vertex", XYZ, [v[:3] for v in _vertices(37)])])
    assert count_points(f) == 37


_TYPES = st.sampled_from(sorted(PLY_TYPES))


@settings(max_examples=60, deadline=None)
@given(
    fmt=st.sampled_from(FORMATS),
    extra=st.lists(_TYPES, max_size=4),
    order=st.permutations(range(3)),
    before=st.integers(0, 2),
    after=st.booleans(),
    n=st.integers(1, 30),
    seed=st.integers(0, 2**31),
)
def test_random_layouts(
    tmp_path_factory: pytest.TempPathFactory,
    fmt: str,
    extra: list[str],
    order: list[int],
    before: int,
    after: bool,
    n: int,
    seed: int,
) -> None:
    """Random property types and order, x/y/z of random types, elements before and after."""
    rng = np.random.default_rng(seed)
    coord_types = [str(rng.choice(["float", "double", "float32", "int", "short"])) for _ in "xyz"]
    props = [(c, coord_types[i]) for i, c in enumerate("xyz")]
    props = [props[i] for i in order] + [(f"e{k}", t) for k, t in enumerate(extra)]
    rows = []
    for _ in range(n):
        row: list[Any] = []
        for _, t in props:
            code = PLY_TYPES[t]
            if code[0] == "f":
                row.append(float(np.asarray(rng.normal(0, 100), dtype=code)))
            else:
                info = np.iinfo(code)
                row.append(int(rng.integers(info.min, int(info.max) + 1)))
        rows.append(row)
    elems: list[Element] = [("vertex", props, rows)]
    for k in range(before):
        elems.insert(0, (f"pre{k}", [FACE, ("q", "double")], [[[1, 2, 3][: k + 1], 0.5]] * 3))
    if after:
        elems.append(("face", [FACE], _faces(n, 5, (3, 4))))
    f = tmp_path_factory.mktemp("ply") / "r.ply"
    write_ply(f, fmt, elems)
    cloud = read_ply(f)
    names = [p[0] for p in props]
    want = np.array([[r[names.index(c)] for c in "xyz"] for r in rows], dtype=np.float64)
    np.testing.assert_array_equal(cloud.xyz, want)
    for k, t in enumerate(extra):
        col = cloud.fields[f"e{k}"]
        assert col.dtype == np.dtype(PLY_TYPES[t])
        np.testing.assert_array_equal(col, [r[names.index(f"e{k}")] for r in rows])


@pytest.mark.parametrize("fmt", FORMATS)
def test_agrees_with_plyfile_on_a_mesh(tmp_path: Path, fmt: str) -> None:
    """Cross-check against another implementation (plyfile writes, we read)."""
    plyfile = pytest.importorskip("plyfile")
    rng = np.random.default_rng(5)
    v = np.empty(400, dtype=[("x", "f4"), ("y", "f4"), ("z", "f8"), ("red", "u1"), ("t", "f8")])
    for c in ("x", "y", "z", "t"):
        v[c] = rng.normal(0, 10, 400)
    v["red"] = rng.integers(0, 256, 400)
    faces = np.empty(100, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [rng.integers(0, 400, 3 + (k % 2)).astype("i4") for k in range(100)]
    f = tmp_path / "pf.ply"
    els = [plyfile.PlyElement.describe(faces, "face"), plyfile.PlyElement.describe(v, "vertex")]
    plyfile.PlyData(
        els, text=fmt == "ascii", byte_order=">" if fmt.endswith("big_endian") else "<"
    ).write(str(f))
    cloud = read_ply(f)
    theirs = plyfile.PlyData.read(str(f))["vertex"].data
    for c in ("x", "y", "z"):
        np.testing.assert_array_equal(cloud.xyz[:, "xyz".index(c)], theirs[c].astype(np.float64))
    for c in ("red", "t"):
        np.testing.assert_array_equal(cloud.fields[c], theirs[c])
        assert cloud.fields[c].dtype == np.dtype(theirs[c].dtype).newbyteorder("=")


def test_reading_does_not_need_plyfile(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """stemmap is MIT licensed and must not use the GPL-3 plyfile: with its import blocked,
    PLY files of every format still read."""
    import sys

    monkeypatch.setitem(sys.modules, "plyfile", None)  # `import plyfile` now raises
    with pytest.raises(ImportError):
        import plyfile  # noqa: F401
    for fmt in FORMATS:
        f = tmp_path / f"{fmt}.ply"
        write_ply(f, fmt, [("vertex", XYZ, [[1.0, 2.0, 3.0]]), ("face", [FACE], [[[0, 0, 0]]])])
        np.testing.assert_array_equal(read_cloud(f).xyz, [[1.0, 2.0, 3.0]])
