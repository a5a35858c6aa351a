"""Bag-writing helpers for the io tests and benchmarks/io_readers.py: real ROS1/ROS2 bags
written with rosbags' own writers (tests import it through tests/conftest.py's sys.path)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore


class BagFactory:
    """Builds ROS messages and writes them to ROS1 (``ros=1``) or ROS2 (``ros=2``) bags."""

    def __init__(
        self, ros: int, storage: str = "sqlite3", chunk_bytes: int = 0, compression: str = ""
    ) -> None:
        self.ros = ros
        self.storage = storage
        self.chunk_bytes = chunk_bytes  # ROS1: chunk size threshold (0 = rosbags' 1 MiB)
        self.compression = compression  # ROS1: "", "bz2" or "lz4"
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)

    def t(self, name: str) -> Any:
        return self.ts.types[name]

    def header(self, time: float, frame: str) -> Any:
        sec = int(np.floor(time))
        stamp = self.t("builtin_interfaces/msg/Time")(sec=sec, nanosec=round((time - sec) * 1e9))
        if self.ros == 1:
            return self.t("std_msgs/msg/Header")(seq=0, stamp=stamp, frame_id=frame)
        return self.t("std_msgs/msg/Header")(stamp=stamp, frame_id=frame)

    def laserscan(
        self,
        time: float,
        ranges: Sequence[float],
        angle_min: float = -1.0,
        angle_increment: float = 0.01,
        range_min: float = 0.1,
        range_max: float = 30.0,
        frame: str = "laser",
        intensities: Sequence[float] | None = None,
    ) -> Any:
        r = np.asarray(ranges, dtype=np.float32)
        return self.t("sensor_msgs/msg/LaserScan")(
            header=self.header(time, frame),
            angle_min=angle_min,
            angle_max=angle_min + angle_increment * (len(r) - 1),
            angle_increment=angle_increment,
            time_increment=0.0,
            scan_time=0.025,
            range_min=range_min,
            range_max=range_max,
            ranges=r,
            intensities=np.asarray(intensities if intensities is not None else [], np.float32),
        )

    def _vec3(self, x: float, y: float, z: float) -> Any:
        return self.t("geometry_msgs/msg/Vector3")(x=x, y=y, z=z)

    def _quat(self, q: Sequence[float]) -> Any:
        return self.t("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3])

    def odometry(
        self,
        time: float,
        xyz: Sequence[float],
        quat: Sequence[float],
        lin: Sequence[float],
        wz: float,
        cov: np.ndarray | None = None,
    ) -> Any:
        pose = self.t("geometry_msgs/msg/Pose")(
            position=self.t("geometry_msgs/msg/Point")(x=xyz[0], y=xyz[1], z=xyz[2]),
            orientation=self._quat(quat),
        )
        twist = self.t("geometry_msgs/msg/Twist")(
            linear=self._vec3(*lin), angular=self._vec3(0.0, 0.0, wz)
        )
        c = np.zeros(36) if cov is None else np.asarray(cov, dtype=np.float64).reshape(36)
        return self.t("nav_msgs/msg/Odometry")(
            header=self.header(time, "odom"),
            child_frame_id="base_link",
            pose=self.t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=c),
            twist=self.t("geometry_msgs/msg/TwistWithCovariance")(
                twist=twist, covariance=np.zeros(36)
            ),
        )

    def imu(
        self,
        time: float,
        quat: Sequence[float],
        acc: Sequence[float],
        gyro: Sequence[float] = (0.0, 0.0, 0.0),
        has_orientation: bool = True,
    ) -> Any:
        ocov = np.zeros(9)
        if not has_orientation:
            ocov[0] = -1.0
        return self.t("sensor_msgs/msg/Imu")(
            header=self.header(time, "imu"),
            orientation=self._quat(quat),
            orientation_covariance=ocov,
            angular_velocity=self._vec3(*gyro),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=self._vec3(*acc),
            linear_acceleration_covariance=np.zeros(9),
        )

    def navsatfix(
        self, time: float, lat: float, lon: float, alt: float, status: int = 0, var: float = 1.0
    ) -> Any:
        st = self.t("sensor_msgs/msg/NavSatStatus")(status=status, service=1)
        return self.t("sensor_msgs/msg/NavSatFix")(
            header=self.header(time, "gps"),
            status=st,
            latitude=lat,
            longitude=lon,
            altitude=alt,
            position_covariance=np.diag([var, var, 4 * var]).reshape(9),
            position_covariance_type=2,
        )

    def pointcloud2(
        self,
        time: float,
        data: bytes,
        fields: Sequence[tuple[str, int, int, int]],
        point_step: int,
        width: int,
        height: int = 1,
        row_step: int | None = None,
        is_bigendian: bool = False,
        frame: str = "velodyne",
    ) -> Any:
        pf = self.t("sensor_msgs/msg/PointField")
        return self.t("sensor_msgs/msg/PointCloud2")(
            header=self.header(time, frame),
            height=height,
            width=width,
            fields=[pf(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
            is_bigendian=is_bigendian,
            point_step=point_step,
            row_step=row_step if row_step is not None else width * point_step,
            data=np.frombuffer(data, dtype=np.uint8).copy(),
            is_dense=False,
        )

    def image(self, time: float, a: np.ndarray, encoding: str, frame: str = "cam") -> Any:
        """A ``sensor_msgs/Image`` holding array ``a`` ((H, W) or (H, W, C)), rows unpadded."""
        a = np.ascontiguousarray(a)
        step = a.shape[1] * (a.shape[2] if a.ndim == 3 else 1) * a.dtype.itemsize
        return self.t("sensor_msgs/msg/Image")(
            header=self.header(time, frame),
            height=a.shape[0],
            width=a.shape[1],
            encoding=encoding,
            is_bigendian=0,
            step=step,
            data=a.view(np.uint8).ravel(),
        )

    def camera_info(
        self,
        time: float,
        k: Sequence[float],
        width: int,
        height: int,
        tx: float = 0.0,
        frame: str = "cam",
    ) -> Any:
        """A ``sensor_msgs/CameraInfo`` with intrinsics ``k`` (9 values, row-major) and the
        projection ``P = [K | (tx, 0, 0)]`` (a right camera's ``tx = -fx * baseline``)."""
        roi = self.t("sensor_msgs/msg/RegionOfInterest")(
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        kk = np.asarray(k, dtype=np.float64)
        p = [kk[0], kk[1], kk[2], tx, kk[3], kk[4], kk[5], 0.0, kk[6], kk[7], kk[8], 0.0]
        mats = {"d": np.zeros(5), "k": kk, "r": np.eye(3).ravel(), "p": np.asarray(p)}
        if self.ros == 1:  # ROS1 names the matrices in capitals
            mats = {m.upper(): v for m, v in mats.items()}
        return self.t("sensor_msgs/msg/CameraInfo")(
            header=self.header(time, frame),
            height=height,
            width=width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **mats,
        )

    def serialize(self, msg: Any) -> bytes:
        if self.ros == 1:
            return bytes(self.ts.serialize_ros1(msg, msg.__msgtype__))
        return bytes(self.ts.serialize_cdr(msg, msg.__msgtype__))

    def write(
        self,
        path: Path,
        messages: Sequence[tuple[str, Any]],
        raw: Sequence[tuple[str, str, bytes]] = (),
    ) -> Path:
        """Write ``(topic, msg)`` pairs (time = header stamp) and optional raw
        ``(topic, msgtype, bytes)`` payloads (e.g. corrupt ones) after them."""
        if self.ros == 1:
            path = path.with_suffix(".bag")
            writer: Any = Writer1(path)
            if self.chunk_bytes:
                writer.chunk_threshold = self.chunk_bytes
            if self.compression:
                writer.set_compression(Writer1.CompressionFormat[self.compression.upper()])
        else:
            plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(path, version=9, storage_plugin=plugin)
        conns: dict[tuple[str, str], Any] = {}
        with writer:
            t_ns = 1
            for topic, msg in messages:
                key = (topic, msg.__msgtype__)
                if key not in conns:
                    conns[key] = writer.add_connection(topic, msg.__msgtype__, typestore=self.ts)
                st = msg.header.stamp
                t_ns = max(1, st.sec * 1_000_000_000 + st.nanosec)
                writer.write(conns[key], t_ns, self.serialize(msg))
            for topic, msgtype, payload in raw:
                key = (topic, msgtype)
                if key not in conns:
                    conns[key] = writer.add_connection(topic, msgtype, typestore=self.ts)
                t_ns += 1
                writer.write(conns[key], t_ns, payload)
        return path
