"""Camera frame folders for visual odometry: stereo pairs or RGB + depth, with intrinsics.

Layout of a frames folder (written by :func:`write_camera_frames`, read by
:func:`read_camera_frames`)::

    FRAMES/
      camera.json          intrinsics (below)
      left/*.png           left images (stereo), or
      rgb/*.png            colour images (RGB-D)
      right/*.png          right images (stereo; rectified, same names as left/)
      depth/*.png|*.npy    depth images (RGB-D; 16-bit PNG scaled by depth_scale, or float .npy m)
      times.txt            optional: one time (s) per frame, in file-name order

``camera.json`` holds either ``fx, fy, cx, cy, width, height`` and ``baseline`` (m, 0 or absent
for RGB-D) and ``depth_scale`` (m per depth unit, default 0.001 for 16-bit PNG, 1 for .npy), or
a ROS ``sensor_msgs/CameraInfo`` as a dict (``K``/``k`` 9 values, ``P``/``p`` 12 values of the
*right* camera, whose ``P[3] = -fx * baseline``, ``width``, ``height``). Optional
``vehicle_from_camera``: the 4x4 pose of the left camera on the vehicle (x forward, y left,
z up), used to turn the camera trajectory into the vehicle's planar path; ``rate_hz`` gives the
frame times when neither ``times.txt`` nor numeric file names (seconds) do.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError
from stemmap.odometry.visual import StereoCalibration, VisualFrame
from stemmap.types import FloatArray
from stemmap.vision.image_io import DEFAULT_MAX_PIXELS

__all__ = ["CameraFrames", "calibration_from_dict", "read_camera_frames", "write_camera_frames"]

_IMG = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")


@dataclass(frozen=True, eq=False)
class CameraFrames:
    """A frames folder opened for reading: calibration, mount and lazily loaded frames.

    Iterating yields :class:`VisualFrame` objects with depth images converted to float metres
    (NaN = no depth), so :attr:`calibration` has ``depth_scale`` 1.
    """

    path: Path
    calibration: StereoCalibration
    vehicle_from_camera: FloatArray | None
    times: FloatArray
    left: tuple[Path, ...]
    right: tuple[Path, ...] | None
    depth: tuple[Path, ...] | None
    depth_scale: float = 0.001

    def __len__(self) -> int:
        return len(self.left)

    def __iter__(self) -> Iterator[VisualFrame]:
        size = (self.calibration.width, self.calibration.height)
        for k, lp in enumerate(self.left):
            left = _read_image(lp, size)
            right = _read_image(self.right[k], size) if self.right is not None else None
            depth = None
            if self.depth is not None:
                dp = self.depth[k]
                # float metres for the odometry: PNG units scaled, .npy already in metres
                scale = 1.0 if dp.suffix == ".npy" else self.depth_scale
                depth = _read_depth(dp, size).astype(np.float64) * scale
                depth[depth <= 0] = np.nan
            yield VisualFrame(float(self.times[k]), left, right, depth)


def calibration_from_dict(d: dict[str, Any], where: str = "camera.json") -> StereoCalibration:
    """:class:`StereoCalibration` from explicit keys or a ROS CameraInfo-like dict."""
    try:
        width, height = int(d["width"]), int(d["height"])
        K = d.get("K", d.get("k"))
        if K is not None:
            k = np.asarray(K, dtype=np.float64).reshape(-1)
            fx, fy, cx, cy = k[0], k[4], k[2], k[5]
        else:
            fx, fy, cx, cy = (float(d[n]) for n in ("fx", "fy", "cx", "cy"))
        baseline = float(d.get("baseline", 0.0))
        P = d.get("P", d.get("p"))
        if "baseline" not in d and P is not None:
            p = np.asarray(P, dtype=np.float64).reshape(-1)
            baseline = -p[3] / p[0] if p[0] else 0.0
        depth_scale = float(d.get("depth_scale", 0.001))
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise InputError(
            f"{where}: needs width, height and fx, fy, cx, cy (or a CameraInfo K); {exc!r}. "
            'Example: {"fx": 160, "fy": 160, "cx": 159.5, "cy": 99.5, "width": 320, '
            '"height": 200, "baseline": 0.12}'
        ) from exc
    if width < 1 or height < 1 or width * height > DEFAULT_MAX_PIXELS:
        raise InputError(
            f"{where}: width x height = {width} x {height}, but a camera frame must have 1 to "
            f"{DEFAULT_MAX_PIXELS:,} pixels (the limit of every image stemmap reads)."
        )
    return StereoCalibration(
        float(fx), float(fy), float(cx), float(cy), width, height, float(baseline), depth_scale
    )


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMG or p.suffix == ".npy")


def _decode(path: Path, size: tuple[int, int]) -> NDArray[Any] | None:
    """Decode an image file, its size checked against camera.json's before decoding.

    The width and height are read from the header first
    (:func:`stemmap.vision.image_io.image_header`: PNG, JPEG, BMP, TIFF, PGM/PPM/PBM/PAM): a
    frame of another size than ``size`` (width, height) is refused before it is decoded (a
    2.6 MB PNG announcing 30000 x 30000 pixels decoded to 5.5 GB first; a 200-byte TIFF or
    a 20-byte PGM announcing 30000 x 30000 made OpenCV allocate 0.9-2.7 GB, its own limit
    being 2^30 pixels), and a PNG, JPEG or BMP cut short is an error (OpenCV decodes half a
    JPEG into grey rows). Any other content (WebP, JPEG 2000, OpenEXR, ... under an image
    name) is refused: OpenCV would decode it without a size check of ours.
    """
    from stemmap.vision.image_io import check_complete, image_header

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc}.") from exc
    fmt, w, h = image_header(data, path, frames=True)
    if (w, h) != size:
        raise InputError(
            f"{path}: image is {w} x {h}, camera.json says {size[0]} x {size[1]} (every "
            "frame must have the calibrated size)."
        )
    check_complete(data, fmt, path)
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def _read_image(path: Path, size: tuple[int, int]) -> NDArray[np.uint8]:
    img = _decode(path, size)
    if img is None:
        raise InputError(f"{path}: not a readable image.")
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)
    return np.asarray(img)


def _read_depth(path: Path, size: tuple[int, int]) -> NDArray[np.generic]:
    if path.suffix == ".npy":
        try:  # memory-mapped: the shape is checked before a byte is read
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise InputError(f"{path}: not a readable .npy depth image ({exc}).") from exc
        if arr.shape != (size[1], size[0]):
            raise InputError(
                f"{path}: depth array has shape {arr.shape}, camera.json says "
                f"{size[1]} x {size[0]} (rows x columns)."
            )
        return np.array(arr)
    img = _decode(path, size)
    if img is None or img.ndim != 2:
        raise InputError(f"{path}: not a single-channel depth image.")
    return np.asarray(img)


def read_camera_frames(folder: str | Path) -> CameraFrames:
    """Open a frames folder (layout in the module docstring).

    Raises
    ------
    InputError
        Naming the missing file or folder, or the mismatched image counts.
    """
    root = Path(folder)
    cfg_path = root / "camera.json"
    if not cfg_path.is_file():
        raise InputError(
            f"{root}: no camera.json (intrinsics). Write fx, fy, cx, cy, width, height and, for "
            "stereo, baseline (m) into it."
        )
    try:
        d = json.loads(cfg_path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{cfg_path}: not valid JSON ({exc}).") from exc
    except RecursionError:  # json's C scanner recurses per nested array or object
        raise InputError(f"{cfg_path}: nests arrays or objects too deeply.") from None
    cal = calibration_from_dict(d, str(cfg_path))
    if (root / "left").is_dir():
        left = _images(root / "left")
        if not (root / "right").is_dir():
            raise InputError(f"{root}: left/ without right/ (stereo needs both).")
        right: list[Path] | None = _images(root / "right")
        depth = None
        if not cal.is_stereo:
            raise InputError(f"{cfg_path}: stereo folders need a baseline > 0 (metres).")
    elif (root / "rgb").is_dir() and (root / "depth").is_dir():
        left, right = _images(root / "rgb"), None
        depth = _images(root / "depth")
        if cal.is_stereo:
            cal = StereoCalibration(
                cal.fx, cal.fy, cal.cx, cal.cy, cal.width, cal.height, 0.0, cal.depth_scale
            )
    else:
        raise InputError(f"{root}: expected left/ + right/ (stereo) or rgb/ + depth/ (RGB-D).")
    if not left:
        raise InputError(f"{root}: no images.")
    for name, other in (("right", right), ("depth", depth)):
        if other is not None and len(other) != len(left):
            raise InputError(f"{root}: {len(left)} left/rgb images but {len(other)} {name} files.")
    times = _times(root, left, d)
    mount = d.get("vehicle_from_camera")
    T = None if mount is None else np.asarray(mount, dtype=np.float64).reshape(4, 4)
    depth_scale = cal.depth_scale
    # frames carry depth in metres (see CameraFrames.__iter__)
    cal = StereoCalibration(cal.fx, cal.fy, cal.cx, cal.cy, cal.width, cal.height, cal.baseline)
    return CameraFrames(
        root,
        cal,
        T,
        times,
        tuple(left),
        None if right is None else tuple(right),
        None if depth is None else tuple(depth),
        depth_scale,
    )


def _times(root: Path, files: Sequence[Path], d: dict[str, Any]) -> FloatArray:
    tfile = root / "times.txt"
    if tfile.is_file():
        t = np.loadtxt(tfile, dtype=np.float64, ndmin=1)
        if t.shape[0] != len(files):
            raise InputError(f"{tfile}: {t.shape[0]} times for {len(files)} frames.")
    else:
        try:
            t = np.array([float(p.stem) for p in files])
        except ValueError:
            rate = float(d.get("rate_hz", math.nan))
            if not rate > 0:
                raise InputError(
                    f"{root}: no frame times. Add times.txt, name the images by time in seconds, "
                    "or set rate_hz in camera.json."
                ) from None
            t = np.arange(len(files)) / rate
    if t.shape[0] > 1 and np.any(np.diff(t) <= 0):
        raise InputError(f"{root}: frame times must increase (file-name order).")
    return np.asarray(t, dtype=np.float64)


def write_camera_frames(
    folder: str | Path,
    frames: Sequence[VisualFrame],
    calibration: StereoCalibration,
    *,
    vehicle_from_camera: FloatArray | None = None,
    depth_scale: float = 0.001,
) -> Path:
    """Write frames (stereo if they carry right images, else RGB + 16-bit depth PNG)."""
    root = Path(folder)
    stereo = frames[0].right is not None
    sub = ("left", "right") if stereo else ("rgb", "depth")
    for s in sub:
        (root / s).mkdir(parents=True, exist_ok=True)
    for k, f in enumerate(frames):
        name = f"{k:06d}.png"
        for s, img in zip(sub, (f.left, f.right if stereo else f.depth), strict=True):
            if img is None:
                raise InputError(f"frame {k}: no {s} image.")
            a = np.asarray(img)
            if s == "depth":
                a = np.where(np.isfinite(a), np.rint(a / depth_scale), 0).clip(0, 65535)
                a = a.astype(np.uint16)
            elif a.ndim == 3:
                a = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(root / s / name), a)
    np.savetxt(root / "times.txt", [f.time for f in frames], fmt="%.9f")
    cfg: dict[str, Any] = {
        "fx": calibration.fx,
        "fy": calibration.fy,
        "cx": calibration.cx,
        "cy": calibration.cy,
        "width": calibration.width,
        "height": calibration.height,
        "baseline": calibration.baseline if stereo else 0.0,
        "depth_scale": depth_scale,
    }
    if vehicle_from_camera is not None:
        cfg["vehicle_from_camera"] = np.asarray(vehicle_from_camera).tolist()
    (root / "camera.json").write_text(json.dumps(cfg, indent=2))
    return root
