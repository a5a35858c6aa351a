"""Safe reading of photos: size checked from the header before decoding, damage detected.

A 1 MB PNG can decode to 20000 x 20000 pixels (1.2 GB of RGB, several GB during processing),
and OpenCV decodes a JPEG cut in half into a complete-looking image (grey bottom rows) without
complaint. :func:`read_image` therefore

1. reads the width and height from the file header (PNG IHDR, JPEG SOFn, BMP info header)
   without decoding, and refuses more than ``max_pixels`` (``stemmap segment --max-pixels``);
2. checks the container is complete: PNG chunks walked to IEND with their CRCs, JPEG entropy
   data followed by its EOI marker, BMP file size against its header (camera frames also:
   every TIFF strip or tile inside the file, the pixels a Netpbm header announces present);
3. decodes and checks the decoded size equals the header's.

:func:`image_header` also reads TIFF (IFD 0) and Netpbm headers for camera frame folders
(:mod:`stemmap.io.camera_frames`), where frames are checked against camera.json's size.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError

__all__ = [
    "DEFAULT_MAX_PIXELS",
    "check_complete",
    "image_format",
    "image_header",
    "read_image",
]

#: Default pixel limit (100 Mpx: a 12-24 Mpx phone photo passes; 400 Mpx bombs do not).
DEFAULT_MAX_PIXELS = 100_000_000

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
# SOF markers carry the frame size; C4 (DHT), C8 (JPG), CC (DAC) are not frames.
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_format(data: bytes) -> str:
    """'png', 'jpeg', 'bmp', 'tiff', 'pnm' (Netpbm) or 'unknown', from the first bytes."""
    if data.startswith(_PNG_SIG):
        return "png"
    if data.startswith(b"\xff\xd8"):
        return "jpeg"
    if data.startswith(b"BM"):
        return "bmp"
    if data[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"):
        return "tiff"
    if len(data) >= 2 and data[0:1] == b"P" and data[1:2] in b"1234567":
        return "pnm"
    return "unknown"


# TIFF field types whose value is an unsigned integer: SHORT, LONG, LONG8 (BigTIFF)
_TIFF_UINT = {3: "H", 4: "I", 16: "Q"}
# IFD tags: ImageWidth, ImageLength; StripOffsets / StripByteCounts; TileOffsets / TileByteCounts
_TIFF_OFFSETS = ((273, 279, "strip"), (324, 325, "tile"))


class _Ifd:
    """IFD 0 of a TIFF (TIFF 6.0, section 2; BigTIFF: 8-byte offsets and counts, 20-byte
    entries): each tag's field type, count and the byte position of its value field."""

    def __init__(self, data: bytes, path: Path) -> None:
        self.data, self.path = data, path
        self.bo = "<" if data[:2] == b"II" else ">"
        big = data[2:4] in (b"+\0", b"\0+")
        self.vfmt = 8 if big else 4  # bytes of an entry's value field
        self.tags: dict[int, tuple[int, int, int]] = {}
        try:
            if big:
                (ifd,) = struct.unpack_from(self.bo + "Q", data, 8)
                (n,) = struct.unpack_from(self.bo + "Q", data, ifd)
                first, entry, cfmt = ifd + 8, 20, "HHQ"
            else:
                (ifd,) = struct.unpack_from(self.bo + "I", data, 4)
                (n,) = struct.unpack_from(self.bo + "H", data, ifd)
                first, entry, cfmt = ifd + 2, 12, "HHI"
            if first + n * entry > len(data):
                raise struct.error("IFD past the end")
            for k in range(n):
                at = first + k * entry
                tag, ftype, count = struct.unpack_from(self.bo + cfmt, data, at)
                self.tags.setdefault(tag, (ftype, count, at + entry - self.vfmt))
        except struct.error:
            raise InputError(
                f"{path}: damaged or truncated TIFF (its first IFD is unreadable)."
            ) from None

    def values(self, tag: int) -> NDArray[np.int64] | None:
        """The unsigned integer values of ``tag`` (None when IFD 0 lacks it), read in place or
        from the offset the entry holds; an array running past the end of the file is
        reported before anything is allocated."""
        if tag not in self.tags:
            return None
        ftype, count, at = self.tags[tag]
        if ftype not in _TIFF_UINT:
            raise InputError(f"{self.path}: damaged TIFF (tag {tag} has field type {ftype}).")
        code = _TIFF_UINT[ftype]
        nbytes = count * struct.calcsize(code)
        if nbytes > self.vfmt:  # the entry holds the array's offset
            (at,) = struct.unpack_from(self.bo + ("Q" if self.vfmt == 8 else "I"), self.data, at)
        if at + nbytes > len(self.data):
            raise InputError(
                f"{self.path}: truncated TIFF (the {count:,} values of tag {tag} at byte {at} "
                f"need {nbytes:,} bytes; the file has {len(self.data):,})."
            )
        dtype = np.dtype(self.bo + code)  # "<H", ">I", ...
        return np.frombuffer(self.data, dtype, count, at).astype(np.int64)


