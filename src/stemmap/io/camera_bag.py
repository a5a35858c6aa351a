"""Camera frames from ROS bags: ``sensor_msgs/Image`` (+ ``sensor_msgs/CameraInfo``) topics.

For :mod:`stemmap.odometry.visual`: a rectified stereo pair (left + right image topics, the
baseline from the right camera's CameraInfo projection matrix, ``P[3] = -fx * baseline`` as in
ROS ``stereo_image_proc``) or an RGB-D camera (colour + depth image topics; depth ``16UC1`` in
millimetres or ``32FC1`` in metres). Bags are opened with :func:`stemmap.io.rosbag.open_bag`
(ROS1 ``.bag``, ROS2 folders, ``.db3``, ``.mcap``).

Pairing: messages are read in bag order; a left (colour) image is paired with the right (depth)
image whose header stamp is within ``max_dt`` seconds (default 0.02 s: a hardware-synchronised
stereo camera such as the ZED 2 stamps both images identically). Unpaired images are dropped
and counted in the log.

Damage: a bag that opens but is damaged further in (a corrupt or truncated chunk, a message that
cannot be decoded) raises an :class:`~stemmap.errors.InputError` naming the bag, the topics, the
message (counted over both image topics) and the bag time where it broke, from the same
message reader as :mod:`stemmap.io.rosbag` (``stemmap.io._bag._decoded``). The scan and
odometry logs there keep what precedes the damage and report the rest as skipped; the camera
reader stops instead, as it does on an image it cannot decode.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError
from stemmap.io._bag import _decoded, _Message
from stemmap.io.rosbag import open_bag
from stemmap.odometry.visual import StereoCalibration, VisualFrame

__all__ = ["CameraBag", "decode_image", "read_camera_bag"]

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

_CHANNELS = {
    "mono8": (1, np.uint8),
    "8uc1": (1, np.uint8),
    "rgb8": (3, np.uint8),
    "bgr8": (3, np.uint8),
    "8uc3": (3, np.uint8),
    "rgba8": (4, np.uint8),
    "bgra8": (4, np.uint8),
    "mono16": (1, np.uint16),
    "16uc1": (1, np.uint16),
    "32fc1": (1, np.float32),
}


def _norm(msgtype: str) -> str:
    return msgtype.replace("/msg/", "/")


def decode_image(msg: Any, where: str = "image") -> NDArray[np.generic]:
    """(H, W) or (H, W, 3) array of a ``sensor_msgs/Image`` (BGR(A) reordered to RGB).

    Raises
    ------
    InputError
        For an unsupported encoding or a data buffer shorter than ``height * step``.
    """
    enc = str(msg.encoding).lower()
    if enc not in _CHANNELS:
        raise InputError(
            f"{where}: image encoding {msg.encoding!r} is not supported; use one of "
            f"{sorted(_CHANNELS)}."
        )
    ch, dt = _CHANNELS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.asarray(msg.data, dtype=np.uint8)
    if buf.size < h * step or step < w * ch * np.dtype(dt).itemsize:
        raise InputError(f"{where}: {buf.size} bytes for a {w} x {h} {enc} image (step {step}).")
    rows = buf[: h * step].reshape(h, step)[:, : w * ch * np.dtype(dt).itemsize]
    src_dt = np.dtype(dt).newbyteorder(">" if msg.is_bigendian else "<")
    a = np.ascontiguousarray(rows).view(src_dt).reshape(h, w, ch)
    a = a.astype(np.dtype(dt).newbyteorder("="))
    if enc.startswith("bgr"):
        a = a[..., [2, 1, 0]]
    elif enc.startswith("rgba"):
        a = a[..., :3]
    return a[..., 0] if ch == 1 else a


def _stamp(msg: Any, fallback: float) -> float:
    try:
        s = msg.header.stamp
        t = float(s.sec) + 1e-9 * float(s.nanosec)
    except AttributeError:
        return fallback
    return t if t > 0 else fallback


def _image_topics(reader: Any) -> list[str]:
    return sorted({c.topic for c in reader.connections if _norm(c.msgtype) == _norm(IMAGE)})


def _good(path: Path, m: _Message, last_time: float) -> Any:
    """``m.msg``; a message that could not be read (damage met mid-read, a message that
    cannot be decoded: :func:`stemmap.io._bag._decoded`) raises an InputError naming the bag,
    the topic(s), the message and the bag time reached."""
    if m.msg is None:
        if math.isfinite(m.bag_time):
            at = f" (bag time {m.bag_time:.3f} s)"
        elif math.isfinite(last_time):
            at = f" (the last message read was at bag time {last_time:.3f} s)"
        else:
            at = ""
        raise InputError(f"ROS bag {str(path)!r}: {m.error}{at}.")
    return m.msg


def _first_info(reader: Any, path: Path, topic: str) -> Any:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        raise InputError(f"no topic {topic!r} in the bag (CameraInfo expected).")
    for m in _decoded(reader, path, conns, CAMERA_INFO, f"topic {topic}"):
        return _good(path, m, math.nan)
    raise InputError(f"topic {topic!r} has no messages.")


@dataclass(frozen=True, eq=False)
class CameraBag:
    """A bag's camera topics opened for visual odometry; iterate for paired frames."""

    path: Path
    calibration: StereoCalibration
    left_topic: str
    right_topic: str | None
    depth_topic: str | None
    max_dt: float = 0.02
    vehicle_from_camera: NDArray[np.float64] | None = None

    def __iter__(self) -> Iterator[VisualFrame]:
        second = self.right_topic or self.depth_topic
        assert second is not None
        depth_scale = 1.0
        with open_bag(self.path) as reader:
            conns = [c for c in reader.connections if c.topic in (self.left_topic, second)]
            pending: dict[str, tuple[float, NDArray[np.generic]]] = {}
            dropped = 0
            last = -np.inf
            bag_time = math.nan
            what = f"topics {self.left_topic} and {second}"
            for m in _decoded(reader, self.path, conns, IMAGE, what):
                msg = _good(self.path, m, bag_time)
                bag_time = m.bag_time
                img = decode_image(msg, f"{self.path}:{m.topic} (message {m.seq} of {what})")
                if m.topic == self.depth_topic:
                    depth_scale = 0.001 if img.dtype == np.uint16 else 1.0
                t = _stamp(msg, m.bag_time)
                if m.topic in pending:
                    dropped += 1
                pending[m.topic] = (t, img)
                if len(pending) == 2:
                    (tl, left), (tr, other) = pending[self.left_topic], pending[second]
                    if abs(tl - tr) <= self.max_dt:
                        pending.clear()
                        if tl <= last:
                            dropped += 1
                            continue
                        last = tl
                        if self.depth_topic is not None:
                            d = other.astype(np.float64) * depth_scale
                            d[d <= 0] = np.nan
                            yield VisualFrame(tl, left, depth=d)
                        else:
                            yield VisualFrame(tl, left, other)
                    else:  # keep the newer one, drop the older
                        older = self.left_topic if tl < tr else second
                        del pending[older]
                        dropped += 1
            if dropped:
                log.info("%s: %d unpaired camera images dropped", self.path, dropped)


