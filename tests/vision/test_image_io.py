"""Safe image reading: pixel limit from the header (before decoding), damaged files refused."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import InputError
from stemmap.vision import image_io
from stemmap.vision.image_io import image_header, read_image

RUNNER = CliRunner()


def _chunk(ctype: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", zlib.crc32(ctype + data))


def _solid_png_1bit(width: int, height: int) -> bytes:
    """A valid solid-black 1-bit greyscale PNG, compressed row by row (small on disk)."""
    row = b"\x00" + bytes((width + 7) // 8)
    comp = zlib.compressobj(9)
    idat = b"".join(comp.compress(row) for _ in range(height)) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )


def _photo(h: int = 150, w: int = 200) -> np.ndarray:
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 2)
    return np.asarray(img, dtype=np.uint8)


def test_huge_png_refused_from_header_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    big = tmp_path / "big.png"
    big.write_bytes(_solid_png_1bit(20000, 20000))
    assert big.stat().st_size < 2_000_000  # a decompression bomb: 400 Mpx from < 2 MB
    assert image_header(big.read_bytes(), big) == ("png", 20000, 20000)

    def no_decode(*_a: object, **_k: object) -> None:
        raise AssertionError("decoded despite the pixel limit")

    monkeypatch.setattr(image_io.cv2, "imdecode", no_decode)
    with pytest.raises(InputError, match="exceeds the limit"):
        read_image(big)
    res = RUNNER.invoke(app, ["segment", str(big), "--out", str(tmp_path / "m.png")])
    text = " ".join(res.output.split())
    assert res.exit_code == 2 and "error:" in text and "400,000,000 pixels" in text
    assert not (tmp_path / "m.png").exists()


def test_max_pixels_option(tmp_path: Path) -> None:
    f = tmp_path / "p.png"
    cv2.imwrite(str(f), _photo())
    assert read_image(f).shape == (150, 200, 3)
    with pytest.raises(InputError, match="30,000 pixels exceeds the limit of 29,999"):
        read_image(f, max_pixels=29_999)
    res = RUNNER.invoke(
        app, ["segment", str(f), "--out", str(tmp_path / "m.png"), "--max-pixels", "1000"]
    )
    assert res.exit_code == 2 and "exceeds the limit" in " ".join(res.output.split())


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_truncated_image_is_an_error(tmp_path: Path, ext: str) -> None:
    img = _photo()
    ok, buf = cv2.imencode(ext, img)
    assert ok
    data = buf.tobytes()
    whole = tmp_path / f"whole{ext}"
    whole.write_bytes(data)
    rgb = read_image(whole)
    assert np.array_equal(rgb, cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
    cut = tmp_path / f"cut{ext}"
    cut.write_bytes(data[: len(data) // 2])
    # OpenCV alone decodes the cut JPEG into a complete-looking image: the reader must not
    with pytest.raises(InputError, match="truncated"):
        read_image(cut)
    res = RUNNER.invoke(app, ["segment", str(cut), "--out", str(tmp_path / "m.png")])
    assert res.exit_code == 2 and "truncated" in " ".join(res.output.split())


def test_damaged_png_crc_and_jpeg_trailer(tmp_path: Path) -> None:
    _, buf = cv2.imencode(".png", _photo())
    data = bytearray(buf.tobytes())
    data[60] ^= 0xFF  # inside IDAT
    bad = tmp_path / "bad.png"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match="CRC"):
        read_image(bad)
    _, jbuf = cv2.imencode(".jpg", _photo())
    trailer = tmp_path / "trailer.jpg"  # some cameras append data after EOI: still complete
    trailer.write_bytes(jbuf.tobytes() + b"\x00" * 100)
    assert read_image(trailer).shape == (150, 200, 3)
    other = tmp_path / "x.gif"
    other.write_bytes(b"GIF89a" + bytes(20))
    with pytest.raises(InputError, match="not a PNG, JPEG or BMP"):
        read_image(other)


def test_a_folder_is_named_as_a_folder(tmp_path: Path) -> None:
    """Issue 13: a folder was reported as "does not exist"."""
    with pytest.raises(InputError, match="is a folder"):
        read_image(tmp_path)
