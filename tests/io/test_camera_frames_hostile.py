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
