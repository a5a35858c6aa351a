"""TIFF and Netpbm camera frames of the calibrated size whose pixel data is cut or whose header
points past the end of the file: one error naming the file and what is missing, before
OpenCV sees it.

Before: a cut TIFF strip, a TIFF whose strips point past the end, a PPM with a short body or
only a header gave "not a readable image" after libtiff / OpenCV printed their own
``[ERROR]`` lines on stderr, and a TIFF whose StripOffsets entry announced 2^32 - 1 values
was decoded without a word. The check reads the strip/tile offsets and byte counts of IFD 0
(TIFF 6.0, section 3) and the Netpbm header's size, depth and maxval (netpbm.sourceforge.net)
and compares them with the file's length; 14 of these 25 cases fail on main.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.io.camera_frames import read_camera_frames, write_camera_frames
from stemmap.odometry.visual import StereoCalibration, VisualFrame

W, H = 64, 48
RNG = np.random.default_rng(3)
IMG = RNG.integers(0, 255, (H, W, 3), dtype=np.uint8)


def _folder(root: Path) -> Path:
    frames = [VisualFrame(0.1 * k, IMG, depth=RNG.uniform(1.0, 5.0, (H, W))) for k in range(3)]
    write_camera_frames(root, frames, StereoCalibration(50.0, 50.0, 31.5, 23.5, W, H))
    return root


def _rgb_as(root: Path, suffix: str, frame1: bytes) -> None:
    """rgb/ frames 0 and 2: IMG written by OpenCV as ``suffix``; frame 1: ``frame1``."""
    for p in (root / "rgb").iterdir():
        p.unlink()
    ok, good = cv2.imencode(suffix, IMG[..., ::-1])  # OpenCV writes BGR
    assert ok
    for k in range(3):
        (root / "rgb" / f"{k:06d}{suffix}").write_bytes(frame1 if k == 1 else good.tobytes())


def _tiff(
    rows_per_strip: int, *, deflate: bool, bo: str = "<", strip_offset_shift: int = 0
) -> bytes:
    """An RGB TIFF of IMG written by hand: IFD first, then the strips (so a cut keeps the
    IFD), StripOffsets / StripByteCounts stored out of line when there are several strips."""
    strips = []
    for r0 in range(0, H, rows_per_strip):
        raw = IMG[r0 : r0 + rows_per_strip].tobytes()
        strips.append(zlib.compress(raw, 9) if deflate else raw)
    n = len(strips)
    n_entries = 10
    ifd_len = 2 + 12 * n_entries + 4
    arrays_at = 8 + ifd_len
    arrays_len = 8 * n if n > 1 else 0
    data_at = arrays_at + arrays_len
    offsets, at = [], data_at
    for s in strips:
        offsets.append(at + strip_offset_shift)
        at += len(s)
    counts = [len(s) for s in strips]
    if n > 1:
        arrays = struct.pack(f"{bo}{n}I", *offsets) + struct.pack(f"{bo}{n}I", *counts)
        off_value, cnt_value = arrays_at, arrays_at + 4 * n
    else:
        arrays, off_value, cnt_value = b"", offsets[0], counts[0]
    entries = [  # tag, type (3 SHORT, 4 LONG), count, value
        (256, 4, 1, W),
        (257, 4, 1, H),
        (258, 3, 1, 8),
        (259, 3, 1, 8 if deflate else 1),
        (262, 3, 1, 2),
        (273, 4, n, off_value),
        (277, 3, 1, 3),
        (278, 4, 1, rows_per_strip),
        (279, 4, n, cnt_value),
        (284, 3, 1, 1),
    ]
    assert len(entries) == n_entries
    ifd = struct.pack(bo + "H", n_entries)
    for tag, ftype, count, value in entries:
        packed = struct.pack(bo + ("H" if ftype == 3 and count == 1 else "I"), value)
        ifd += struct.pack(bo + "HHI", tag, ftype, count) + packed.ljust(4, b"\0")
    head = (b"II*\0" if bo == "<" else b"MM\0*") + struct.pack(bo + "I", 8)
    return head + ifd + struct.pack(bo + "I", 0) + arrays + b"".join(strips)


@pytest.mark.parametrize("deflate", [False, True])
@pytest.mark.parametrize("rows_per_strip", [H, 8])
@pytest.mark.parametrize("bo", ["<", ">"])
def test_hand_made_tiffs_decode_to_the_image(
    tmp_path: Path, deflate: bool, rows_per_strip: int, bo: str
) -> None:
    root = _folder(tmp_path)
    _rgb_as(root, ".tif", _tiff(rows_per_strip, deflate=deflate, bo=bo))
    frames = list(read_camera_frames(root))
    assert np.array_equal(frames[1].left, IMG)  # the builder is right, so the cuts below are
    assert np.array_equal(frames[0].left, IMG)  # the only thing wrong with them


@pytest.mark.parametrize("deflate", [False, True])
@pytest.mark.parametrize("rows_per_strip", [H, 8])
def test_a_tiff_cut_in_its_strips_is_an_error(
    tmp_path: Path, deflate: bool, rows_per_strip: int
) -> None:
    # before (deflate, one strip): the frame decoded all black, no word
    root = _folder(tmp_path)
    data = _tiff(rows_per_strip, deflate=deflate)
    _rgb_as(root, ".tif", data[: len(data) - 100])
    with pytest.raises(InputError, match=r"000001\.tif: truncated TIFF \(strip \d+ at byte"):
        list(read_camera_frames(root))


def test_a_tiff_whose_strips_point_past_the_end_is_an_error(tmp_path: Path) -> None:
    root = _folder(tmp_path)
    _rgb_as(root, ".tif", _tiff(8, deflate=True, strip_offset_shift=10**6))
    with pytest.raises(InputError, match=r"000001\.tif: truncated TIFF"):
        list(read_camera_frames(root))


def test_a_tiff_without_strip_or_tile_offsets_is_an_error(tmp_path: Path) -> None:
    root = _folder(tmp_path)
    data = bytearray(_tiff(H, deflate=False))
    at = 8 + 2 + 12 * 5  # the 6th entry, StripOffsets: retag it as an unknown private tag
    assert struct.unpack_from("<H", data, at)[0] == 273
    struct.pack_into("<H", data, at, 65000)
    _rgb_as(root, ".tif", bytes(data))
    with pytest.raises(InputError, match=r"000001\.tif: damaged TIFF \(no StripOffsets"):
        list(read_camera_frames(root))


def test_a_tiff_announcing_a_huge_offsets_array_is_an_error(tmp_path: Path) -> None:
    # a StripOffsets count of 2^32 - 1: refused from the file length, nothing allocated
    root = _folder(tmp_path)
    data = bytearray(_tiff(8, deflate=False))
    at = 8 + 2 + 12 * 5
    struct.pack_into("<I", data, at + 4, 2**32 - 1)
    _rgb_as(root, ".tif", bytes(data))
    with pytest.raises(InputError, match=r"000001\.tif: truncated TIFF"):
        list(read_camera_frames(root))


PPM = b"P6\n%d %d\n255\n" % (W, H) + IMG.tobytes()


@pytest.mark.parametrize(
    ("name", "data", "missing"),
    [
        ("P6 cut", PPM[:-1], 1),
        ("P6 header only", PPM[: PPM.index(b"255\n") + 4], W * H * 3),
        ("P5 16-bit cut", b"P5\n%d %d\n65535\n" % (W, H) + bytes(W * H * 2 - 10), 10),
        ("P6 16-bit with 8-bit data", b"P6 %d %d 1023\n" % (W, H) + bytes(W * H * 3), W * H * 3),
        ("P4 cut", b"P4\n%d %d\n" % (W, H) + bytes(W // 8 * H - 1), 1),
        (
            "P7 cut",
            b"P7\nWIDTH %d\nHEIGHT %d\nDEPTH 3\nMAXVAL 255\nTUPLTYPE RGB\nENDHDR\n" % (W, H)
            + bytes(W * H * 3 - 5),
            5,
        ),
    ],
    ids=lambda v: v if isinstance(v, str) else "",
)
def test_a_netpbm_frame_with_a_short_body_is_an_error(
    tmp_path: Path, name: str, data: bytes, missing: int
) -> None:
    root = _folder(tmp_path)
    _rgb_as(root, ".ppm", data)
    with pytest.raises(
        InputError, match=rf"000001\.ppm: truncated Netpbm .*; {missing:,} bytes? short"
    ):
        list(read_camera_frames(root))


@pytest.mark.parametrize(
    "data",
    [
        PPM,
        b"P6 # a comment\n%d\n%d\n255\n" % (W, H) + IMG.tobytes(),
        b"P3\n%d %d\n255\n" % (W, H) + b" ".join(b"%d" % v for v in IMG.ravel()) + b"\n",
    ],
    ids=["P6", "P6 comments", "P3 ascii"],
)
def test_intact_netpbm_frames_read(tmp_path: Path, data: bytes) -> None:
    root = _folder(tmp_path)
    _rgb_as(root, ".ppm", data)
    frames = list(read_camera_frames(root))
    assert np.array_equal(frames[1].left, IMG)


def test_an_ascii_ppm_with_too_few_samples_is_an_error(tmp_path: Path) -> None:
    root = _folder(tmp_path)
    samples = b" ".join(b"%d" % v for v in IMG.ravel()[:-7])
    _rgb_as(root, ".ppm", b"P3\n%d %d\n255\n" % (W, H) + samples + b"\n")
    with pytest.raises(InputError, match=r"000001\.ppm: truncated Netpbm .*7 samples short"):
        list(read_camera_frames(root))
