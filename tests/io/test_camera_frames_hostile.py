"""Camera frames folders with a frame of another size, a bomb or a cut file: refused from the
header, before decoding (``stemmap odometry --camera``, ``map --motion visual|fused``).

Before, every frame was decoded first: a 30000 x 30000 PNG (2.6 MB on disk) in ``rgb/`` took
5.5 GB and 50 s before the size check, a JPEG cut in half decoded into grey rows without a
word, and a depth ``.npy`` announcing a huge shape was allocated at that shape.
"""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.lib import format as npy_format

from stemmap.errors import InputError
from stemmap.io.camera_frames import read_camera_frames, write_camera_frames
from stemmap.odometry.visual import StereoCalibration, VisualFrame

W, H = 64, 48


def _folder(root: Path, n: int = 3) -> Path:
    rng = np.random.default_rng(0)
    frames = [
        VisualFrame(
            0.1 * k,
            rng.integers(0, 255, (H, W, 3), dtype=np.uint8),
            depth=rng.uniform(1.0, 5.0, (H, W)),
        )
        for k in range(n)
    ]
    write_camera_frames(root, frames, StereoCalibration(50.0, 50.0, 31.5, 23.5, W, H))
    return root


def _png_header_only(w: int, h: int) -> bytes:
    """A complete, tiny PNG whose IHDR announces w x h pixels (its IDAT holds one row)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\0" + b"\0" * 3 * w)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_intact_folder_reads(tmp_path: Path) -> None:
    frames = list(read_camera_frames(_folder(tmp_path)))
    assert len(frames) == 3 and frames[0].left.shape == (H, W, 3)
    assert frames[0].depth is not None and frames[0].depth.shape == (H, W)


def test_bomb_is_refused_from_its_header(tmp_path: Path) -> None:
    root = _folder(tmp_path)
    (root / "rgb" / "000001.png").write_bytes(_png_header_only(30000, 30000))
    it = iter(read_camera_frames(root))
    next(it)
    with pytest.raises(InputError, match=r"000001\.png: image is 30000 x 30000, camera\.json"):
        next(it)


def test_cut_jpeg_is_an_error(tmp_path: Path) -> None:
    root = _folder(tmp_path)
    img = np.random.default_rng(1).integers(0, 255, (H, W, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    for p in (root / "rgb").iterdir():
        p.unlink()
    for k in range(3):
        data = buf.tobytes()
        (root / "rgb" / f"{k:06d}.jpg").write_bytes(data[: len(data) // 2] if k == 2 else data)
    with pytest.raises(InputError, match=r"000002\.jpg: truncated JPEG"):
        list(read_camera_frames(root))


def test_depth_npy_announcing_a_huge_shape(tmp_path: Path) -> None:
    root = _folder(tmp_path)
    for k, p in enumerate(sorted((root / "depth").iterdir())):
        p.unlink()
        np.save(root / "depth" / f"{k:06d}.npy", np.full((H, W), 2.0))
    frames = list(read_camera_frames(root))  # .npy depth in metres reads
    assert np.allclose(frames[0].depth, 2.0)
    head = io.BytesIO()
    npy_format.write_array_header_1_0(
        head, {"descr": "<f8", "fortran_order": False, "shape": (10**6, 10**6)}
    )
    (root / "depth" / "000000.npy").write_bytes(head.getvalue() + b"\0" * 64)
    with pytest.raises(InputError, match=r"000000\.npy"):
        list(read_camera_frames(root))


def _tiff(w: int, h: int, *, big_endian: bool = False, data: int = 8) -> bytes:
    """An uncompressed grey TIFF whose IFD 0 announces w x h pixels, in one strip that holds
    ``data`` bytes (w * h for a complete image)."""
    bo = ">" if big_endian else "<"
    entries = [  # tag, type (3 SHORT, 4 LONG), value
        (256, 4, w),
        (257, 4, h),
        (258, 3, 8),
        (259, 3, 1),
        (262, 3, 1),
        (273, 4, 8 + 2 + 12 * 9 + 4),
        (277, 3, 1),
        (278, 4, h),
        (279, 4, data),
    ]
    ifd = struct.pack(bo + "H", len(entries))
    for tag, ftype, value in entries:
        packed = struct.pack(bo + ("H" if ftype == 3 else "I"), value).ljust(4, b"\0")
        ifd += struct.pack(bo + "HHI", tag, ftype, 1) + packed
    head = (b"MM\0*" if big_endian else b"II*\0") + struct.pack(bo + "I", 8)
    return head + ifd + struct.pack(bo + "I", 0) + b"\x80" * data


def _rgb_as(root: Path, suffix: str, encode) -> None:
    """Replace the folder's rgb/ frames by ``encode(k)`` bytes named 00000k``suffix``."""
    for p in (root / "rgb").iterdir():
        p.unlink()
    for k in range(3):
        (root / "rgb" / f"{k:06d}{suffix}").write_bytes(encode(k))