def _tiff_size(data: bytes, path: Path) -> tuple[int, int]:
    """(width, height) of a TIFF's first image: ImageWidth (256) and ImageLength (257) of
    IFD 0. What OpenCV decodes is that first image."""
    ifd = _Ifd(data, path)
    size = {}
    for tag in (256, 257):
        if tag in ifd.tags and ifd.tags[tag][1] == 1:
            size[tag] = int(ifd.values(tag)[0])  # type: ignore[index]
    if len(size) < 2:
        raise InputError(f"{path}: damaged TIFF (no ImageWidth / ImageLength in its first IFD).")
    return size[256], size[257]


def _tiff_check_complete(data: bytes, path: Path) -> None:
    """Every strip (or tile) of IFD 0 lies inside the file: offset + byte count <= file size.
    A cut file or a header pointing past the end would otherwise reach libtiff, which reports
    it on stderr and leaves OpenCV with no image, or with the rows it could read."""
    ifd = _Ifd(data, path)
    for off_tag, cnt_tag, what in _TIFF_OFFSETS:
        offsets = ifd.values(off_tag)
        if offsets is None:
            continue
        counts = ifd.values(cnt_tag)
        if counts is None:  # libtiff estimates them for uncompressed data: check the starts
            counts = np.zeros_like(offsets)
        if counts.shape != offsets.shape:
            raise InputError(
                f"{path}: damaged TIFF ({offsets.size} {what} offsets but {counts.size} "
                "byte counts)."
            )
        short = np.flatnonzero(offsets + counts > len(data))
        if short.size:
            k = int(short[0])
            raise InputError(
                f"{path}: truncated TIFF ({what} {k} at byte {int(offsets[k])} needs "
                f"{int(counts[k]):,} bytes; the file ends "
                f"{int(offsets[k] + counts[k]) - len(data):,} bytes short of it). The file was "
                "cut short (e.g. an interrupted copy) or its header is damaged."
            )
        return
    raise InputError(f"{path}: damaged TIFF (no StripOffsets or TileOffsets in its first IFD).")


_PNM_WHITESPACE = b" \t\n\v\f\r"


def _pnm_layout(data: bytes, path: Path) -> tuple[int, int, int, int, int]:
    """(width, height, header length, samples per pixel, bytes per sample) of a Netpbm image:
    P1-P6 (whitespace-separated width, height and maxval after the magic, ``#`` comments to
    the end of a line, one whitespace byte before the pixels) or P7 (PAM: ``WIDTH``,
    ``HEIGHT``, ``DEPTH``, ``MAXVAL`` lines up to ``ENDHDR``); netpbm.sourceforge.net/doc.
    Bytes per sample is 0 for the plain (ascii) formats P1-P3 and for the bitmap P4, whose
    rows are ceil(width / 8) bytes."""
    kind = data[1:2]
    if kind == b"7":
        end = data.find(b"ENDHDR", 0, 4096)
        if end < 0:
            raise InputError(f"{path}: damaged PAM header (no ENDHDR in its first 4 kB).")
        fields = dict(
            ln.split(None, 1)
            for ln in data[:end].splitlines()[1:]
            if len(ln.split(None, 1)) == 2 and not ln.startswith(b"#")
        )
        try:
            w, h = int(fields[b"WIDTH"]), int(fields[b"HEIGHT"])
            depth = int(fields.get(b"DEPTH", b"1"))
            maxval = int(fields.get(b"MAXVAL", b"255"))
        except (KeyError, ValueError):
            raise InputError(f"{path}: damaged PAM header (no WIDTH / HEIGHT).") from None
        return w, h, end + len(b"ENDHDR") + 1, depth, _pnm_sample_bytes(maxval, path)
    n_fields = 2 if kind in (b"1", b"4") else 3
    tokens: list[bytes] = []
    pos, n = 2, min(len(data), 4096)
    while len(tokens) < n_fields and pos < n:
        c = data[pos : pos + 1]
        if c in _PNM_WHITESPACE:
            pos += 1
        elif c == b"#":
            eol = data.find(b"\n", pos)
            pos = n if eol < 0 else eol + 1
        else:
            start = pos
            while pos < n and data[pos : pos + 1] not in _PNM_WHITESPACE + b"#":
                pos += 1
            tokens.append(data[start:pos])
    try:
        w, h = int(tokens[0]), int(tokens[1])
        maxval = int(tokens[2]) if n_fields == 3 else 1
    except (IndexError, ValueError):
        raise InputError(f"{path}: damaged Netpbm header (no width and height).") from None
    channels = 3 if kind in (b"3", b"6") else 1
    plain = kind in (b"1", b"2", b"3")
    nbytes = 0 if plain or kind == b"4" else _pnm_sample_bytes(maxval, path)
    return w, h, pos + 1, channels, nbytes


