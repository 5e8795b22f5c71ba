"""Writing the simulated bags: a thin layer over the rosbags writers (ROS 2 sqlite3/mcap and
ROS 1), and the velodyne_pointcloud point layout."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.names import BAG_FORMATS
from mfp_mapper.sensing.pointcloud import FieldSpec, pack_records, point_fields
from mfp_mapper.sources.sim_scene import SimulationError

FloatArray = NDArray[np.float64]

VELODYNE_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "ring", "time"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 18],
        "itemsize": 22,
    }
)
VELODYNE_FIELDS = tuple(point_fields(VELODYNE_DTYPE)[0])


def bag_format_for(path: Path, fmt: str | None) -> str:
    """The storage to write: ``fmt`` if given, ``ros1`` for ``*.bag``, else ``mcap``."""
    if fmt is None:
        return "ros1" if path.suffix == ".bag" else "mcap"
    if fmt not in BAG_FORMATS:
        raise SimulationError(f"unknown bag format {fmt!r}: expected one of {BAG_FORMATS}")
    if (fmt == "ros1") != (path.suffix == ".bag"):
        raise SimulationError(
            f"{path}: ROS 1 bags are files named *.bag, ROS 2 bags are directories without "
            f"that suffix (format {fmt})"
        )
    return fmt


class BagSink:
    """A thin layer over the rosbags writers: builds and serialises messages for one format."""

    def __init__(self, path: Path, fmt: str) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ros1 = fmt == "ros1"
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self.typestore = get_typestore(Stores.ROS1_NOETIC)
            self.typestore.register(
                get_types_from_msg(
                    "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
                )
            )
            self.writer: Any = Writer1(path)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2

            self.typestore = get_typestore(Stores.ROS2_JAZZY)
            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.types = self.typestore.types
        self.connections: dict[str, Any] = {}
        self.seq = 0

    def __enter__(self) -> BagSink:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def add(self, topic: str, msgtype: str, latched: bool = False) -> None:
        if self.ros1:
            conn = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore, latching=1 if latched else None
            )
        else:
            qos = [_latched_qos()] if latched else ()
            conn = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore, offered_qos_profiles=qos
            )
        self.connections[topic] = conn

    def write(self, topic: str, stamp: float, msg: Any) -> None:
        conn = self.connections[topic]
        if self.ros1:
            data = self.typestore.serialize_ros1(msg, conn.msgtype)
        else:
            data = self.typestore.serialize_cdr(msg, conn.msgtype)
        self.writer.write(conn, int(round(stamp * 1e9)), data)

    # --- message builders (field sets differ between ROS 1 and ROS 2) ---
    def time(self, stamp: float) -> Any:
        ns = int(round(stamp * 1e9))
        return self.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)

    def header(self, stamp: float, frame: str) -> Any:
        if self.ros1:
            self.seq += 1
            return self.types["std_msgs/msg/Header"](
                seq=self.seq, stamp=self.time(stamp), frame_id=frame
            )
        return self.types["std_msgs/msg/Header"](stamp=self.time(stamp), frame_id=frame)

    def transform_stamped(
        self, stamp: float, parent: str, child: str, xyz: FloatArray, q: FloatArray
    ) -> Any:
        t = self.types
        return t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](*map(float, xyz)),
                rotation=t["geometry_msgs/msg/Quaternion"](*map(float, q)),
            ),
        )

    def tf_message(self, transforms: list[Any]) -> Any:
        return self.types["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def odometry(
        self,
        stamp: float,
        parent: str,
        child: str,
        xyz: FloatArray,
        q: FloatArray,
        linear: float,
        angular: float,
    ) -> Any:
        t = self.types
        vec = t["geometry_msgs/msg/Vector3"]
        cov = np.zeros(36, dtype=np.float64)
        return t["nav_msgs/msg/Odometry"](
            header=self.header(stamp, parent),
            child_frame_id=child,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](*map(float, xyz)),
                    orientation=t["geometry_msgs/msg/Quaternion"](*map(float, q)),
                ),
                covariance=cov,
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=vec(float(linear), 0.0, 0.0), angular=vec(0.0, 0.0, float(angular))
                ),
                covariance=cov.copy(),
            ),
        )

    def pointcloud(
        self,
        stamp: float,
        frame: str,
        records: NDArray[np.void],
        fields: tuple[FieldSpec, ...] | None = None,
    ) -> Any:
        """A sensor_msgs/PointCloud2 holding ``records`` (``pack_records``); ``fields``
        replaces the field list derived from their dtype."""
        t = self.types
        packed = pack_records(records)
        return t["sensor_msgs/msg/PointCloud2"](
            header=self.header(stamp, frame),
            fields=[
                t["sensor_msgs/msg/PointField"](
                    name=f.name, offset=f.offset, datatype=f.datatype, count=f.count
                )
                for f in (packed.fields if fields is None else fields)
            ],
            data=np.frombuffer(packed.data, dtype=np.uint8),
            is_dense=records.ndim == 1,  # organized clouds hold NaN for no-returns
            **packed.layout(),
        )


def _latched_qos() -> Any:
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return Qos(
        QosHistory.KEEP_LAST,
        1,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        zero,
        zero,
        QosLiveliness.AUTOMATIC,
        zero,
        False,
    )
