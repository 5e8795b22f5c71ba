"""Conversions between ROS messages and the ROS-free types, written once."""

from __future__ import annotations

import array
import math
from typing import Any

from builtin_interfaces.msg import Time as TimeMsg
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import PointCloud2, PointField

from mfp_mapper.core.gridmap import HitGrid
from mfp_mapper.sensing.pointcloud import PackedCloud


def stamp_msg(seconds: float) -> TimeMsg:
    """A builtin_interfaces/Time of ``seconds``."""
    sec = math.floor(seconds)
    return TimeMsg(sec=int(sec), nanosec=min(int(round((seconds - sec) * 1e9)), 999_999_999))


def cloud_msg(packed: PackedCloud, frame_id: str, stamp: Any) -> PointCloud2:
    """A sensor_msgs/PointCloud2 from a ``sensing.pointcloud.PackedCloud``."""
    msg = PointCloud2()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.height = packed.height
    msg.width = packed.width
    msg.fields = [
        PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
        for f in packed.fields
    ]
    msg.is_bigendian = packed.is_bigendian
    msg.point_step = packed.point_step
    msg.row_step = packed.row_step
    msg.data = packed.data
    msg.is_dense = True
    return msg


def grid_msg(
    grid: HitGrid, resolution: float, frame_id: str, stamp: Any, load_time: Any, z: float
) -> OccupancyGrid:
    """A nav_msgs/OccupancyGrid of a projected grid (rows = y, origin at its lower corner)."""
    out = OccupancyGrid()
    out.header.frame_id = frame_id
    out.header.stamp = stamp
    out.info.map_load_time = load_time
    out.info.resolution = float(resolution)
    out.info.width = grid.width
    out.info.height = grid.height
    out.info.origin.position.x = grid.origin[0]
    out.info.origin.position.y = grid.origin[1]
    out.info.origin.position.z = float(z)
    out.info.origin.orientation.w = 1.0
    out.data = array.array("b", grid.data.tobytes())
    return out