def _pnm_sample_bytes(maxval: int, path: Path) -> int:
    if not 1 <= maxval <= 65535:
        raise InputError(f"{path}: damaged Netpbm header (maxval {maxval}, not 1..65535).")
    return 1 if maxval < 256 else 2


def _pnm_size(data: bytes, path: Path) -> tuple[int, int]:
    w, h, *_ = _pnm_layout(data, path)
    return w, h


def _count(n: int, unit: str) -> str:
    return f"{n:,} {unit}{'' if n == 1 else 's'}"


def _pnm_check_complete(data: bytes, path: Path) -> None:
    """The pixels after a Netpbm header are all there: width x height x samples x bytes for
    the binary formats (P4: height rows of ceil(width / 8) bytes), as many numbers for the
    plain ones (P1: one digit per pixel, no separator needed)."""
    w, h, start, channels, nbytes = _pnm_layout(data, path)
    kind = data[:2].decode("latin-1")
    body = memoryview(data)[start:]
    if kind in ("P1", "P2", "P3"):
        arr = np.frombuffer(body, np.uint8)
        if kind == "P1":
            have = int(np.count_nonzero((arr == ord("0")) | (arr == ord("1"))))
        else:
            word = ~np.isin(arr, np.frombuffer(_PNM_WHITESPACE, np.uint8))
            have = int(np.count_nonzero(word[1:] & ~word[:-1])) + int(word[:1].sum())
        need = w * h * channels
        if have < need:
            raise InputError(
                f"{path}: truncated Netpbm ({kind}, {w} x {h}: the pixels need {need:,} "
                f"samples after the header, the file holds {have:,}; "
                f"{_count(need - have, 'sample')} short)."
            )
        return
    need = (w + 7) // 8 * h if kind == "P4" else w * h * channels * nbytes
    if len(body) < need:
        raise InputError(
            f"{path}: truncated Netpbm ({kind}, {w} x {h}: the pixels need {need:,} bytes after "
            f"the header, the file holds {len(body):,}; {_count(need - len(body), 'byte')} "
            "short). The file was cut short or its header is damaged."
        )


def _jpeg_frame(data: bytes, path: Path) -> tuple[int, int, int]:
    """(width, height, offset of the first SOS segment) from the JPEG marker stream."""
    pos, n = 2, len(data)
    size: tuple[int, int] | None = None
    while pos + 4 <= n:
        if data[pos] != 0xFF:
            raise InputError(f"{path}: damaged JPEG header (no marker at byte {pos}).")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        if length < 2 or pos + 2 + length > n:
            raise InputError(f"{path}: truncated JPEG (segment at byte {pos} runs past the end).")
        if marker in _SOF:
            if length < 7:
                raise InputError(f"{path}: damaged JPEG frame header.")
            h, w = struct.unpack(">HH", data[pos + 5 : pos + 9])
            size = (w, h)
        if marker == 0xDA:  # start of scan: entropy-coded data follows
            if size is None:
                raise InputError(f"{path}: JPEG without a frame header (SOF) before its data.")
            return size[0], size[1], pos + 2 + length
        pos += 2 + length
    raise InputError(f"{path}: truncated JPEG (header ends before the image data).")