@pytest.mark.parametrize("big_endian", [False, True])
def test_tiff_bomb_is_refused_from_its_header(tmp_path: Path, big_endian: bool) -> None:
    # before: a 130-byte TIFF announcing 30000 x 30000 was handed to OpenCV (its own limit is
    # 2^30 pixels), which allocated the image before finding one strip of data
    root = _folder(tmp_path)
    img = np.random.default_rng(1).integers(0, 255, (H, W, 3), dtype=np.uint8)
    ok, good = cv2.imencode(".tif", img)
    assert ok
    _rgb_as(root, ".tif", lambda k: good.tobytes() if k else _tiff(W, H, data=W * H))
    # the hand-made TIFF decodes (so the bomb below differs from it only in its header)
    assert next(iter(read_camera_frames(root))).left.shape[:2] == (H, W)
    _rgb_as(
        root,
        ".tif",
        lambda k: good.tobytes() if k != 1 else _tiff(30000, 30000, big_endian=big_endian),
    )
    with pytest.raises(InputError, match=r"000001\.tif: image is 30000 x 30000, camera\.json"):
        list(read_camera_frames(root))


@pytest.mark.parametrize(
    "header",
    [b"P5\n30000 30000\n255\n", b"P5 # comment\n30000\n30000 255\n", b"P6\n30000 30000 255\n"],
)
def test_pgm_bomb_is_refused_from_its_header(tmp_path: Path, header: bytes) -> None:
    root = _folder(tmp_path)
    good = b"P6\n%d %d\n255\n" % (W, H) + bytes(W * H * 3)
    assert cv2.imdecode(np.frombuffer(good, np.uint8), cv2.IMREAD_UNCHANGED).shape == (H, W, 3)
    _rgb_as(root, ".ppm", lambda k: good if k != 2 else header + bytes(16))
    with pytest.raises(InputError, match=r"000002\.ppm: image is 30000 x 30000, camera\.json"):
        list(read_camera_frames(root))
    _rgb_as(root, ".ppm", lambda k: good)
    assert len(list(read_camera_frames(root))) == 3


def test_unknown_content_under_an_image_name_is_refused(tmp_path: Path) -> None:
    root = _folder(tmp_path)
    _rgb_as(root, ".png", lambda k: b"RIFF\0\0\0\0WEBPVP8 " + bytes(64))
    with pytest.raises(InputError, match=r"not a PNG, JPEG, BMP, TIFF or Netpbm"):
        list(read_camera_frames(root))


def test_camera_json_announcing_a_huge_frame_is_refused(tmp_path: Path) -> None:
    import json

    root = _folder(tmp_path)
    cfg = json.loads((root / "camera.json").read_text())
    cfg.update(width=30000, height=30000)
    (root / "camera.json").write_text(json.dumps(cfg))
    with pytest.raises(InputError, match=r"30000 x 30000, but a camera frame must have 1 to"):
        read_camera_frames(root)