def read_camera_bag(
    path: str | Path,
    *,
    left_topic: str | None = None,
    right_topic: str | None = None,
    depth_topic: str | None = None,
    info_topic: str | None = None,
    right_info_topic: str | None = None,
    baseline: float | None = None,
    max_dt: float = 0.02,
) -> CameraBag:
    """Open the camera topics of a bag (stereo: left + right; RGB-D: left (colour) + depth).

    Topics left as None are guessed when unambiguous: the image topics whose names contain
    ``left`` / ``right`` (or ``depth``), and the CameraInfo topics next to them
    (``.../camera_info`` in the same namespace). The baseline comes from the right CameraInfo's
    ``P`` (or ``baseline``, metres, when the bag has no right CameraInfo).

    Raises
    ------
    InputError
        Naming the available image / CameraInfo topics when a topic cannot be chosen.
    """
    p = Path(path)
    with open_bag(p) as reader:
        images = _image_topics(reader)
        infos = sorted(
            {c.topic for c in reader.connections if _norm(c.msgtype) == _norm(CAMERA_INFO)}
        )

        def guess(key: str) -> str | None:
            hits = [t for t in images if key in t.lower()]
            return hits[0] if len(hits) == 1 else None

        left_topic = left_topic or guess("left") or guess("rgb") or guess("color")
        if depth_topic is None and right_topic is None:
            right_topic = guess("right")
            if right_topic is None:
                depth_topic = guess("depth")
        if left_topic is None or (right_topic is None and depth_topic is None):
            raise InputError(
                f"{p}: cannot tell the camera topics apart; pass --left-topic and --right-topic "
                f"(or --depth-topic). Image topics: {images or 'none'}."
            )

        def info_for(img_topic: str) -> str | None:
            ns = img_topic.rsplit("/", 1)[0]
            hits = [t for t in infos if t.rsplit("/", 1)[0] == ns]
            if not hits:  # e.g. /cam/left/image_rect and /cam/left/camera_info one level up
                hits = [t for t in infos if t.startswith(ns.rsplit("/", 1)[0] + "/")]
            return hits[0] if len(hits) == 1 else None

        info_topic = info_topic or info_for(left_topic)
        if info_topic is None:
            raise InputError(
                f"{p}: no CameraInfo for {left_topic}; pass --info-topic. CameraInfo topics: "
                f"{infos or 'none'}."
            )
        info = _first_info(reader, p, info_topic)
        k = np.asarray(info.k if hasattr(info, "k") else info.K, dtype=np.float64).reshape(-1)
        b = 0.0
        if right_topic is not None:
            right_info_topic = right_info_topic or info_for(right_topic)
            if right_info_topic is not None and right_info_topic != info_topic:
                rinfo = _first_info(reader, p, right_info_topic)
                pr = np.asarray(rinfo.p if hasattr(rinfo, "p") else rinfo.P, dtype=np.float64)
                b = -pr[3] / pr[0] if pr[0] else 0.0
            if baseline is not None:
                b = baseline
            if not b > 0:
                raise InputError(
                    f"{p}: no stereo baseline: the right CameraInfo's P[3] is 0 or missing; "
                    "pass --baseline (metres)."
                )
    cal = StereoCalibration(
        float(k[0]), float(k[4]), float(k[2]), float(k[5]), int(info.width), int(info.height), b
    )
    return CameraBag(p, cal, left_topic, right_topic, depth_topic, max_dt)