def _png_size_and_check(data: bytes, path: Path, *, full: bool) -> tuple[int, int]:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise InputError(f"{path}: damaged PNG (no IHDR chunk).")
    w, h = struct.unpack(">II", data[16:24])
    if not full:
        return w, h
    pos, n = 8, len(data)
    while True:
        if pos + 12 > n:
            raise InputError(
                f"{path}: truncated PNG ({n} bytes; the data stops inside chunk at byte {pos}, "
                "no IEND)."
            )
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        ctype = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > n:
            raise InputError(
                f"{path}: truncated PNG (chunk {ctype.decode('latin-1')!r} at byte {pos} needs "
                f"{length} bytes, the file ends {end - n} bytes short)."
            )
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(data[pos + 4 : end - 4]) != crc:
            raise InputError(
                f"{path}: damaged PNG (CRC error in chunk {ctype.decode('latin-1')!r} at byte "
                f"{pos})."
            )
        if ctype == b"IEND":
            return w, h
        pos = end


def image_header(data: bytes, path: Path, *, frames: bool = False) -> tuple[str, int, int]:
    """(format, width, height) from the header bytes, without decoding.

    PNG, JPEG and BMP; with ``frames`` (camera frame folders) also TIFF and Netpbm (PGM, PPM,
    PBM, PAM), which :func:`read_image` does not take."""
    fmt = image_format(data)
    if fmt == "png":
        w, h = _png_size_and_check(data, path, full=False)
    elif fmt == "jpeg":
        w, h, _ = _jpeg_frame(data, path)
    elif fmt == "bmp":
        if len(data) < 26:
            raise InputError(f"{path}: truncated BMP header.")
        w, h = struct.unpack("<ii", data[18:26])
        w, h = abs(w), abs(h)
    elif fmt == "tiff" and frames:
        w, h = _tiff_size(data, path)
    elif fmt == "pnm" and frames:
        w, h = _pnm_size(data, path)
    else:
        kinds = "PNG, JPEG, BMP, TIFF or Netpbm (PGM/PPM)" if frames else "PNG, JPEG or BMP"
        raise InputError(
            f"{path}: not a {kinds} image (first bytes {data[:8]!r}); convert it to PNG or JPEG."
        )
    if w < 1 or h < 1:
        raise InputError(f"{path}: header gives an empty image ({w} x {h}).")
    return fmt, int(w), int(h)


def check_complete(data: bytes, fmt: str, path: Path) -> None:
    """Raise InputError when the file is cut short or its container is damaged."""
    if fmt == "png":
        _png_size_and_check(data, path, full=True)
    elif fmt == "jpeg":
        _, _, sos = _jpeg_frame(data, path)
        if data.find(b"\xff\xd9", sos) < 0:
            raise InputError(
                f"{path}: truncated JPEG (no end-of-image marker after the image data; "
                f"{len(data)} bytes). The file was cut short, e.g. an interrupted copy."
            )
    elif fmt == "tiff":
        _tiff_check_complete(data, path)
    elif fmt == "pnm":
        _pnm_check_complete(data, path)
    elif fmt == "bmp":
        (declared,) = struct.unpack("<I", data[2:6])
        if declared > len(data):
            raise InputError(
                f"{path}: truncated BMP (header says {declared} bytes, file has {len(data)})."
            )


def read_image(path: str | Path, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> NDArray[np.uint8]:
    """Read a PNG / JPEG / BMP photo as (H, W, 3) uint8 **RGB**, safely.

    Parameters
    ----------
    path : image file
    max_pixels : refuse images with more pixels than this (checked on the header, before
        decoding); ``stemmap segment --max-pixels``.

    Raises
    ------
    InputError
        Missing file, unknown format, too many pixels, truncated or damaged file.
    """
    p = Path(path)
    if max_pixels < 1:
        raise InputError(f"max_pixels must be >= 1, got {max_pixels}.")
    if p.is_dir():
        raise InputError(f"image {p} is a folder; give an image file (PNG, JPEG or BMP).")
    if not p.is_file():
        raise InputError(f"image {p} does not exist.")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read image {p}: {exc}") from exc
    fmt, w, h = image_header(data, p)
    if w * h > max_pixels:
        raise InputError(
            f"{p}: {w} x {h} = {w * h:,} pixels exceeds the limit of {max_pixels:,} "
            f"(decoding would need ~{3 * w * h / 1e9:.1f} GB); downscale the image or raise "
            "--max-pixels."
        )
    check_complete(data, fmt, p)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"{p}: the {fmt.upper()} data could not be decoded (damaged file?).")
    if bgr.shape[:2] not in ((h, w), (w, h)):  # (w, h): EXIF orientation applied
        raise InputError(
            f"{p}: decoded {bgr.shape[1]} x {bgr.shape[0]} pixels but the header says {w} x {h}."
        )
    return np.ascontiguousarray(bgr[..., ::-1])
